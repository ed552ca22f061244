"""A contact sheet of scenes: RGB, depth and instance masks side by side."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from prismonet.files import write_image

INSTANCE_PALETTE = np.array(
    [(0, 0, 0), (230, 25, 75), (60, 180, 75), (255, 225, 25), (0, 130, 200), (245, 130, 48),
     (145, 30, 180), (70, 240, 240), (240, 50, 230), (210, 245, 60), (250, 190, 212)],
    dtype=np.uint8,
)
"""Instance id -> RGB (0 = background, black); ids past the end wrap around (skipping 0)."""


def colorize_instances(instance: np.ndarray) -> np.ndarray:
    """``(H, W)`` integer ids to ``(H, W, 3)`` uint8 RGB."""
    ids = np.asarray(instance, dtype=np.int64)
    wrapped = np.where(ids > 0, (ids - 1) % (len(INSTANCE_PALETTE) - 1) + 1, 0)
    return INSTANCE_PALETTE[wrapped]


def colorize_depth(depth: np.ndarray, near: float | None = None, far: float | None = None) -> np.ndarray:
    """``(H, W)`` depth to ``(H, W, 3)`` uint8 RGB (turbo colour map, near = red); 0 = unknown = black."""
    import cv2

    d = np.asarray(depth, dtype=np.float64)
    valid = d > 0
    if not valid.any():
        return np.zeros((*d.shape, 3), np.uint8)
    lo = d[valid].min() if near is None else near
    hi = d[valid].max() if far is None else far
    x = np.clip((hi - d) / max(hi - lo, 1e-9), 0.0, 1.0)
    rgb = cv2.applyColorMap(np.rint(x * 255).astype(np.uint8), cv2.COLORMAP_TURBO)[..., ::-1]
    return np.where(valid[..., None], rgb, 0).astype(np.uint8)


def contact_sheet(arrays: dict[str, np.ndarray], path: str | Path, upscale: int = 2, columns: int = 2) -> Path:
    """Write a PNG with one tile per scene: RGB | depth | instances. Returns the path.

    Args:
        arrays: scene arrays as loaded (``rgb`` (N, H, W, 3), ``depth`` (N, H, W), ``instance`` (N, H, W)).
        path: output PNG.
        upscale: nearest-neighbour enlargement of every image.
        columns: scene tiles per row.
    """
    import cv2

    n, H, W = arrays["rgb"].shape[:3]
    if n == 0:
        raise ValueError("contact_sheet: no scenes")
    gap = 4
    tiles = []
    for i in range(n):
        panels = [
            np.asarray(arrays["rgb"][i]),
            colorize_depth(arrays["depth"][i]),
            colorize_instances(arrays["instance"][i]),
        ]
        panels = [cv2.resize(p, (W * upscale, H * upscale), interpolation=cv2.INTER_NEAREST) for p in panels]
        sep = np.full((H * upscale, gap // 2, 3), 255, np.uint8)
        tiles.append(np.concatenate([panels[0], sep, panels[1], sep, panels[2]], axis=1))
    th, tw = tiles[0].shape[:2]
    rows = (n + columns - 1) // columns
    sheet = np.full((rows * (th + gap) + gap, columns * (tw + gap) + gap, 3), 255, np.uint8)
    for i, tile in enumerate(tiles):
        r, c = divmod(i, columns)
        y, x = gap + r * (th + gap), gap + c * (tw + gap)
        sheet[y : y + th, x : x + tw] = tile
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if not write_image(path, sheet[..., ::-1]):
        raise OSError(f"{path}: could not write the PNG")
    return path


__all__ = ["colorize_depth", "colorize_instances", "contact_sheet"]
