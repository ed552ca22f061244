"""Anti-aliased images: each pixel the mean of ``s x s`` rays through evenly spaced points inside it (a box filter).

The renderer casts one ray through each pixel centre, as the paper's does and as the data's images are made. An
object's outline then falls on whole pixels, and an outline off by half a pixel costs the full colour difference at
every pixel along it. Rendering the same scene at ``s`` times the resolution (``resize_intrinsics``: the rays of a
pixel pass through ``u + (i + 0.5) / s - 0.5``, ``i = 0 .. s-1``) and averaging each ``s x s`` block gives each
pixel the share of its area that each object covers instead.

A display and measurement option, beyond the paper: the latents, the instance masks and the depth are the
one-ray-per-pixel render's. It costs ``s^2`` times the render's rays.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
import torch.nn.functional as F

from prismonet.geometry.camera import resize_intrinsics
from prismonet.render.background import plane_depth
from prismonet.render.composite import composite
from prismonet.render.renderer import RenderSettings, SceneParams, render_objects


def supersampled_image(sdf_fn: Callable, color_fn: Callable, params: SceneParams, bg_color: torch.Tensor, K: torch.Tensor,
                       T_world_cam: torch.Tensor, height: int, width: int, ground_z, samples: int,
                       settings: RenderSettings = RenderSettings()) -> torch.Tensor:
    """``(B, 3, H, W)``: the scene of ``params`` over the ground plane, ``samples x samples`` rays per pixel, averaged.

    Args:
        sdf_fn, color_fn: the shape and texture fields, as ``render_objects`` takes them.
        params: the slots (``SceneParams``; inactive slots are not drawn).
        bg_color: ``(B, 3)`` the ground's colour.
        K: ``(B, 3, 3)``; T_world_cam: ``(B, 4, 4)``; ground_z: float or ``(B,)``.
        samples: rays per pixel along each side (1: the ordinary render).
        settings: the renderer's (its ``far_depth`` also clips the ground, as ``render_latents``).
    """
    if samples < 1:
        raise ValueError(f"samples per pixel side: expected at least 1, got {samples}")
    Ks = resize_intrinsics(K, float(samples), float(samples))
    Hs, Ws = samples * height, samples * width
    obj = render_objects(sdf_fn, color_fn, params, Ks, T_world_cam, Hs, Ws, settings)
    comp = composite(obj.depth, obj.mask, obj.color, bg_color, plane_depth(Ks, T_world_cam, Hs, Ws, ground_z, settings.far_depth))
    return comp.image if samples == 1 else F.avg_pool2d(comp.image, samples)
