"""Choose the pruning rule on a validation split: decode every scene once with the test-time steps,
then prune that decoding with each rule of a small grid (``prismonet.model.prune``; pruning casts no
ray, so one decoding serves every rule) and score each with the evaluation's own measures.

    python3 scripts/prune_sweep.py runs/clevr1to8 data/clevr1to8 --split val --limit 96 --search 3 --fit-color 50 \
        --out runs/prune_sweep_1to8.json
"""

from __future__ import annotations

import argparse
import itertools
import json
from pathlib import Path

import numpy as np
from tqdm import tqdm

from prismonet.data.dataset import SceneDataset
from prismonet.evaluation.metrics import count_metrics, detection_metrics
from prismonet.model.inference import InferenceConfig, infer
from prismonet.model.io import load_model
from prismonet.model.prune import prune
from prismonet.model.stopping import StopRule


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("model")
    ap.add_argument("data")
    ap.add_argument("--split", default="val")
    ap.add_argument("--limit", type=int, default=96)
    ap.add_argument("--batch", type=int, default=16)
    ap.add_argument("--extra-slots", type=int, default=0)
    ap.add_argument("--search", type=int, default=0)
    ap.add_argument("--search-coarse", type=int, default=0)
    ap.add_argument("--search-grid", type=int, default=0)
    ap.add_argument("--search-scales", default=None, help="the search's trial scales (comma-separated; default: the search's)")
    ap.add_argument("--search-shapes", type=int, default=0)
    ap.add_argument("--fit-color", type=int, default=0)
    ap.add_argument("--color-only", action="store_true", help="the decoding and the rule read colour alone")
    ap.add_argument("--color-tols", default="0.1,0.25", help="the grid's colour tolerances (comma-separated)")
    ap.add_argument("--gains", default="1,5,10,25", help="the grid's least gains in pixels (comma-separated)")
    ap.add_argument("--out", required=True)
    args = ap.parse_args()
    from prismonet.threads import use_free_cores

    use_free_cores(exit_on_error=True)  # the cores others leave free; PRISMONET_THREADS=N to choose
    model, _ = load_model(args.model)
    ds = SceneDataset(args.data, split=args.split)
    n = min(args.limit, len(ds))
    cfg = InferenceConfig.of(extra_slots=args.extra_slots, search=args.search, search_coarse=args.search_coarse,
                             search_grid=args.search_grid, fit_color=args.fit_color, use_depth=not args.color_only,
                             search_scales=None if args.search_scales is None else [float(v) for v in args.search_scales.split(",")],
                             search_shapes=args.search_shapes)
    colors = [float(v) for v in args.color_tols.split(",")]
    gains = [int(v) for v in args.gains.split(",")]
    depths = (StopRule().depth_tol,) if args.color_only else (0.05, 0.1, 0.25, 0.5)  # colour alone: depth is never read
    grid = [StopRule(color_tol=c, depth_tol=d, min_gain=g) for c, d, g in itertools.product(colors, depths, gains)]
    full_inst, gt_inst = [], []
    pruned_inst, kept = {r: [] for r in grid}, {r: [] for r in grid}
    for s in tqdm(range(0, n, args.batch), desc="decode"):
        b = ds.batch(list(range(s, min(s + args.batch, n))))
        out = infer(model, b, cfg)
        full_inst.append(out.composite.instance.numpy())
        gt_inst.append(b.instance.numpy())
        depth = None if args.color_only else b.depth
        for r in grid:
            p = prune(out, b.rgb, depth, r)
            pruned_inst[r].append(p.composite.instance.numpy())
            kept[r].append(p.latents.params.active.sum(1).numpy())
    gt = np.concatenate(gt_inst)
    row = lambda inst: {**detection_metrics(inst, gt), **count_metrics(inst, gt)}
    rows = [{"rule": "no pruning", "slots": float(model.cfg.num_slots), **row(np.concatenate(full_inst))}]
    for r in grid:
        rows.append({"rule": r.record(), "slots": float(np.concatenate(kept[r]).mean()), **row(np.concatenate(pruned_inst[r]))})
    Path(args.out).write_text(json.dumps({"model": args.model, "data": args.data, "split": args.split, "scenes": n,
                                          "inference": cfg.record(), "rows": rows}, indent=1))
    print("| rule | slots | AP0.5 | AP0.5 unf. | AR0.5 | allObj | count exact | count bias |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        name = r["rule"] if isinstance(r["rule"], str) else "c{color_tol} d{depth_tol} g{min_gain}".format(**r["rule"])
        print(f"| {name} | {r['slots']:.2f} | {r['AP0.5']:.3f} | {r['AP0.5_unfiltered']:.3f} | {r['AR0.5']:.3f} | "
              f"{r['allObj']:.3f} | {r['count_exact']:.3f} | {r['count_bias']:+.2f} |")


if __name__ == "__main__":
    main()
