"""The decomposition figure: input, reconstruction, depth, instance masks, and each object alone,
every panel labelled; slots with too few visible pixels to count as objects are marked."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from prismonet.files import write_image

LABEL_HEIGHT = 18
"""Pixels of the strip above each panel that holds its label."""
MIN_PIXELS = 25
"""Visible pixels for a slot to count as an object (the evaluation's 25-pixel rule)."""


def _u8(img: torch.Tensor) -> np.ndarray:
    return (img.detach().clamp(0, 1).permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)


def _text(img: np.ndarray, text: str, x: int, y: int, scale: float = 0.42, color=(0, 0, 0)) -> None:
    import cv2

    cv2.putText(img, text, (x, y), cv2.FONT_HERSHEY_SIMPLEX, scale, color, 1, cv2.LINE_AA)


def labelled_panel(tile: np.ndarray, label: str, size: tuple[int, int], dim: bool = False) -> np.ndarray:
    """``tile`` scaled to ``size`` (nearest, so pixels stay visible) under a label strip; ``dim``: washed out."""
    import cv2

    big = cv2.resize(tile, size, interpolation=cv2.INTER_NEAREST)
    if dim:
        big = (0.35 * big + 0.65 * 255).astype(np.uint8)
    strip = np.full((LABEL_HEIGHT, size[0], 3), 255, np.uint8)
    _text(strip, label, 2, LABEL_HEIGHT - 5, color=(150, 0, 0) if dim else (0, 0, 0))
    return np.concatenate([strip, big], 0)


def _photo_tile(photo: np.ndarray, outline: np.ndarray | None, size: tuple[int, int]) -> np.ndarray:
    """The photo fitted into a panel, with the region the model sees outlined."""
    import cv2

    W, H = size
    photo = photo.copy()
    if outline is not None:
        pts = np.round(np.asarray(outline, np.float64)).astype(np.int32).reshape(-1, 1, 2)
        cv2.polylines(photo, [pts], True, (255, 40, 40), max(2, photo.shape[1] // 200), cv2.LINE_AA)
    f = min(H / photo.shape[0], W / photo.shape[1])
    small = cv2.resize(photo, (max(1, round(photo.shape[1] * f)), max(1, round(photo.shape[0] * f))), interpolation=cv2.INTER_AREA)
    tile = np.full((H, W, 3), 255, np.uint8)
    tile[: small.shape[0], : small.shape[1]] = small
    return tile


SLOTS_PER_ROW = 8
"""Slot panels per row of a figure (more slots, e.g. added by re-seeding, wrap onto further rows)."""


def _object_panels(out, i: int, size, min_pixels: int) -> list[np.ndarray]:
    """Each slot rendered alone over the background, labelled with its visible pixels."""
    from prismonet.render.composite import composite

    N = out.obj_depth.shape[1]
    visible = torch.bincount(out.composite.instance[i].reshape(-1), minlength=N + 1)[1:]
    active = out.latents.params.active
    panels = []
    for k in range(N):
        if active is not None and not bool(active[i, k]):
            continue  # never decoded, pruned, or added for re-seeding and not used: nothing to show
        keep = torch.zeros(N, dtype=torch.bool)
        keep[k] = True
        alone = composite(out.obj_depth[i : i + 1, keep], out.obj_mask[i : i + 1, keep], out.obj_color[i : i + 1, keep],
                          out.latents.bg_color[i : i + 1], out.bg_depth[i : i + 1])
        n = int(visible[k])
        counted = n >= min_pixels
        panels.append(labelled_panel(_u8(alone.image[0]), f"slot {k + 1}: {n} px" + ("" if counted else ", not counted"), size, dim=not counted))
    return panels


def decomposition_figure(image: torch.Tensor, out, index: int, path: str | Path, depth_gt: torch.Tensor | None = None,
                         upscale: int = 3, photo: np.ndarray | None = None, photo_outline: np.ndarray | None = None,
                         title: str | None = None, min_pixels: int = MIN_PIXELS) -> Path:
    """Write one scene's figure as PNG. Top row: [photo,] input, reconstruction, [target depth,]
    rendered depth, instances. Below: each active slot rendered alone over the background, with its
    visible pixels, ``SLOTS_PER_ROW`` (or as many as the top row) per row; slots under ``min_pixels`` are
    washed out and marked "not counted".

    Args:
        image: ``(B, 3, H, W)`` the model's input; ``out``: its ``ModelOutput``; ``index``: which scene.
        photo: optional ``(h, w, 3)`` uint8 RGB original photo, shown first (fitted into a panel).
        photo_outline: ``(n, 2)`` photo pixels of the region the model sees (a crop box, or the
            rectified view's footprint), drawn on the photo.
        title: a line above the panels (e.g. the scene's measures).
    """
    import cv2

    from prismonet.viz.contact_sheet import colorize_depth, colorize_instances

    i = index
    H, W = image.shape[-2:]
    size = (W * upscale, H * upscale)
    d = out.composite.depth[i, 0].detach().numpy()
    lo, hi = float(d.min()), float(d.max())
    if depth_gt is not None:
        g = depth_gt[i, 0].numpy()
        lo, hi = (float(g[g > 0].min()), float(g.max())) if (g > 0).any() else (lo, hi)
    top = [labelled_panel(_u8(image[i]), "input", size), labelled_panel(_u8(out.composite.image[i]), "reconstruction", size)]
    if photo is not None:
        top.insert(0, labelled_panel(_photo_tile(photo, photo_outline, size), "photo (model's view outlined)" if photo_outline is not None else "photo", size))
    if depth_gt is not None:
        top.append(labelled_panel(colorize_depth(depth_gt[i, 0].numpy(), lo, hi), "depth target", size))
    top += [labelled_panel(colorize_depth(d, lo, hi), "depth", size), labelled_panel(colorize_instances(out.composite.instance[i].numpy()), "instances", size)]
    bottom = _object_panels(out, i, size, min_pixels)
    blank = np.full_like(top[0], 255)
    cols = max(len(top), min(len(bottom), SLOTS_PER_ROW))
    rows = [top] + [bottom[j : j + cols] for j in range(0, len(bottom), cols)]  # many slots wrap onto more rows
    gap = 4
    lines = []
    for row in rows:
        row = row + [blank] * (cols - len(row))
        sep = np.full((row[0].shape[0], gap, 3), 255, np.uint8)
        lines.append(np.concatenate(sum([[t, sep] for t in row], [])[:-1], axis=1))
    parts = sum([[line, np.full((gap, lines[0].shape[1], 3), 255, np.uint8)] for line in lines], [])[:-1]
    if title:
        head = np.full((LABEL_HEIGHT + 6, lines[0].shape[1], 3), 255, np.uint8)
        _text(head, title, 2, LABEL_HEIGHT, scale=0.5)
        parts.insert(0, head)
    sheet = np.concatenate(parts, axis=0)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_image(path, cv2.cvtColor(sheet, cv2.COLOR_RGB2BGR))
    return path
