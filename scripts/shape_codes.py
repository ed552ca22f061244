"""Which shape does the encoder predict? Nearest prior code (L2) of each matched slot's z_sh, by true category.

    python3 scripts/shape_codes.py RUN DATA [--split test] [--limit 400] [--search R] [--set shape_trials=true --set shape_yaws=[30,60]]

For every predicted object matched to a true one at IoU 0.5, the category of the prior's training
code nearest to its shape latent, against the true category (a confusion table), and the median
distance to that nearest code. Answers whether cubes come out round because the prior cannot draw
them (then the codes would be right and the meshes wrong) or because the encoder does not ask for them.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np
import torch

CATS = ("sphere", "cylinder", "cube")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run")
    ap.add_argument("data")
    ap.add_argument("--split", default="test")
    ap.add_argument("--limit", type=int, default=400)
    ap.add_argument("--search", type=int, default=0)
    ap.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE",
                    help="a SearchConfig field for the search, as JSON, e.g. shape_trials=true or shape_yaws=[30,60] (repeatable)")
    args = ap.parse_args(argv)
    if args.limit <= 0 or args.search < 0:
        print("shape_codes: error: --limit must be positive and --search non-negative", file=sys.stderr)
        return 2
    from prismonet.config import load_config
    from prismonet.data.dataset import SceneDataset
    from prismonet.evaluation.metrics import scene_detection
    from prismonet.model.io import load_model
    from prismonet.model.search import SearchConfig, search_latents

    try:  # ValueError covers the config's, the checkpoint's and the dataset's errors
        search_cfg = load_config(SearchConfig, "-", [f"rounds={args.search}", *args.set])
        model, _ = load_model(args.run)
        ds = SceneDataset(args.data, args.split)
    except (ValueError, FileNotFoundError) as e:
        print(f"shape_codes: error: {str(e).splitlines()[0]}", file=sys.stderr)
        return 2
    codes = model.prior.latents.detach()  # (27, D)
    code_cat = torch.tensor(model.prior.category_ids)
    n = min(args.limit, len(ds))
    conf = np.zeros((3, 3), np.int64)
    dist = {c: [] for c in range(3)}
    with torch.no_grad():
        for s in range(0, n, 16):
            b = ds.batch(list(range(s, min(s + 16, n))))
            out = model(b.rgb, b.K, b.T_world_cam, b.ground_z)
            if args.search:
                out = search_latents(model, out, b, search_cfg)
            z = out.latents.params.z_sh  # (B, N, D)
            d = torch.cdist(z, codes[None].expand(len(z), -1, -1))  # (B, N, 27)
            near = d.argmin(-1)
            for j in range(len(b)):
                for pk, gk in scene_detection(out.composite.instance[j].numpy(), b.instance[j].numpy(), 0.5)["pairs"]:
                    true = int(code_cat[int(b.obj_shape[j, gk - 1])])
                    pred = int(code_cat[int(near[j, pk - 1])])
                    conf[true, pred] += 1
                    dist[true].append(float(d[j, pk - 1].min()))
    print(f"{n} scenes of {args.data} [{args.split}], search rounds {args.search} {args.set or ''}: nearest prior code of matched slots")
    print("| true \\ nearest code | " + " | ".join(CATS) + " | share right | median distance to nearest code |")
    print("|---|---|---|---|---|---|")
    for t in range(3):
        row = conf[t]
        print(f"| {CATS[t]} | " + " | ".join(str(v) for v in row) + f" | {row[t] / max(row.sum(), 1):.3f} | {np.median(dist[t]) if dist[t] else float('nan'):.3f} |")
    spread = torch.cdist(codes, codes)
    print(f"(for scale: median distance between two different prior codes {spread[spread > 0].median():.3f})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
