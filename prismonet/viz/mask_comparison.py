"""One image comparing instance masks of several models on the same scenes: a row per scene, a labelled
column per model (the input and the ground truth first)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from prismonet.files import write_image
from prismonet.viz.contact_sheet import colorize_instances
from prismonet.viz.decomposition import labelled_panel

PANEL = (128, 128)


def mask_comparison_figure(rgb: np.ndarray, gt_instance: np.ndarray, columns: list[tuple[str, np.ndarray]],
                           path: str | Path) -> Path:
    """``rgb (n, 3, H, W)`` in [0, 1], ``gt_instance (n, H, W)`` and ``columns``: ``(name, instances (n, H, W))``
    per model (0 = background). Each mask panel's label carries the model's name and the number of its
    instances in that scene."""
    rows = []
    for i in range(len(rgb)):
        image = chw_to_u8(rgb[i])
        n_gt = len(np.unique(gt_instance[i])) - (0 in gt_instance[i])
        tiles = [labelled_panel(image, "input", PANEL), labelled_panel(colorize_instances(gt_instance[i]), f"truth ({n_gt})", PANEL)]
        for name, inst in columns:
            n = len(np.unique(inst[i])) - (0 in inst[i])
            tiles.append(labelled_panel(colorize_instances(inst[i]), f"{name} ({n})", PANEL))
        rows.append(tiles)
    return write_image(Path(path), panel_grid(rows)[..., ::-1])  # RGB -> OpenCV's BGR


def chw_to_u8(rgb: np.ndarray) -> np.ndarray:
    """An image ``(3, H, W)`` in [0, 1] as ``(H, W, 3)`` uint8."""
    return (np.clip(rgb.transpose(1, 2, 0), 0, 1) * 255).round().astype(np.uint8)


def panel_grid(rows: list[list[np.ndarray]], gap: int = 4) -> np.ndarray:
    """Panels of equal size (``labelled_panel``'s) laid out in rows, with white gaps between them; shorter rows
    are filled with blank panels."""
    n = max(len(tiles) for tiles in rows)
    rows = [tiles + [np.full_like(tiles[0], 255)] * (n - len(tiles)) for tiles in rows]
    lines = []
    for tiles in rows:
        g = np.full((tiles[0].shape[0], gap, 3), 255, np.uint8)
        lines.append(np.concatenate([t for tile in tiles for t in (tile, g)][:-1], 1))
    sep = np.full((gap, lines[0].shape[1], 3), 255, np.uint8)
    return np.concatenate([r for line in lines for r in (line, sep)][:-1], 0)
