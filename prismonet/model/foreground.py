"""What the RGB-D input alone says about objects: pixels in front of the known ground plane, and the
pixels where depth says nothing (the far clip). Read by L_mask's depth-made target and by the seek term."""

from __future__ import annotations

import torch

FAR_TOL = 1e-3
"""A depth within this of the far clip reads as the clip."""


def depth_foreground(depth: torch.Tensor, bg_depth: torch.Tensor, margin: float) -> torch.Tensor:
    """Bool, the shape of ``depth``: pixels in front of the known ground plane (depth ``bg_depth``) by
    more than ``margin`` (what the RGB-D input and the plane imply is an object; no labels)."""
    return (depth > 0) & (depth < bg_depth - margin)


def at_far_clip(depth: torch.Tensor, far_depth: float) -> torch.Tensor:
    """Bool: pixels whose depth reads the far clip (or no return), where depth says nothing."""
    return (depth <= 0) | (depth >= far_depth - FAR_TOL)
