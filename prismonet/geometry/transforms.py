"""Homogeneous 4x4 transforms between frames.

A transform ``T_a_b`` of shape ``(..., 4, 4)`` maps points in frame ``b`` to frame ``a``:
``x_a = T_a_b @ x_b``. Object poses are similarities (rotation times a positive scale), so the
inverse here handles a uniform scale, not only rigid motions.
"""

from __future__ import annotations

import torch
from kornia.geometry.linalg import transform_points as _kornia_transform_points


def _check_4x4(T: torch.Tensor, name: str) -> None:
    if not isinstance(T, torch.Tensor):
        raise TypeError(f"{name}: expected a torch.Tensor, got {type(T).__name__}")
    if T.shape[-2:] != (4, 4):
        raise ValueError(f"{name}: expected shape (..., 4, 4), got {tuple(T.shape)}")


def transform_points(T_a_b: torch.Tensor, x_b: torch.Tensor) -> torch.Tensor:
    """Apply ``T_a_b`` to points.

    Args:
        T_a_b: ``(B, 4, 4)`` or ``(4, 4)``.
        x_b: ``(B, N, 3)`` points in frame ``b`` (or ``(N, 3)`` with a ``(4, 4)`` transform).

    Returns:
        ``x_a`` with the shape of ``x_b``.

    Example:
        >>> T = torch.eye(4); T[:3, 3] = torch.tensor([1.0, 2.0, 3.0])
        >>> transform_points(T, torch.zeros(1, 3))
        tensor([[1., 2., 3.]])
    """
    _check_4x4(T_a_b, "T_a_b")
    if x_b.shape[-1] != 3:
        raise ValueError(f"x_b: expected shape (..., 3), got {tuple(x_b.shape)}")
    if T_a_b.dim() == 2 and x_b.dim() == 2:
        return _kornia_transform_points(T_a_b[None], x_b[None])[0]
    return _kornia_transform_points(T_a_b, x_b)


def compose(T_a_b: torch.Tensor, T_b_c: torch.Tensor) -> torch.Tensor:
    """``T_a_c = T_a_b @ T_b_c``; frames chain left to right."""
    _check_4x4(T_a_b, "T_a_b")
    _check_4x4(T_b_c, "T_b_c")
    return T_a_b @ T_b_c


def invert_similarity(T_a_b: torch.Tensor) -> torch.Tensor:
    """Invert ``[s R | t]`` with ``R`` a rotation and ``s > 0`` a uniform scale.

    ``T_b_a = [R^T / s | -R^T t / s]``. Exact (no general matrix inverse), differentiable.
    """
    _check_4x4(T_a_b, "T_a_b")
    A = T_a_b[..., :3, :3]  # s R
    t = T_a_b[..., :3, 3:]
    # s^2 = squared norm of any column of sR; average the three for symmetry.
    s2 = (A * A).sum(dim=-2).mean(dim=-1)[..., None, None]
    A_inv = A.transpose(-1, -2) / s2
    out = torch.zeros_like(T_a_b)
    out[..., :3, :3] = A_inv
    out[..., :3, 3:] = -A_inv @ t
    out[..., 3, 3] = 1.0
    return out
