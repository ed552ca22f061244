"""The main demo: the shipped 3-object model decomposes the shipped test scenes.

Per scene it writes the decomposition figure (input, reconstruction, target and rendered depth,
instance masks, each object alone), the latent scene, and the scene's measures; over all scenes, a
Markdown table of the paper's measures and ``metrics.json``.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from prismonet.files import write_atomic


def scene_metrics(pred_instance, gt_instance, pred_image, gt_image, pred_depth, gt_depth) -> dict:
    """The paper's measures of one scene (numpy arrays without the batch axis)."""
    from prismonet.evaluation.metrics import depth_metrics, detection_metrics, image_metrics

    m = detection_metrics(pred_instance[None], gt_instance[None])
    m.update(image_metrics(pred_image[None], gt_image[None]))
    m.update(depth_metrics(pred_depth[None], gt_depth[None]))
    return m


def run_demo(out: str | Path, scenes: int = 8, model: str | Path = "shipped", data: str | Path | None = None,
             inference=None, progress: bool = True) -> dict:
    """Run the demo into ``out``; returns ``{"scenes": [...per-scene records], "mean": {...}}``.

    ``inference``: the test-time steps after the encoder (an ``InferenceConfig``; default: none, the
    paper's feed-forward decoding)."""
    from tqdm import tqdm

    from prismonet.assets import samples_for
    from prismonet.data.dataset import SceneDataset
    from prismonet.evaluation.evaluate import check_compatible
    from prismonet.model.inference import InferenceConfig, infer
    from prismonet.model.io import load_model, prior_fingerprint, training_loss_config
    from prismonet.scene import LatentScene
    from prismonet.viz.decomposition import decomposition_figure

    cfg = inference or InferenceConfig()
    if scenes <= 0:
        raise ValueError(f"--scenes must be positive, got {scenes}")
    out = Path(out)
    net, info = load_model(model)
    ds = SceneDataset(samples_for(model) if data is None else data, split="test")
    check_compatible(net, info, ds)
    n = min(scenes, len(ds))
    fp = prior_fingerprint(net.prior)
    loss_cfg = training_loss_config(info)
    records = []
    for i in tqdm(range(n), desc="demo", unit="scene", disable=not progress):
        b = ds.batch([i])
        o = infer(net, b, cfg, loss_cfg)
        name = f"scene_{i:03d}"
        LatentScene.from_output(o, b, 0, fp).save(out / f"{name}.json")
        m = scene_metrics(o.composite.instance[0].numpy(), b.instance[0].numpy(), o.composite.image[0].numpy(),
                          b.rgb[0].numpy(), o.composite.depth[0, 0].numpy(), b.depth[0, 0].numpy())
        title = f"{name}: AP0.5 {m['AP0.5']:.2f}, AR0.5 {m['AR0.5']:.2f}, PSNR {m['PSNR']:.1f} dB, depth RMSE {m['depth_RMSE']:.3f} ({cfg.describe()})"
        fig = decomposition_figure(b.rgb, o, 0, out / f"{name}.png", b.depth, title=title)
        records.append({"scene": name, "figure": str(fig), "latent_scene": str(out / f"{name}.json"), **m})
    keys = [k for k in records[0] if isinstance(records[0][k], float)]
    mean = {k: float(np.mean([r[k] for r in records])) for k in keys}
    result = {"model": str(model), "inference": cfg.record(), "steps": cfg.describe(), "refine_passes": net.cfg.refine_passes,
              "scenes": records, "mean": mean}
    write_atomic(out / "metrics.json", json.dumps(result, indent=1))
    return result


def format_demo_table(result: dict) -> str:
    cols = [("AP0.5", 3), ("AR0.5", 3), ("allObj", 3), ("PSNR", 1), ("SSIM", 3), ("depth_RMSE", 3)]
    lines = ["| scene | " + " | ".join(c for c, _ in cols) + " |", "|---" * (len(cols) + 1) + "|"]
    for r in result["scenes"] + [{"scene": "**mean**", **result["mean"]}]:
        lines.append(f"| {r['scene']} | " + " | ".join(f"{r[c]:.{d}f}" for c, d in cols) + " |")
    return "\n".join(lines)
