"""The photoreal ladder as one image: a row per scene; per rung its input and the instances a model found."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from prismonet.files import write_image
from prismonet.viz.contact_sheet import colorize_instances
from prismonet.viz.decomposition import labelled_panel
from prismonet.viz.mask_comparison import PANEL, chw_to_u8, panel_grid


def ladder_figure(rungs: list[tuple[str, np.ndarray, np.ndarray, np.ndarray]], path: str | Path) -> Path:
    """Per rung ``(name, rgb (n, 3, H, W) in [0, 1], true instances (n, H, W), found instances (n, H, W))``.
    A truth panel precedes a rung whose scenes differ from those before it (the first, and e.g. a rung
    with camera jitter); each found panel's label carries the count found against the truth."""
    rows = []
    for i in range(len(rungs[0][1])):
        tiles, last = [], None
        for name, rgb, gt, inst in rungs:
            n_gt = len(np.unique(gt[i])) - (0 in gt[i])
            if last is None or not np.array_equal(gt[i], last):
                tiles.append(labelled_panel(colorize_instances(gt[i]), f"truth ({n_gt})", PANEL))
                last = gt[i]
            n = len(np.unique(inst[i])) - (0 in inst[i])
            tiles += [labelled_panel(chw_to_u8(rgb[i]), name, PANEL), labelled_panel(colorize_instances(inst[i]), f"found {n}/{n_gt}", PANEL)]
        rows.append(tiles)
    return write_image(Path(path), panel_grid(rows)[..., ::-1])
