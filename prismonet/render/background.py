"""The background: a ground plane of known pose, with a regressed uniform colour."""

from __future__ import annotations

import torch

from prismonet.geometry.camera import pixel_grid
from prismonet.render.rays import EPS_RAY_DIR


def plane_depth(K: torch.Tensor, T_world_cam: torch.Tensor, height: int, width: int, ground_z, far_depth: float = 12.0) -> torch.Tensor:
    """Depth image ``(B, 1, H, W)`` of the plane ``z = ground_z`` (world), clipped at ``far_depth``.

    Pixels whose ray does not meet the plane in front of the camera get ``far_depth``.
    ``K``: ``(B, 3, 3)``; ``T_world_cam``: ``(B, 4, 4)``; ``ground_z``: float or ``(B,)``.
    """
    B = K.shape[0]
    uv = pixel_grid(height, width, dtype=K.dtype, device=K.device).reshape(-1, 2)
    d_cam = torch.cat([(uv[None, :, :1] - K[:, None, 0:1, 2]) / K[:, None, 0:1, 0], (uv[None, :, 1:] - K[:, None, 1:2, 2]) / K[:, None, 1:2, 1]], -1)
    d_cam = torch.cat([d_cam, torch.ones_like(d_cam[..., :1])], -1)  # (B, HW, 3), z = 1
    d_z = torch.einsum("bj,bpj->bp", T_world_cam[:, 2, :3], d_cam)  # world z of the direction
    c_z = T_world_cam[:, 2, 3:4]
    gz = torch.as_tensor(ground_z, dtype=K.dtype, device=K.device).reshape(-1, 1).expand(B, 1)
    t = (gz - c_z) / torch.where(d_z.abs() < EPS_RAY_DIR, torch.full_like(d_z, -EPS_RAY_DIR), d_z)  # horizontal rays: no 0/0
    t = torch.where((d_z < 0) & (t > 0), t, torch.full_like(t, far_depth)).clamp(max=far_depth)
    return t.reshape(B, 1, height, width)
