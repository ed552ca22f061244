"""Tiled reading of crowded photos: overlapping square tiles, each a scene of its own, and their detections merged.

The model reads a 64-pixel square and has a few slots (8 for the tabletop models). A photo of two dozen coins, or a
dozen sweets spread over a wide table, puts more objects into one view than it has slots, each only a few pixels
across. Tiling reads the table region as an ``n``-by-``m`` grid of overlapping square tiles, each prepared and
decoded as its own photo (uncalibrated: seen by the training camera, as a whole photo is); every object is whole in
at least one tile when it is smaller than the overlap. The tiles' detections (instance masks mapped back to photo
boxes) are then merged:

- a detection whose mask touches a tile edge that lies inside the region is *cut* (the object goes on in the
  next tile); whole detections are taken before cut ones, and larger before smaller (``score``, visible pixels);
- a detection is dropped when it overlaps one already taken by IoU >= ``MERGE_IOU``, or when
  ``MERGE_COVER`` of the smaller box lies inside the other (the same object seen whole in one tile and cut in
  the next).

Each tile's 3-D scene is its own (the training camera is assumed per tile); ``realdata.assemble`` moves the merged
objects into one scene of the whole photo.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

MIN_ZOOM = 1.15
MAX_ZOOM = 3.0
MERGE_IOU = 0.2
MERGE_COVER = 0.5


@dataclass(frozen=True)
class TileConfig:
    """How to read a photo in tiles."""

    tiles: float = 2
    """Tiles along the region's shorter side (1: the whole region at once; a fraction above 1 sets the tiles' side;
    under 1, one view ``1 / tiles`` times as wide as the whole one: zoomed out, ``zoom_out``)."""
    overlap: float = 0.25
    """The part of a tile's side that neighbouring tiles share."""
    color: str = "region"
    """Where the colour mapping is read: ``"region"`` (once, off the whole table region) or ``"tile"`` (off each tile)."""
    target_px: float | None = None
    """Size the tiles per photo instead: read it whole first, then zoom by ``sqrt(target_px / m)`` (``m`` the median
    visible pixels of its objects; at most ``MAX_ZOOM``), or keep the whole reading where that zoom is under
    ``MIN_ZOOM``. ``tiles`` is then ignored."""
    below_px: float | None = None
    """Tile only the photos whose whole reading finds objects of a median size under this many visible pixels (of the
    model's view), or that find none; the others keep their whole reading (``None``: tile every photo)."""
    below_psnr: float | None = None
    """With ``below_px``: also tile (``tiles`` across) the photos whose whole reading explains them poorly, its
    reconstruction under this PSNR (dB) against the prepared view (e.g. a table of small, alike objects read as a few
    blobs)."""
    fine_tiles: float | None = None
    """With ``below_px``: read the photos whose whole reading finds objects of a median size under ``fine_below_px``
    in this many tiles across instead of ``tiles`` (more zoom for the smallest objects)."""
    fine_below_px: float | None = None
    """The median size (visible pixels of the model's view) under which ``fine_tiles`` is used."""
    zoom_out: float | None = None
    """Read the photos whose whole reading finds objects of a median size above ``zoom_out_above_px`` again, zoomed out
    this many times: one square view this many times as wide as the whole one, on the same centre, the part beyond the
    photo filled with the median colour of the whole view's border, so that objects larger than the model was trained
    on shrink to its sizes (a close-up of a cup is otherwise read as several slots). The tile rules come first. Measured
    on close-up stand-ins and not chosen for the photo setting (EVALUATION.md, session 86)."""
    zoom_out_above_px: float | None = None
    """The median size (visible pixels of the model's view) above which ``zoom_out`` is used."""

    def __post_init__(self):
        if not self.tiles > 0:
            raise ValueError(f"tiles: expected a positive number, got {self.tiles}")
        if not 0.0 <= self.overlap < 1.0:
            raise ValueError(f"tile overlap: expected a fraction in [0, 1), got {self.overlap}")
        if self.target_px is not None and not self.target_px > 0:
            raise ValueError(f"tile size target: expected a positive number of pixels, got {self.target_px}")
        if self.below_px is not None and not self.below_px > 0:
            raise ValueError(f"tile size rule: expected a positive number of pixels, got {self.below_px}")
        if self.below_psnr is not None and not self.below_psnr > 0:
            raise ValueError(f"tile PSNR rule: expected a positive number of dB, got {self.below_psnr}")
        if (self.fine_tiles is None) != (self.fine_below_px is None):
            raise ValueError("fine tiles: give both the count and the size under which it is used")
        if self.fine_tiles is not None and not self.fine_tiles >= 1:
            raise ValueError(f"fine tiles: expected at least 1, got {self.fine_tiles}")
        if self.fine_below_px is not None and not self.fine_below_px > 0:
            raise ValueError(f"fine tile size rule: expected a positive number of pixels, got {self.fine_below_px}")
        if (self.below_psnr is not None or self.fine_tiles is not None) and (self.below_px is None or self.target_px is not None):
            raise ValueError("the PSNR and fine-tile rules refine the size rule: "
                             "give --tile-below (below_px) and no --tile-size (target_px)")
        if (self.zoom_out is None) != (self.zoom_out_above_px is None):
            raise ValueError("zoom out: give both the factor and the size above which it is used")
        if self.zoom_out is not None and not (self.zoom_out > 1 and self.zoom_out_above_px > 0):
            raise ValueError(f"zoom out: expected a factor above 1 and a positive size, got {self.zoom_out}, {self.zoom_out_above_px}")
        if self.zoom_out is not None and self.tiles > 1 and self.below_px is None:
            raise ValueError("zoom out with tiles needs the size rule (--tile-below) to say which photos are read whole")
        if self.zoom_out is not None and self.target_px is not None:
            raise ValueError("zoom out refines the size rule: give no --tile-size (target_px) with it")
        if self.color not in ("region", "tile"):
            raise ValueError(f"tile colour mapping: expected region or tile, got {self.color!r}")

    def record(self) -> dict:
        return {"tiles": self.tiles, "overlap": self.overlap, "color": self.color, "below_px": self.below_px, "target_px": self.target_px,
                "below_psnr": self.below_psnr, "fine_tiles": self.fine_tiles, "fine_below_px": self.fine_below_px,
                "zoom_out": self.zoom_out, "zoom_out_above_px": self.zoom_out_above_px}

    @property
    def reads_whole_first(self) -> bool:
        """Whether each photo is read whole first and the count of tiles chosen from that reading."""
        return (self.target_px is not None or self.zoom_out is not None
                or (self.below_px is not None and (self.tiles > 1 or self.fine_tiles is not None)))

    def tiles_after(self, median_px: float, found: int, psnr: float | None) -> float:
        """Tiles across for a photo whose whole reading found ``found`` objects of median size ``median_px`` (visible
        pixels of the model's view) and reconstructs it at ``psnr`` dB (``None``: not measured); 1: keep it whole; under
        1: read it zoomed out (``1 / zoom_out``).

        With ``target_px``, ``tiles_for``. Otherwise, in this order: ``fine_tiles`` where objects were found with a
        median under ``fine_below_px``; ``tiles`` where none was found, the median is under ``below_px``, or the PSNR
        is under ``below_psnr``; ``1 / zoom_out`` where the median is above ``zoom_out_above_px``; else 1."""
        if self.target_px is not None:
            return self.tiles_for(median_px if found else 0.0)
        if self.fine_tiles is not None and found > 0 and median_px < self.fine_below_px:
            return float(self.fine_tiles)
        if self.below_px is not None and (found == 0 or median_px < self.below_px):
            return float(self.tiles)
        if self.below_psnr is not None and psnr is not None and psnr < self.below_psnr:
            return float(self.tiles)
        if self.zoom_out is not None and found > 0 and median_px > self.zoom_out_above_px:
            return 1.0 / self.zoom_out
        return 1.0

    def tiles_for(self, median_px: float) -> float:
        """With ``target_px``: the tiles along the shorter side that zoom objects of ``median_px`` to the target
        (1: read whole)."""
        z = MAX_ZOOM if median_px <= 0 else min(MAX_ZOOM, math.sqrt(self.target_px / median_px))
        return 1.0 if z < MIN_ZOOM else 1 + (z - 1) / (1 - self.overlap)


def tile_boxes(region: tuple[int, int, int, int], tiles: float, overlap: float) -> list[tuple[int, int, int, int]]:
    """Square tiles ``(x0, y0, side, side)`` covering ``region = (x0, y0, w, h)``: ``tiles`` along its shorter side
    (a fraction gives the side ``short / (1 + (tiles - 1) (1 - overlap))`` all the same),
    neighbours sharing ``overlap`` of a side, and as many along the longer side as cover it at the same or a
    smaller stride; the tiles of a row (column) are spread evenly from one end of the region to the other."""
    if tiles < 1:
        raise ValueError(f"tiles: expected at least 1, got {tiles}")
    if not 0.0 <= overlap < 1.0:
        raise ValueError(f"tile overlap: expected a fraction in [0, 1), got {overlap}")
    x0, y0, w, h = (int(v) for v in region)
    short = min(w, h)
    side = short if tiles == 1 else int(math.ceil(short / (1 + (tiles - 1) * (1 - overlap)) - 1e-9))
    side = min(side, short)

    def starts(length: int) -> list[int]:
        if length <= side:
            return [0]
        n = max(2, int(math.ceil((length - side) / (side * (1 - overlap)) - 1e-9)) + 1)
        return [int(round(i * (length - side) / (n - 1))) for i in range(n)]

    return [(x0 + sx, y0 + sy, side, side) for sy in starts(h) for sx in starts(w)]


def inner_edges(tile: tuple[int, int, int, int], region: tuple[int, int, int, int]) -> tuple[bool, bool, bool, bool]:
    """Which of the tile's edges (left, top, right, bottom) lie inside the region (another tile goes on past them)."""
    tx, ty, ts, _ = tile
    rx, ry, rw, rh = region
    return tx > rx, ty > ry, tx + ts < rx + rw, ty + ts < ry + rh


def mask_cut(mask: np.ndarray, inner: tuple[bool, bool, bool, bool]) -> bool:
    """Whether a view mask ``(S, S)`` touches one of the inner edges (left, top, right, bottom)."""
    left, top, right, bottom = inner
    return bool((left and mask[:, 0].any()) or (top and mask[0].any()) or (right and mask[:, -1].any()) or (bottom and mask[-1].any()))


def merge_detections(boxes: np.ndarray, scores: np.ndarray, cut: np.ndarray,
                     iou: float = MERGE_IOU, cover: float = MERGE_COVER) -> np.ndarray:
    """Indices of the detections kept (in the order taken): whole before cut, then by falling score; one is
    dropped when it overlaps a kept one by IoU >= ``iou`` or has ``cover`` of the smaller box inside the other."""
    from realdata.boxes import box_iou

    boxes = np.asarray(boxes, np.float64).reshape(-1, 4)
    if len(boxes) == 0:
        return np.zeros(0, np.int64)
    order = np.lexsort((-np.asarray(scores, np.float64), np.asarray(cut, bool)))
    ious = box_iou(boxes, boxes)
    area = (boxes[:, 2] - boxes[:, 0]) * (boxes[:, 3] - boxes[:, 1])
    inter = ious * (area[:, None] + area[None, :]) / (1 + ious)
    covered = inter / np.minimum(area[:, None], area[None, :])
    kept: list[int] = []
    for i in order:
        if all(ious[i, j] < iou and covered[i, j] < cover for j in kept):
            kept.append(int(i))
    return np.array(kept, np.int64)
