"""Choose the encoder's stop rule on a validation split: decode every scene once with all slots,
then read off, for each rule of a small grid, the slots a stopped encoder would keep
(``prismonet.model.stopping.stop_counts``; exact, as the slots before a stop do not depend on it),
and score them with the evaluation's own measures.

    python3 scripts/stop_sweep.py runs/clevr1to8 data/clevr1to8 --split val --limit 200 --out runs/stop_sweep.json
"""

from __future__ import annotations

import argparse
import itertools
import json
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from prismonet.data.dataset import SceneDataset
from prismonet.evaluation.metrics import count_metrics, detection_metrics
from prismonet.model.io import load_model
from prismonet.model.stopping import StopRule, keep_first, stop_counts


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("model")
    ap.add_argument("data")
    ap.add_argument("--split", default="val")
    ap.add_argument("--limit", type=int, default=200)
    ap.add_argument("--batch", type=int, default=16)
    ap.add_argument("--color-only", action="store_true", help="the rule reads colour alone")
    ap.add_argument("--out", required=True)
    args = ap.parse_args()
    from prismonet.threads import use_free_cores

    use_free_cores(exit_on_error=True)  # the cores others leave free; PRISMONET_THREADS=N to choose
    model, _ = load_model(args.model)
    ds = SceneDataset(args.data, split=args.split)
    n = min(args.limit, len(ds))
    grid = [StopRule(color_tol=c, depth_tol=d, erode=e, min_gain=g)
            for c, d, e, g in itertools.product((0.15, 0.25), (0.25, 0.5), (0, 1), (1, 5, 10))]
    full_inst, gt_inst, kept_inst = [], [], {r: [] for r in grid}
    kept = {r: [] for r in grid}
    for s in tqdm(range(0, n, args.batch), desc="decode"):
        b = ds.batch(list(range(s, min(s + args.batch, n))))
        with torch.no_grad():
            out = model(b.rgb, b.K, b.T_world_cam, b.ground_z)
        full_inst.append(out.composite.instance.numpy())
        gt_inst.append(b.instance.numpy())
        depth = None if args.color_only else b.depth
        for r in grid:
            c = stop_counts(r, out, b.rgb, depth)
            kept[r].append(c.numpy())
            kept_inst[r].append(keep_first(out, c).composite.instance.numpy())
    gt = np.concatenate(gt_inst)
    row = lambda inst: {**detection_metrics(inst, gt), **count_metrics(inst, gt)}
    rows = [{"rule": "no stop", "slots": float(model.cfg.num_slots), **row(np.concatenate(full_inst))}]
    for r in grid:
        rows.append({"rule": r.record(), "slots": float(np.concatenate(kept[r]).mean()), **row(np.concatenate(kept_inst[r]))})
    Path(args.out).write_text(json.dumps({"model": args.model, "data": args.data, "split": args.split, "scenes": n,
                                          "color_only": args.color_only, "rows": rows}, indent=1))
    print("| rule | slots | AP0.5 | AR0.5 | allObj | count exact |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        name = r["rule"] if isinstance(r["rule"], str) else "c{color_tol} d{depth_tol} e{erode} g{min_gain}".format(**r["rule"])
        print(f"| {name} | {r['slots']:.2f} | {r['AP0.5']:.3f} | {r['AR0.5']:.3f} | {r['allObj']:.3f} | {r['count_exact']:.3f} |")


if __name__ == "__main__":
    main()
