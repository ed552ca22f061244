"""The decomposition figure: input, reconstruction, depth, instance masks, and each object alone."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from prismonet.files import write_image


def _u8(img: torch.Tensor) -> np.ndarray:
    return (img.detach().clamp(0, 1).permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)


def decomposition_figure(image: torch.Tensor, out, index: int, path: str | Path, depth_gt: torch.Tensor | None = None,
                         upscale: int = 3, photo: np.ndarray | None = None) -> Path:
    """Write one scene's figure as PNG. Top row: [photo,] input, reconstruction, [target depth,]
    rendered depth, instances. Bottom row: each slot rendered alone over the background.

    Args:
        image: ``(B, 3, H, W)`` the model's input; ``out``: its ``ModelOutput``; ``index``: which scene.
        photo: optional ``(h, w, 3)`` uint8 RGB original photo, shown first (fitted into a tile).
    """
    import cv2

    from prismonet.render.composite import composite
    from prismonet.viz.contact_sheet import colorize_depth, colorize_instances

    i = index
    d = out.composite.depth[i, 0].detach().numpy()
    lo, hi = float(d.min()), float(d.max())
    if depth_gt is not None:
        g = depth_gt[i, 0].numpy()
        lo, hi = float(g[g > 0].min()), float(g.max())
    top = [_u8(image[i]), _u8(out.composite.image[i])]
    if photo is not None:
        H, W = image.shape[-2:]
        f = min(H / photo.shape[0], W / photo.shape[1])
        small = cv2.resize(photo, (max(1, round(photo.shape[1] * f)), max(1, round(photo.shape[0] * f))), interpolation=cv2.INTER_AREA)
        tile = np.full((H, W, 3), 255, np.uint8)
        tile[: small.shape[0], : small.shape[1]] = small
        top.insert(0, tile)
    if depth_gt is not None:
        top.append(colorize_depth(depth_gt[i, 0].numpy(), lo, hi))
    top += [colorize_depth(d, lo, hi), colorize_instances(out.composite.instance[i].numpy())]
    N = out.obj_depth.shape[1]
    bottom = []
    for k in range(N):
        keep = torch.zeros(N, dtype=torch.bool)
        keep[k] = True
        alone = composite(out.obj_depth[i : i + 1, keep], out.obj_mask[i : i + 1, keep], out.obj_color[i : i + 1, keep],
                          out.latents.bg_color[i : i + 1], out.bg_depth[i : i + 1])
        bottom.append(_u8(alone.image[0]))
    H, W = image.shape[-2:]
    size = (W * upscale, H * upscale)
    blank = np.full((H, W, 3), 255, np.uint8)
    cols = max(len(top), len(bottom))
    rows = [top + [blank] * (cols - len(top)), bottom + [blank] * (cols - len(bottom))]
    gap = 4
    lines = []
    for row in rows:
        tiles = [cv2.resize(t, size, interpolation=cv2.INTER_NEAREST) for t in row]
        sep = np.full((size[1], gap, 3), 255, np.uint8)
        lines.append(np.concatenate(sum([[t, sep] for t in tiles], [])[:-1], axis=1))
    sheet = np.concatenate([lines[0], np.full((gap, lines[0].shape[1], 3), 255, np.uint8), lines[1]], axis=0)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_image(path, sheet[..., ::-1])
    return path
