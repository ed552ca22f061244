"""Boxes in photo pixels: their overlap, and a model-view mask's box mapped back to the photo."""

from __future__ import annotations

import numpy as np


def box_iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``(N, M)`` IoU of boxes ``(N, 4)`` and ``(M, 4)`` given as ``x0, y0, x1, y1``."""
    a, b = np.asarray(a, np.float64).reshape(-1, 4), np.asarray(b, np.float64).reshape(-1, 4)
    w = np.clip(np.minimum(a[:, None, 2], b[None, :, 2]) - np.maximum(a[:, None, 0], b[None, :, 0]), 0, None)
    h = np.clip(np.minimum(a[:, None, 3], b[None, :, 3]) - np.maximum(a[:, None, 1], b[None, :, 1]), 0, None)
    inter = w * h
    area = lambda x: (x[:, 2] - x[:, 0]) * (x[:, 3] - x[:, 1])
    return inter / (area(a)[:, None] + area(b)[None, :] - inter)


def view_to_photo(outline, size: int) -> np.ndarray:
    """``(3, 3)`` homography from model-view pixels to photo pixels, from the view's outline in the photo."""
    import cv2

    corners = np.float32([[-0.5, -0.5], [size - 0.5, -0.5], [size - 0.5, size - 0.5], [-0.5, size - 0.5]])
    return cv2.getPerspectiveTransform(corners, np.float32(outline))


def mask_box(mask: np.ndarray, H: np.ndarray) -> tuple[float, float, float, float]:
    """The photo box of a view mask: every mask pixel's four corners through ``H``."""
    v, u = np.nonzero(mask)
    c = np.concatenate([np.stack([u + du, v + dv, np.ones_like(u, dtype=np.float64)], 1) for du in (-0.5, 0.5) for dv in (-0.5, 0.5)])
    q = c @ H.T
    xy = q[:, :2] / q[:, 2:]
    return float(xy[:, 0].min()), float(xy[:, 1].min()), float(xy[:, 0].max()), float(xy[:, 1].max())
