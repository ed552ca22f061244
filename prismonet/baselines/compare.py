"""The slot masks of trained 2-D baselines beside PriSMONet's instances on the same scenes, as one figure."""

from __future__ import annotations

from pathlib import Path

import torch


@torch.no_grad()
def compare_masks(runs: list[str | Path], data: str | Path, out: str | Path, split: str = "test", scenes: int = 6,
                  model: str = "shipped") -> Path:
    """Write the figure of ``prismonet.viz.mask_comparison`` for the first ``scenes`` scenes of ``data``:
    PriSMONet (``model``, feed-forward) and each baseline run (argmax of its slot masks, the slot
    covering most ground pixels as background, as in the evaluation)."""
    from prismonet.baselines.train import instances_from_masks, load_baseline
    from prismonet.data.dataset import SceneDataset
    from prismonet.model.io import load_model
    from prismonet.viz.mask_comparison import mask_comparison_figure

    ds = SceneDataset(data, split)
    n = min(scenes, len(ds))
    if n <= 0:
        raise ValueError(f"{data}: split {split!r} has no scenes")
    b = ds.batch(list(range(n)))
    gt = b.instance.numpy()
    net, _ = load_model(model)
    columns = [("PriSMONet", net(b.rgb, b.K, b.T_world_cam, b.ground_z).composite.instance.numpy())]
    for run in runs:
        baseline, cfg = load_baseline(run)
        masks = baseline(b.rgb, torch.Generator().manual_seed(0)).masks.numpy()
        columns.append((cfg.name.replace("_", " "), instances_from_masks(masks, gt)))
    return mask_comparison_figure(b.rgb.numpy(), gt, columns, out)
