"""Seeking the unexplained (beyond the paper, still weakly supervised): a pull on slots that explain
nothing towards what no slot explains yet.

A slot that the encoder hides (tiny, or behind the others) gets no gradient from the image, depth or
mask losses towards an object that no slot covers: its silhouette is nowhere near it. So a model
trained on scenes of many objects learns to find a few and hide the rest (EVALUATION.md, the 1-8
models). This term gives such a slot a direction, from the input RGB-D alone:

1. The foreground (``seek_foreground``) is what lies in front of the known ground plane (as
   ``LossConfig.mask_from_depth``), and, where the depth reads the far clip and cannot tell, what
   differs in colour from the background colour; the *unexplained* foreground is where the render shows
   the ground there instead of a slot.
2. A slot *explains* the scene where it wins at least ``MIN_PIXELS`` foreground pixels of the render
   (its visible pixels, after the z-buffer with the other slots and the ground). In encoder order, a
   slot that does not, while the unexplained foreground holds a connected region of at least
   ``MIN_PIXELS`` after a morphological opening (which removes the thin rims around the slots'
   silhouettes), *seeks* the largest such region not claimed by an earlier seeking slot. Its target is
   the mean world position of the region's depth points, or, for a region beyond the depth clip, where
   the ray through the middle of its lowest row meets the ground (the object's foot).
3. ``seek_loss``: the L1 distance, in the ground plane (x, y), between each seeking slot's centre and
   its target, averaged over a scene's seeking slots and over the scenes.

The target is a visible surface's centroid or the object's foot, a little in front of its centre as the
camera sees it; it only has to bring the slot close enough for the image, depth and mask losses to take
over. No pose, mask or instance label is read.
"""

from __future__ import annotations

import cv2
import numpy as np
import torch

from prismonet.geometry.camera import pixel_grid, unproject
from prismonet.geometry.transforms import transform_points
from prismonet.model.foreground import at_far_clip, depth_foreground

MIN_PIXELS = 25
"""Foreground pixels that make a region worth seeking, and that a slot must win to explain (the
metrics' visibility rule)."""

COLOR_TOL = 0.1
"""Beyond the depth clip, a pixel is foreground when a colour channel differs from the background
colour by more than this."""


def seek_foreground(rgb: torch.Tensor, depth: torch.Tensor, bg_depth: torch.Tensor, bg_color: torch.Tensor,
                    far_depth: float | None, margin: float) -> torch.Tensor:
    """``(B, H, W)`` bool: pixels in front of the ground by depth (``depth_foreground``), and, with
    ``far_depth``, pixels at the far clip whose colour is not the background's (``bg_color (B, 3)``)."""
    fg = depth_foreground(depth, bg_depth, margin)[:, 0]
    if far_depth is not None:
        off = (rgb - bg_color[:, :, None, None]).abs().amax(1) > COLOR_TOL
        fg = fg | (at_far_clip(depth, far_depth)[:, 0] & off)
    return fg


@torch.no_grad()
def seek_targets(instance: torch.Tensor, num_slots: int, foreground: torch.Tensor, depth: torch.Tensor, K: torch.Tensor,
                 T_world_cam: torch.Tensor, ground_z: torch.Tensor, far_depth: float | None = None,
                 min_pixels: int = MIN_PIXELS) -> tuple[torch.Tensor, torch.Tensor]:
    """Targets for the slots that explain nothing.

    Args:
        instance: ``(B, H, W)`` the render's winners: 0 the ground, k the slot k - 1 (``Composite.instance``).
        num_slots: N, the slots in encoder order.
        foreground: ``(B, H, W)`` bool (``seek_foreground``).
        depth: ``(B, H, W)`` the input's camera-z depth.
        K: ``(B, 3, 3)``; T_world_cam: ``(B, 4, 4)``; ground_z: ``(B,)``.
        far_depth: the depth clip: a region most of whose pixels read it is placed by the ground instead.

    Returns:
        ``targets (B, N, 3)`` world points and ``weight (B, N)``: 1 for a seeking slot, else 0.
    """
    B, H, W = instance.shape
    if foreground.shape != (B, H, W) or depth.shape != (B, H, W):
        raise ValueError(f"foreground and depth: expected shape {(B, H, W)}, got {tuple(foreground.shape)} and {tuple(depth.shape)}")
    targets = torch.zeros(B, num_slots, 3, dtype=depth.dtype, device=depth.device)
    weight = torch.zeros(B, num_slots, dtype=depth.dtype, device=depth.device)
    inst, fg = instance.cpu().numpy(), foreground.cpu().numpy()
    far = at_far_clip(depth, far_depth).cpu().numpy() if far_depth is not None else np.zeros((B, H, W), bool)
    kernel = np.ones((3, 3), np.uint8)
    uv = pixel_grid(H, W, dtype=depth.dtype, device=depth.device)
    for b in range(B):
        won = np.bincount(inst[b][fg[b]].ravel(), minlength=num_slots + 1)[1:]
        left = cv2.morphologyEx((fg[b] & (inst[b] == 0)).astype(np.uint8), cv2.MORPH_OPEN, kernel)
        _, labels, stats, _ = cv2.connectedComponentsWithStats(left, connectivity=4)
        areas = stats[1:, cv2.CC_STAT_AREA]
        largest = [i + 1 for i in np.argsort(-areas, kind="stable") if areas[i] >= min_pixels]
        # seeking slots in encoder order take the regions from the largest down, one each
        for k, label in zip(np.flatnonzero(won < min_pixels), largest):
            region = labels == label
            target = _foot(region, K[b], T_world_cam[b], float(ground_z[b])) if far[b][region].mean() > 0.5 else _centroid(region, uv, depth[b], K[b], T_world_cam[b])
            if target is not None:
                targets[b, k] = target
                weight[b, k] = 1.0
    return targets, weight


def _centroid(region: np.ndarray, uv: torch.Tensor, depth: torch.Tensor, K: torch.Tensor, T_world_cam: torch.Tensor) -> torch.Tensor:
    """Mean world point of the region's depth points."""
    sel = torch.from_numpy(region).to(uv.device)
    return transform_points(T_world_cam, unproject(uv[sel], depth[sel][:, None], K)).mean(0)


def _foot(region: np.ndarray, K: torch.Tensor, T_world_cam: torch.Tensor, ground_z: float) -> torch.Tensor | None:
    """Where the ray through the middle of the region's lowest row meets the ground; ``None`` if it
    does not go down."""
    rows, cols = np.nonzero(region)
    v = rows.max()
    u = cols[rows == v].mean()
    ray = unproject(torch.tensor([[u, float(v)]], dtype=K.dtype, device=K.device), torch.ones(1, 1, dtype=K.dtype, device=K.device), K)[0]
    d = T_world_cam[:3, :3] @ ray
    o = T_world_cam[:3, 3]
    if d[2] >= 0:
        return None
    return o + (ground_z - o[2]) / d[2] * d


def seek_loss(position: torch.Tensor, targets: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
    """``()``: the L1 ground-plane distance of the seeking slots (``weight``) from their targets, the mean
    over a scene's seeking slots (0 where none seeks), then over scenes. ``position`` ``(B, N, 3)`` world,
    with gradient. A mean, not a sum: with a sum a scene that explains little pulls hardest, and a first
    run at weight 0.05 fed on itself (more hidden slots, a larger pull on the shared encoder, worse slots)."""
    per_slot = (position[..., :2] - targets[..., :2]).abs().sum(-1)
    return ((weight * per_slot).sum(1) / weight.sum(1).clamp_min(1.0)).mean()
