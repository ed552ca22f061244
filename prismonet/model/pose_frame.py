"""Object poses relative to the camera (``ModelConfig.pose_frame = "camera"``), for models that see many cameras.

A model trained with one camera can regress world positions directly (the paper's parametrisation and
``pose_frame = "world"``): the image fixes the world. With cameras drawn per scene (``RandomizeConfig``) the
same image position means another world position, so the encoder regresses what the image shows instead:

- the pixel of the object's centre, ``(u, v) = (c_x, c_y) + (S / 2) (a, b)`` for raw outputs ``(a, b)``
  (``S`` the image side: raw 0 is the principal point);
- the centre's height above the ground, ``offset_z + scale_z * h`` (as the world frame's z);
- the yaw about world z from the camera's heading (its viewing direction on the ground).

The centre is where the viewing ray through ``(u, v)`` meets the horizontal plane at that height: exact,
differentiable, and the same for every camera. Rays that do not go down to the plane (a camera below it, or
a ray above the horizon) are held at ``t`` in ``[T_MIN, t_max]`` along the ray.
"""

from __future__ import annotations

import torch

DOWN_MIN = 1e-3
"""Rays are taken to descend at least this much per unit (no division by ~0 at the horizon)."""
T_MIN = 0.1


def camera_heading(T_world_cam: torch.Tensor) -> torch.Tensor:
    """``(B,)`` angle about world z of each camera's viewing direction (its z axis) projected on the ground."""
    f = T_world_cam[:, :3, 2]
    return torch.atan2(f[:, 1], f[:, 0])


def rotate_about_z(v: torch.Tensor, angle: torch.Tensor) -> torch.Tensor:
    """``v (B, 2 or 3)`` turned by ``angle (B,)`` about world z (the first two components)."""
    c, s = torch.cos(angle), torch.sin(angle)
    xy = torch.stack([c * v[:, 0] - s * v[:, 1], s * v[:, 0] + c * v[:, 1]], 1)
    return torch.cat([xy, v[:, 2:]], 1)


def centre_from_pixel(ab: torch.Tensor, height: torch.Tensor, K: torch.Tensor, T_world_cam: torch.Tensor,
                      ground_z: torch.Tensor, image_size: int, t_max: float) -> torch.Tensor:
    """World centres ``(B, 3)``: on the ray through pixel ``c + (S / 2) ab`` at ``height`` above the ground."""
    half = image_size / 2.0
    d_cam = torch.stack([half * ab[:, 0] / K[:, 0, 0], half * ab[:, 1] / K[:, 1, 1], torch.ones_like(ab[:, 0])], 1)
    d = (T_world_cam[:, :3, :3] @ d_cam[:, :, None])[:, :, 0]
    o = T_world_cam[:, :3, 3]
    z = ground_z.to(ab.dtype) + height
    t = ((z - o[:, 2]) / d[:, 2].clamp(max=-DOWN_MIN)).clamp(T_MIN, t_max)
    return o + t[:, None] * d


def pixel_from_centre(x_world: torch.Tensor, K: torch.Tensor, T_world_cam: torch.Tensor, image_size: int) -> torch.Tensor:
    """The inverse of ``centre_from_pixel`` for the pixel: raw ``ab (B, 2)`` of world centres ``(B, 3)``."""
    T_cam_world = torch.linalg.inv(T_world_cam)
    x = (T_cam_world[:, :3, :3] @ x_world[:, :, None])[:, :, 0] + T_cam_world[:, :3, 3]
    half = image_size / 2.0
    return torch.stack([K[:, 0, 0] * x[:, 0] / x[:, 2] / half, K[:, 1, 1] * x[:, 1] / x[:, 2] / half], 1)
