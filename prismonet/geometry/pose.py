"""Object pose from the paper's extrinsics encoding ``z_ext = (p, z_cos, z_sin, s)``.

The pose maps object coordinates to world coordinates as a similarity,
``x_world = s R x_obj + p``, i.e. ``T_world_obj = [[s R, p], [0, 1]]``. The paper writes the
inverse, ``T_o^w``. ``R`` rotates by ``theta = atan2(z_sin, z_cos)`` about the world z axis
(objects stand upright), or, for the paper's full-6-DoF variant, about a given unit axis
``z_rot`` (an axis-angle rotation whose angle is carried by ``(z_cos, z_sin)``).

Because ``s`` is uniform, signed distances scale with it: ``sdf_world(x) = s * sdf_obj(x_obj)``.
"""

from __future__ import annotations

import math

import torch

EPS_YAW_NORM = 1e-6
"""Added (squared) to ``z_cos^2 + z_sin^2`` before the square root that normalises the pair.

Without it a regressed pair near ``(0, 0)`` gives a 0/0 and an unbounded gradient; with it the
normalised pair stays finite and its gradient is bounded by ``1 / EPS_YAW_NORM``.
"""

EPS_AXIS_NORM = 1e-9
"""Guards the normalisation of a rotation axis of (near) zero length. Added squared under the
square root, so a unit axis stays unit to float64 precision (a ``+ eps`` outside would not)."""


def yaw_to_cos_sin(yaw: torch.Tensor) -> torch.Tensor:
    """``(...,)`` angles to ``(..., 2)`` pairs ``(cos, sin)``."""
    return torch.stack([torch.cos(yaw), torch.sin(yaw)], dim=-1)


def rotation_from_axis_cos_sin(cos_sin: torch.Tensor, axis: torch.Tensor | None = None) -> torch.Tensor:
    """Rotation matrices ``(..., 3, 3)`` by angle ``atan2(sin, cos)`` about ``axis`` (Rodrigues).

    Args:
        cos_sin: ``(..., 2)``; need not be unit length (it is normalised, see ``EPS_YAW_NORM``).
        axis: ``(..., 3)`` rotation axis, normalised here; ``None`` means the world z axis.
    """
    if cos_sin.shape[-1] != 2:
        raise ValueError(f"cos_sin: expected shape (..., 2), got {tuple(cos_sin.shape)}")
    norm = torch.sqrt((cos_sin * cos_sin).sum(-1, keepdim=True) + EPS_YAW_NORM**2)
    c, s = (cos_sin / norm).unbind(-1)
    c, s = c[..., None, None], s[..., None, None]
    if axis is None:
        axis = torch.zeros(*cos_sin.shape[:-1], 3, dtype=cos_sin.dtype, device=cos_sin.device)
        axis[..., 2] = 1.0
    elif axis.shape != (*cos_sin.shape[:-1], 3):
        raise ValueError(f"axis: expected shape {(*cos_sin.shape[:-1], 3)}, got {tuple(axis.shape)}")
    else:
        axis = axis / torch.sqrt((axis * axis).sum(-1, keepdim=True) + EPS_AXIS_NORM**2)
    kx, ky, kz = axis.unbind(-1)
    zero = torch.zeros_like(kx)
    cross = torch.stack(
        [torch.stack([zero, -kz, ky], -1), torch.stack([kz, zero, -kx], -1), torch.stack([-ky, kx, zero], -1)], -2
    )
    eye = torch.eye(3, dtype=cos_sin.dtype, device=cos_sin.device)
    outer = axis[..., :, None] * axis[..., None, :]
    return c * eye + s * cross + (1.0 - c) * outer


def T_world_obj_from_extrinsics(
    position: torch.Tensor,
    cos_sin: torch.Tensor,
    scale: torch.Tensor,
    axis: torch.Tensor | None = None,
) -> torch.Tensor:
    """Object-to-world similarity ``(..., 4, 4)`` from extrinsics.

    Args:
        position: ``(..., 3)`` object origin in the world, ``p``.
        cos_sin: ``(..., 2)`` the angle as ``(z_cos, z_sin)``.
        scale: ``(...,)`` positive uniform scale ``s``.
        axis: optional ``(..., 3)`` rotation axis (full-6-DoF variant); default world z.

    Example:
        >>> T = T_world_obj_from_extrinsics(torch.tensor([1.0, 2.0, 0.5]),
        ...                                 torch.tensor([0.0, 1.0]), torch.tensor(2.0))
        >>> T @ torch.tensor([1.0, 0.0, 0.0, 1.0])  # x axis turns to y, scaled by 2
        tensor([1.0000, 4.0000, 0.5000, 1.0000])
    """
    if position.shape[-1] != 3:
        raise ValueError(f"position: expected shape (..., 3), got {tuple(position.shape)}")
    if scale.shape != position.shape[:-1]:
        raise ValueError(f"scale: expected shape {tuple(position.shape[:-1])}, got {tuple(scale.shape)}")
    R = rotation_from_axis_cos_sin(cos_sin, axis)
    T = torch.zeros(*position.shape[:-1], 4, 4, dtype=position.dtype, device=position.device)
    T[..., :3, :3] = scale[..., None, None] * R
    T[..., :3, 3] = position
    T[..., 3, 3] = 1.0
    return T


def random_rotation_axis_angle(rng) -> tuple[list[float], float]:
    """A uniformly random 3-D rotation as (unit axis, angle in [0, pi]); ``rng``: numpy Generator."""
    q = rng.normal(size=4)
    q /= math.sqrt(float((q * q).sum()))
    if q[0] < 0:
        q = -q
    angle = 2.0 * math.acos(min(1.0, float(q[0])))
    v = q[1:]
    n = math.sqrt(float((v * v).sum()))
    axis = [0.0, 0.0, 1.0] if n < 1e-12 else [float(a / n) for a in v]
    return axis, angle
