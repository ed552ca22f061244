"""Can a shape prior draw the shapes it was not trained on? Volumetric IoU of a setting's seen and unseen meshes.

    python3 scripts/prior_unseen.py cars data/furniture/cars [--resolution 32] [--out runs/prior_unseen_cars.json]

Per mesh, from its SDF samples (``sample_sdf``, the pre-training settings): the code fitted with the decoder frozen
(``prismonet.shapes.code_fit.fit_code``, from the mean training code), and the training code that fits the samples
best (``nearest_code``: what the search's shape trials can offer). Seen meshes also get their own training code. IoU at
``--resolution``^3 against the mesh's occupancy, as the prior's training table (EVALUATION.md, "ShapeNet-style
settings"). The unseen rows are the most a scene model on this prior could draw of a novel shape.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("prior", help="a shipped prior name (cars, chairs, tableware) or a prior stem")
    ap.add_argument("shapes", help="the imported folder it was trained on (models.json, with seen and unseen models)")
    ap.add_argument("--resolution", type=int, default=32)
    ap.add_argument("--steps", type=int, default=800, help="code-fit steps per mesh")
    ap.add_argument("--out", default=None, help="JSON of every mesh's row")
    a = ap.parse_args(argv)
    from prismonet.threads import use_free_cores

    if argv is None:  # the command line; a caller passing argv (a test) keeps its own threads
        use_free_cores(exit_on_error=True)  # the cores others leave free; PRISMONET_THREADS=N to choose
    if not (Path(a.shapes) / "models.json").is_file():
        print(f"prior_unseen: error: {a.shapes} has no models.json (import the setting with `prismonet shapes import-furniture`)",
              file=sys.stderr)
        return 2

    from prismonet.shapes.code_fit import CodeFitConfig, fit_code, nearest_code
    from prismonet.shapes.metrics import decoder_occupancy, grid_points, mesh_occupancy, volumetric_iou
    from prismonet.shapes.pretrain import load_shape_set
    from prismonet.shapes.prior import load_prior
    from prismonet.shapes.sdf_samples import SamplingConfig, sample_sdf

    prior = load_prior(a.prior)
    cfg = CodeFitConfig(steps=a.steps)
    grid = grid_points(a.resolution)
    rows = []
    for split in ("seen", "unseen"):
        shapes = load_shape_set(a.shapes, split)
        if split == "seen" and len(shapes.meshes) != len(prior.latents):
            print(f"prior_unseen: error: {a.prior} has {len(prior.latents)} codes, {a.shapes} {len(shapes.meshes)} seen meshes",
                  file=sys.stderr)
            return 2
        for i, ((v, f), name) in enumerate(tqdm(list(zip(shapes.meshes, shapes.names)), desc=split)):
            p, s = sample_sdf(v, f, SamplingConfig(), np.random.default_rng(1000 + i), name)
            p, s = torch.from_numpy(p), torch.from_numpy(s)
            occ = mesh_occupancy(v, f, grid)
            z, fit_err = fit_code(prior, p, s, cfg)
            k, near_err = nearest_code(prior, p, s, cfg.clamp_delta)
            row = {"split": split, "shape": name, "fit_iou": volumetric_iou(occ, decoder_occupancy(prior.decoder, z, grid)),
                   "fit_l1": fit_err, "nearest": prior.shape_names[k], "nearest_l1": near_err,
                   "nearest_iou": volumetric_iou(occ, decoder_occupancy(prior.decoder, prior.latents[k], grid))}
            if split == "seen":
                row["own_iou"] = volumetric_iou(occ, decoder_occupancy(prior.decoder, prior.latents[i], grid))
            rows.append(row)
    print(f"{a.prior} prior on {a.shapes}, IoU at {a.resolution}^3, mean / median / min over meshes:")
    print("| meshes | n | own training code | fitted code | nearest training code |\n|---|---|---|---|---|")
    stat = lambda xs: f"{np.mean(xs):.3f} / {np.median(xs):.3f} / {np.min(xs):.3f}"
    for split in ("seen", "unseen"):
        r = [x for x in rows if x["split"] == split]
        own = stat([x["own_iou"] for x in r]) if split == "seen" else "-"
        print(f"| {split} | {len(r)} | {own} | {stat([x['fit_iou'] for x in r])} | {stat([x['nearest_iou'] for x in r])} |")
    if a.out:
        Path(a.out).parent.mkdir(parents=True, exist_ok=True)
        Path(a.out).write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
