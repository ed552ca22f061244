"""The figure of a photo read in tiles: the photo with its tiles outlined, every tile's detections, and the
objects kept after merging, each panel labelled."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from prismonet.files import write_image
from prismonet.viz.decomposition import labelled_panel
from prismonet.viz.mask_comparison import panel_grid

PANEL_SIDE = 360
"""The longer side of each panel, in pixels."""
TILE_COLOR = (90, 90, 255)
KEPT_COLOR = (230, 30, 30)
CUT_COLOR = (240, 160, 0)
DROPPED_COLOR = (150, 150, 150)


def _fit(photo: np.ndarray) -> tuple[np.ndarray, float]:
    import cv2

    f = PANEL_SIDE / max(photo.shape[:2])
    return cv2.resize(photo, (max(1, round(photo.shape[1] * f)), max(1, round(photo.shape[0] * f))), interpolation=cv2.INTER_AREA), f


def _boxes(img: np.ndarray, boxes, f: float, color, width: int = 2) -> None:
    import cv2

    for x0, y0, x1, y1 in np.asarray(boxes, np.float64).reshape(-1, 4):
        cv2.rectangle(img, (round((x0 + 0.5) * f), round((y0 + 0.5) * f)), (round((x1 - 0.5) * f), round((y1 - 0.5) * f)), color, width, cv2.LINE_AA)


def tiled_photo_figure(photo: np.ndarray, outlines: list, boxes: np.ndarray, cut: np.ndarray, kept: np.ndarray,
                       path: str | Path, truth: np.ndarray | None = None, rendered: np.ndarray | None = None) -> Path:
    """Write the figure as PNG. ``photo``: ``(h, w, 3)`` uint8 RGB; ``outlines``: each tile's four corners in photo
    pixels; ``boxes (n, 4)``, ``cut (n,)``: every tile's detections and whether each is cut by an inner tile edge;
    ``kept``: the indices merging kept; ``truth``: optional true boxes, drawn on the third panel; ``rendered``: optional
    ``(h, w, 3)`` uint8, the kept objects' assembled scene rendered onto the photo's pixels (a fourth panel)."""
    import cv2

    small, f = _fit(photo)
    size = (small.shape[1], small.shape[0])
    tiles = small.copy()
    for o in outlines:
        pts = np.round(np.asarray(o, np.float64) * f + 0.5 * f).astype(np.int32).reshape(-1, 1, 2)
        cv2.polylines(tiles, [pts], True, TILE_COLOR, 1, cv2.LINE_AA)
    every = small.copy()
    cut = np.asarray(cut, bool)
    _boxes(every, np.asarray(boxes).reshape(-1, 4)[~cut], f, KEPT_COLOR)
    _boxes(every, np.asarray(boxes).reshape(-1, 4)[cut], f, CUT_COLOR)
    merged = small.copy()
    if truth is not None:
        _boxes(merged, truth, f, (0, 170, 0), 1)
    _boxes(merged, np.asarray(boxes).reshape(-1, 4)[np.asarray(kept, np.int64)], f, KEPT_COLOR)
    panels = [labelled_panel(tiles, f"photo, {len(outlines)} tiles", size),
              labelled_panel(every, f"tiles' detections: {int((~cut).sum())} whole, {int(cut.sum())} cut", size),
              labelled_panel(merged, f"{len(kept)} objects after merging" + (f" ({len(truth)} true, green)" if truth is not None else ""), size)]
    if rendered is not None:
        panels.append(labelled_panel(_fit(rendered)[0], "the assembled 3-D scene, rendered", size))
    return write_image(Path(path), panel_grid([panels])[..., ::-1])
