"""Rays for each object: projected-box culling and exact ray-box (slab) intervals.

Every shape lives in the object-frame cube ``[-BOX_HALF, BOX_HALF]^3`` (``prismonet.shapes``),
so each object's pixels are those inside the projection of its posed cube, and each ray's
samples need only cover the segment of the ray inside the cube. A prior whose shapes fill less of
it (cars are long and flat) gives a tighter box (``ShapePrior.bounds``): fewer rays, and the same
samples spread over a shorter segment.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from prismonet.shapes.normalize import PADDED_CUBE

NEAR_Z = 1e-2
"""Samples start at least this far in front of the camera (camera z): a box that reaches behind
the camera is cut at this plane, so no sample is ever behind it or at z = 0."""
EPS_RAY_DIR = 1e-12
"""Ray direction components below this magnitude are replaced by +-EPS_RAY_DIR in the slab test,
so that an axis-parallel ray gives +-inf slab bounds instead of 0/0 = NaN."""

Box = tuple[tuple[float, float, float], tuple[float, float, float]]
"""An object-frame axis-aligned box ``(lo, hi)``."""
FULL_BOX: Box = PADDED_CUBE


def _corners(box: Box, dtype, device=None) -> torch.Tensor:
    lo, hi = box
    return torch.tensor([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])], dtype=dtype, device=device)


@dataclass
class ObjectRays:
    """Rays of all objects of a batch, flattened (R rays). Everything here is detached.

    Attributes:
        obj: ``(R,)`` object index into the flattened ``B*K`` slots.
        pix: ``(R,)`` pixel index into ``H*W``.
        t_near, t_far: ``(R,)`` the ray's depth interval inside the object's box (camera z).
        d_cam: ``(R, 3)`` ray direction in the camera frame, z = 1.
    """

    obj: torch.Tensor
    pix: torch.Tensor
    t_near: torch.Tensor
    t_far: torch.Tensor
    d_cam: torch.Tensor

    def __len__(self) -> int:
        return self.obj.shape[0]


def projected_box_rects(T_cam_obj: torch.Tensor, K: torch.Tensor, height: int, width: int, box: Box = FULL_BOX) -> torch.Tensor:
    """Pixel rectangles ``(N, 4)`` as ``(u0, v0, u1, v1)`` inclusive, covering each posed box.

    ``T_cam_obj``: ``(N, 4, 4)``; ``K``: ``(N, 3, 3)``. A box that reaches behind ``NEAR_Z`` gets
    the whole image (conservative). Off-screen boxes get an empty rectangle (``u1 < u0``).
    """
    c = _corners(box, T_cam_obj.dtype, T_cam_obj.device)
    x = torch.einsum("nij,cj->nci", T_cam_obj[:, :3, :3], c) + T_cam_obj[:, None, :3, 3]  # (N, 8, 3)
    z = x[..., 2]
    behind = (z < NEAR_Z).any(dim=1)
    zs = z.clamp_min(NEAR_Z)
    u = K[:, None, 0, 0] * x[..., 0] / zs + K[:, None, 0, 2]
    v = K[:, None, 1, 1] * x[..., 1] / zs + K[:, None, 1, 2]
    # pixel centres at integers: a pixel is inside if its centre is within the projected hull's bbox
    u0 = torch.ceil(u.min(1).values).clamp(0, width)
    u1 = torch.floor(u.max(1).values).clamp(-1, width - 1)
    v0 = torch.ceil(v.min(1).values).clamp(0, height)
    v1 = torch.floor(v.max(1).values).clamp(-1, height - 1)
    full = torch.tensor([0, 0, width - 1, height - 1], dtype=u0.dtype, device=u0.device)
    rects = torch.stack([u0, v0, u1, v1], dim=1)
    rects = torch.where(behind[:, None], full, rects)
    all_behind = (z < NEAR_Z).all(dim=1)
    rects[all_behind] = torch.tensor([0, 0, -1, -1], dtype=u0.dtype, device=u0.device)
    return rects.long()


def slab_interval(o: torch.Tensor, d: torch.Tensor, box: Box = FULL_BOX) -> tuple[torch.Tensor, torch.Tensor]:
    """Ray parameter interval ``[t0, t1]`` of ``o + t d`` inside the box (object frame), ``(R,)`` each.

    Rays that miss the box get ``t0 > t1``.
    """
    d_safe = torch.where(d.abs() < EPS_RAY_DIR, torch.where(d < 0, -EPS_RAY_DIR, EPS_RAY_DIR), d)
    inv = 1.0 / d_safe
    lo, hi = (torch.tensor(b, dtype=o.dtype, device=o.device) for b in box)
    ta = (lo - o) * inv
    tb = (hi - o) * inv
    t0 = torch.minimum(ta, tb).max(dim=-1).values
    t1 = torch.maximum(ta, tb).min(dim=-1).values
    return t0, t1


def object_rays(
    T_obj_cam: torch.Tensor, T_cam_obj: torch.Tensor, K: torch.Tensor, active: torch.Tensor, height: int, width: int,
    cull: bool = True,
    interval: str = "ray",
    box: Box = FULL_BOX,
) -> ObjectRays:
    """Rays of every active object, inside its projected box (``cull``) or over the whole image.

    Args:
        T_obj_cam, T_cam_obj: ``(N, 4, 4)`` for the N = B*K flattened slots (detached).
        K: ``(N, 3, 3)`` intrinsics of each slot's image.
        active: ``(N,)`` bool; inactive slots (empty, or masked out) cast no rays.
        cull: restrict to the projected box; ``False`` casts every pixel (reference path).
        interval: ``"ray"``: each ray's exact segment inside the box (slab test); ``"object"``:
            the depth range of the object's box corners for every ray (the paper's choice).
        box: the object-frame box the shapes lie in (default: the padded cube).
    """
    if interval not in ("ray", "object"):
        raise ValueError(f"interval: expected 'ray' or 'object', got {interval!r}")
    N = T_obj_cam.shape[0]
    dtype, device = T_obj_cam.dtype, T_obj_cam.device
    if cull:
        rects = projected_box_rects(T_cam_obj, K, height, width, box)
    else:
        rects = torch.tensor([[0, 0, width - 1, height - 1]], dtype=torch.long, device=device).expand(N, 4)
    # every (object, pixel) inside the object's rectangle, objects in order and pixels row-major within each: one
    # mask and one nonzero for all objects (an off-screen rectangle, u1 < u0, holds no pixel)
    cols = torch.arange(width, device=device)
    rows = torch.arange(height, device=device)
    in_u = (cols[None] >= rects[:, 0:1]) & (cols[None] <= rects[:, 2:3])  # (N, W)
    in_v = (rows[None] >= rects[:, 1:2]) & (rows[None] <= rects[:, 3:4])  # (N, H)
    inside = in_v[:, :, None] & in_u[:, None, :] & active.reshape(N, 1, 1)
    obj, pix = torch.nonzero(inside.reshape(N, height * width), as_tuple=True)
    if obj.numel() == 0:
        z = torch.zeros(0, dtype=dtype, device=device)
        return ObjectRays(obj, pix, z, z, torch.zeros(0, 3, dtype=dtype, device=device))
    u = (pix % width).to(dtype)
    v = (pix // width).to(dtype)
    Kr = K[obj]
    d_cam = torch.stack([(u - Kr[:, 0, 2]) / Kr[:, 0, 0], (v - Kr[:, 1, 2]) / Kr[:, 1, 1], torch.ones_like(u)], dim=-1)
    A = T_obj_cam[obj, :3, :3]
    o_obj = T_obj_cam[obj, :3, 3]
    d_obj = torch.einsum("rij,rj->ri", A, d_cam)
    if interval == "ray":
        t0, t1 = slab_interval(o_obj, d_obj, box)
    else:
        c = _corners(box, dtype, device)
        zc = torch.einsum("nj,cj->nc", T_cam_obj[:, 2, :3], c) + T_cam_obj[:, None, 2, 3]  # (N, 8)
        t0, t1 = zc.min(1).values[obj], zc.max(1).values[obj]
    t0 = t0.clamp_min(NEAR_Z)
    keep = t1 > t0
    return ObjectRays(obj[keep], pix[keep], t0[keep], t1[keep], d_cam[keep])
