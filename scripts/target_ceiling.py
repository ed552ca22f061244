"""What a perfect fit to distillation targets could give: a model's feed-forward decoding of the held-out target scenes
against the same scenes rendered from their targets.

    python3 scripts/target_ceiling.py chairs_refiner data/chairs runs/distill_chairs_shipped [--holdout 256]

Rows, on the last ``--holdout`` scenes that have targets (the ones a refiner fit holds out): the model as it is; the
model with each slot's shape latent replaced by its target's where the target's is one of the prior's codes and the
fit shows the slot (what a refiner that picked the right code would add; targets made with ``--search-shapes``); and
the targets themselves, rendered with the model's renderer, the slots the fit does not show left out (what a refiner
that learnt its targets exactly would reach). Detection against the true instances of those training scenes.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np
import torch

CODE_TOL = 1e-4
"""A target shape latent this close to a prior code is that code (the search's shape trials copy codes exactly)."""


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("model")
    ap.add_argument("data")
    ap.add_argument("targets")
    ap.add_argument("--holdout", type=int, default=256)
    ap.add_argument("--batch", type=int, default=64)
    a = ap.parse_args(argv)
    from prismonet.threads import use_free_cores

    if argv is None:  # the command line; a caller passing argv (a test) keeps its own threads
        use_free_cores(exit_on_error=True)  # the cores others leave free; PRISMONET_THREADS=N to choose
    if a.holdout <= 0 or a.batch <= 0:
        print("target_ceiling: error: --holdout and --batch must be positive", file=sys.stderr)
        return 2

    from prismonet.data.dataset import SceneDataset
    from prismonet.evaluation.metrics import detection_metrics
    from prismonet.model.distill import MIN_VISIBLE, SHAPE, VISIBLE, DistillTargets
    from prismonet.model.io import load_model
    from prismonet.model.refine import render_latents
    from prismonet.render import SceneParams

    model, _ = load_model(a.model)
    ds = SceneDataset(a.data, split="train")
    targets = DistillTargets(a.targets, model.cfg.num_slots)
    if VISIBLE not in targets.t:
        print(f"target_ceiling: error: {a.targets} does not say which slots the fit shows (made before session 47)", file=sys.stderr)
        return 2
    count = min(targets.count, len(ds))
    first = max(0, count - a.holdout)
    codes = model.prior.latents.detach()
    rows: dict[str, list[np.ndarray]] = {"model": [], "model, target shape codes": [], "targets": []}
    gt = []
    model.eval()
    with torch.no_grad():
        for s in range(first, count, a.batch):
            idx = list(range(s, min(s + a.batch, count)))
            b = ds.batch(idx)
            H, W = b.rgb.shape[-2:]
            out = model(b.rgb, b.K, b.T_world_cam, b.ground_z)
            p = out.latents.params
            t, _ = targets.lookup(torch.tensor(idx))
            shown = t[VISIBLE] >= MIN_VISIBLE
            z_sh = p.z_sh
            if SHAPE in t:
                is_code = (torch.cdist(t[SHAPE], codes[None].expand(len(idx), -1, -1)).min(-1).values < CODE_TOL) & shown
                z_sh = torch.where(is_code[..., None], t[SHAPE], p.z_sh)
            q = SceneParams(z_sh, p.z_tex, p.position, p.cos_sin, p.scale, p.axis, p.active)
            own = render_latents(model, q, out.latents.bg_color, b.K, b.T_world_cam, b.ground_z, H, W)
            tq = SceneParams(t.get(SHAPE, p.z_sh), t["z_tex"], t["position"], t["cos_sin"], t["scale"], p.axis, shown)
            fit = render_latents(model, tq, t["bg_color"], b.K, b.T_world_cam, b.ground_z, H, W)
            rows["model"].append(out.composite.instance.numpy())
            rows["model, target shape codes"].append(own.composite.instance.numpy())
            rows["targets"].append(fit.composite.instance.numpy())
            gt.append(b.instance.numpy())
    G = np.concatenate(gt)
    print(f"scenes {first}-{count - 1} of {a.data} [train] (held out of {a.targets}), {a.model}:")
    print("| decoding | AP0.5 / unf. | AR0.5 | mAP |\n|---|---|---|---|")
    for name, inst in rows.items():
        d = detection_metrics(np.concatenate(inst), G)
        print(f"| {name} | {d['AP0.5']:.3f} / {d['AP0.5_unfiltered']:.3f} | {d['AR0.5']:.3f} | {d['mAP']:.3f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
