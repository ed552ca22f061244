"""New colours for the objects of a training scene, found from its depth alone (``TrainConfig.recolor_objects``).

Why: each ShapeNet-style mesh keeps its own colour, so an encoder can tell a seen model by its colour, and it does:
a novel grey car is fitted with the shape of the seen car of nearly its grey (EVALUATION.md, session 73). Turning hues
about the grey axis (``prismonet.data.hue``) cannot change a grey; this can.

How: the pixels off the ground plane (the depth differs from the plane's own depth by more than ``GROUND_TOL``, and
reads less than the far clip) are split into connected regions, and each region's pixels are multiplied per channel by
its own gains ``c / m``, where ``m`` is the region's mean colour and ``c`` a random colour of the same mean brightness
times a random factor. For the Lambertian scenes this is an exact re-rendering: a pixel is ``albedo * shading`` per
channel, so per-channel gains give every object in the region the albedo ``albedo * gains``. Only depth is read, as
training may (no mask, no pose). Objects beyond the far clip, which depth cannot tell from the ground, keep their colours.
"""

from __future__ import annotations

import numpy as np
import torch

GROUND_TOL = 1e-3
"""Depth difference (world units) from the ground plane's depth above which a pixel belongs to an object."""
MIN_PIXELS = 4
"""Regions smaller than this keep their colours (too few pixels for a mean)."""
MAX_GAIN = 8.0
"""Per-channel gains are capped here (a nearly black channel would otherwise be blown up)."""


def object_regions(depth: torch.Tensor, ground_depth: torch.Tensor, far_depth: float) -> np.ndarray:
    """``(B, H, W)`` int labels (0: ground or beyond the clip) of the connected regions off the ground plane, from
    ``depth`` and ``ground_depth`` ``(B, 1, H, W)``."""
    import cv2

    off = ((depth - ground_depth).abs() > GROUND_TOL) & (depth < far_depth - GROUND_TOL)
    off = off[:, 0].cpu().numpy().astype(np.uint8)
    return np.stack([cv2.connectedComponents(m, connectivity=8)[1] for m in off]).astype(np.int64)


def batch_regions(batch, far_depth: float) -> np.ndarray:
    """``object_regions`` of a batch of scenes (its depth against its own ground plane's depth)."""
    from prismonet.render.background import plane_depth

    H, W = batch.depth.shape[-2:]
    return object_regions(batch.depth, plane_depth(batch.K, batch.T_world_cam, H, W, batch.ground_z, far_depth), far_depth)


def recolor_regions(rgb: torch.Tensor, labels: np.ndarray, g: torch.Generator, brightness: tuple[float, float] = (0.7, 1.3),
                    which: torch.Tensor | None = None) -> torch.Tensor:
    """``rgb (B, 3, H, W)`` with every region of ``labels (B, H, W)`` (0: left alone) multiplied per channel by gains
    that give it a random colour (each channel uniform in ``[0, 1)``, rescaled to the region's mean brightness times
    a factor uniform in ``brightness``), clamped to ``[0, 1]``. ``which (B,)`` bool: only those images (all without
    it). Draws from ``g`` in a fixed order: per image, per region, four numbers."""
    out = rgb.clone()
    lab = torch.from_numpy(labels).to(rgb.device)
    for b in range(rgb.shape[0]):
        n = int(lab[b].max())
        for r in range(1, n + 1):
            draw = torch.rand(4, generator=g, dtype=torch.float64)
            if which is not None and not bool(which[b]):
                continue
            m = lab[b] == r
            if int(m.sum()) < MIN_PIXELS:
                continue
            mean = rgb[b][:, m].double().mean(1)  # (3,)
            c = draw[:3] + 1e-3
            factor = brightness[0] + (brightness[1] - brightness[0]) * draw[3]
            c = c * (mean.mean() * factor / c.mean())
            gains = (c / mean.clamp_min(1e-4)).clamp(max=MAX_GAIN).to(rgb.dtype)
            out[b][:, m] = (rgb[b][:, m] * gains[:, None]).clamp(0.0, 1.0)
    return out


class RecoloredScenes:
    """A dataset (``SceneDataset``-like: ``len`` and ``batch(indices)``) whose images have new object colours, drawn
    once per scene from ``(seed, index)`` with ``recolor_regions`` and kept: a scene reads the same wherever and
    however often it is asked for. For fits that cache what a model makes of each scene (``refiner_fit``): the cache
    and the fit's steps must see the same colours. Depth, poses and everything else are the scene's own."""

    def __init__(self, ds, far_depth: float, seed: int = 0, brightness: tuple[float, float] = (0.7, 1.3)) -> None:
        self.ds, self.far_depth, self.seed, self.brightness = ds, far_depth, seed, brightness
        self._rgb: dict[int, torch.Tensor] = {}

    def __len__(self) -> int:
        return len(self.ds)

    def batch(self, indices):
        from dataclasses import replace

        indices = [int(i) for i in indices]
        b = self.ds.batch(indices)
        new = [j for j, i in enumerate(indices) if i not in self._rgb]
        if new:
            labels = batch_regions(b, self.far_depth)
            for j in new:
                g = torch.Generator().manual_seed(self.seed * 1_000_003 + indices[j])
                self._rgb[indices[j]] = recolor_regions(b.rgb[j : j + 1], labels[j : j + 1], g, self.brightness)[0]
        return replace(b, rgb=torch.stack([self._rgb[i] for i in indices]))
