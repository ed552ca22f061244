"""Preparing a photo for the model: undistort, crop, resize, with the camera updated to match.

The camera is a ``prismonet.geometry.Camera`` (OpenCV convention); crops and resizes go through
``crop_intrinsics`` / ``resize_intrinsics`` so that projection stays exact.
"""

from __future__ import annotations

import numpy as np

from realdata.io import PhotoError


def undistort(image: np.ndarray, K: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """Remove lens distortion, keeping the same ``K`` (cv2.undistort)."""
    import cv2

    return cv2.undistort(image, np.asarray(K, np.float64), np.asarray(dist, np.float64))


def check_box(box, shape: tuple[int, ...], where: str = "") -> tuple[int, int, int, int]:
    """``box = (x0, y0, width, height)`` as ints, refused in one line (``PhotoError``, prefixed by ``where``) unless it
    is non-empty and lies inside a photo of ``shape`` ``(H, W, ...)``."""
    x0, y0, w, h = (int(v) for v in box)
    H, W = shape[:2]
    if w <= 0 or h <= 0 or x0 < 0 or y0 < 0 or x0 + w > W or y0 + h > H:
        raise PhotoError(f"{where + ': ' if where else ''}crop box {tuple(box)} does not fit in the {W}x{H} photo")
    return x0, y0, w, h


def crop(image: np.ndarray, camera, box: tuple[int, int, int, int]):
    """Crop to ``box = (x0, y0, width, height)``; returns ``(image, camera)``."""
    x0, y0, w, h = check_box(box, image.shape)
    return image[y0 : y0 + h, x0 : x0 + w].copy(), camera.cropped(x0, y0, h, w)


def resize(image: np.ndarray, camera, size: int):
    """Resize to ``size x size`` (area averaging when shrinking); returns ``(image, camera)``."""
    import cv2

    H, W = image.shape[:2]
    interp = cv2.INTER_AREA if size < min(H, W) else cv2.INTER_LINEAR
    return cv2.resize(image, (size, size), interpolation=interp), camera.resized(size, size)


def center_square(image: np.ndarray, camera):
    """The largest centred square crop (the model's images are square)."""
    H, W = image.shape[:2]
    s = min(H, W)
    return crop(image, camera, ((W - s) // 2, (H - s) // 2, s, s))


TABLE_TOLERANCE = 0.12
"""Max RGB distance (0-1 units) from the table colour for a pixel to count as table."""
REGION_SHARE: float | None = 0.1
"""The table region is the bounding box of every table-coloured piece at least this share of the largest one's area
(cast shadows and objects break the table into pieces); None: the largest piece alone. Chosen on the stand-ins
(0.1 against 0.25 and None; EVALUATION.md, "Session 53")."""


def table_region(image: np.ndarray) -> tuple[int, int, int, int]:
    """``(x0, y0, w, h)``: the bounding box of the large regions of table-coloured pixels (morphologically closed):
    every piece of at least ``REGION_SHARE`` of the largest one's area."""
    import cv2

    from realdata.color import estimate_table_color

    table = estimate_table_color(image)
    mask = (np.linalg.norm(image - table, axis=-1) < TABLE_TOLERANCE).astype(np.uint8)
    k = max(3, min(image.shape[:2]) // 40) | 1
    mask = cv2.morphologyEx(mask, cv2.MORPH_CLOSE, np.ones((k, k), np.uint8))
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask)
    if n <= 1:
        raise PhotoError("no table region found (no large area of one colour)")
    area = stats[1:, cv2.CC_STAT_AREA]
    keep = 1 + np.flatnonzero(area >= (area.max() if REGION_SHARE is None else REGION_SHARE * area.max()))
    x0, y0 = stats[keep, cv2.CC_STAT_LEFT].min(), stats[keep, cv2.CC_STAT_TOP].min()
    x1 = (stats[keep, cv2.CC_STAT_LEFT] + stats[keep, cv2.CC_STAT_WIDTH]).max()
    y1 = (stats[keep, cv2.CC_STAT_TOP] + stats[keep, cv2.CC_STAT_HEIGHT]).max()
    return int(x0), int(y0), int(x1 - x0), int(y1 - y0)


def auto_table_box(image: np.ndarray, min_side: int = 0, region: tuple[int, int, int, int] | None = None) -> tuple[int, int, int, int]:
    """A square ``(x0, y0, side, side)`` around the table (``table_region``, or ``region`` when already found), grown to
    a square and kept in the photo; when that is smaller than ``min_side`` (the table found is a fragment: shadows,
    uneven light), the largest centred square of the photo."""
    x, y, w, h = table_region(image) if region is None else region
    H, W = image.shape[:2]
    side = min(max(w, h), H, W)
    if side < min_side:
        s = min(H, W)
        return (W - s) // 2, (H - s) // 2, s, s
    x0 = min(max(0, x + w // 2 - side // 2), W - side)
    y0 = min(max(0, y + h // 2 - side // 2), H - side)
    return x0, y0, side, side
