"""Instance masks of several models on the same scenes, one labelled figure: a row per scene, the input and the truth
first, then a column per model (its name and its instance count in each label). Feed-forward, as each model ships.

    python3 scripts/instance_figure.py cars_keep runs/s72/ship_rescue40 --names "cars_keep,+ rescue 40" \\
        --data data/cars_novel_val --split val --differ 6 --out benchmarks/rescue_novel_cars.png

``--differ N`` shows the first N scenes (in split order, of the first ``--limit``) where the models' counts differ;
``--scenes i,j,...`` names them instead.
"""
from __future__ import annotations

import argparse

import numpy as np
import torch

from prismonet.data.dataset import SceneDataset
from prismonet.model.io import load_model
from prismonet.viz.mask_comparison import mask_comparison_figure


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("models", nargs="+", help="run folders or shipped names")
    ap.add_argument("--names", default=None, help="comma-separated column labels (default: the model arguments)")
    ap.add_argument("--data", required=True)
    ap.add_argument("--split", default="val")
    ap.add_argument("--scenes", default=None, help="comma-separated scene indices")
    ap.add_argument("--differ", type=int, default=6, help="without --scenes: the first N scenes where the counts differ")
    ap.add_argument("--limit", type=int, default=256, help="scenes searched for --differ")
    ap.add_argument("--out", required=True, help="PNG path")
    args = ap.parse_args()
    from prismonet.threads import use_free_cores

    use_free_cores(exit_on_error=True)  # the cores others leave free; PRISMONET_THREADS=N to choose
    names = args.names.split(",") if args.names else args.models
    if len(names) != len(args.models):
        raise SystemExit(f"--names: {len(names)} labels for {len(args.models)} models")
    ds = SceneDataset(args.data, split=args.split)
    try:
        idx = [int(i) for i in args.scenes.split(",")] if args.scenes else list(range(min(args.limit, len(ds))))
    except ValueError:
        raise SystemExit(f"--scenes: expected comma-separated scene indices, got {args.scenes!r}") from None
    if not idx or any(not 0 <= i < len(ds) for i in idx):
        raise SystemExit(f"--scenes: indices must be within the {len(ds)} scenes of {args.data} ({args.split}), got {idx}")
    models = [load_model(m)[0].eval() for m in args.models]
    b = ds.batch(idx)
    with torch.no_grad():
        inst = [m(b.rgb, b.K, b.T_world_cam, b.ground_z).composite.instance.numpy() for m in models]
    if not args.scenes:
        counts = np.stack([[len(np.unique(x[i])) - (0 in x[i]) for i in range(len(idx))] for x in inst])
        rows = [i for i in range(len(idx)) if len(set(counts[:, i])) > 1][: args.differ]
        if not rows:
            raise SystemExit(f"no scene among the first {len(idx)} where the models' counts differ")
    else:
        rows = list(range(len(idx)))
    path = mask_comparison_figure(b.rgb.numpy()[rows], b.instance.numpy()[rows], [(n, x[rows]) for n, x in zip(names, inst)], args.out)
    print(f"wrote {path}: scenes {[idx[i] for i in rows]}")


if __name__ == "__main__":
    main()
