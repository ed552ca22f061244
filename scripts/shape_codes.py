"""Which shape does the encoder predict? Nearest prior code (L2) of each matched slot's z_sh, by true category.

    python3 scripts/shape_codes.py RUN DATA [--split test] [--limit 400] [--search R] [--set shape_trials=true --set shape_yaws=[30,60]]
    python3 scripts/shape_codes.py shipped data/clevr3 --split val --limit 64 --search 3 --set ... --true-parts position,yaw --category 2

For every predicted object matched to a true one at IoU 0.5, the category of the prior's training
code nearest to its shape latent, against the true category (a confusion table), and the median
distance to that nearest code. Answers whether cubes come out round because the prior cannot draw
them (then the codes would be right and the meshes wrong) or because the encoder does not ask for them.

``--true-parts`` (a diagnostic that reads the data's poses): before the search, the slot that each true object of
``--category`` takes (paired as L_pose pairs them) is given those parts of the object's true pose. It tells which part of
the pose the search fails to find (EVALUATION.md, session 75).
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
    ap.add_argument("--true-parts", default="", metavar="PARTS",
                    help="comma-separated parts of the true pose (position, yaw, scale) given to the slots of --category's objects before the search")
    ap.add_argument("--category", type=int, default=2, help="with --true-parts: the prior's category id (Clevr: 2, cubes)")
    ap.add_argument("--library", default="clevr", help="with --true-parts: the shape library whose yaw periods the true poses take")
    args = ap.parse_args(argv)
    from prismonet.threads import use_free_cores

    if argv is None:  # the command line; a caller passing argv (a test) keeps its own threads
        use_free_cores(exit_on_error=True)  # the cores others leave free; PRISMONET_THREADS=N to choose
    parts = [t for t in args.true_parts.split(",") if t]
    if any(t not in ("position", "yaw", "scale") for t in parts):
        print(f"shape_codes: error: --true-parts takes position, yaw and scale, got {args.true_parts!r}", file=sys.stderr)
        return 2
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
        if parts:
            from prismonet.shapes.symmetry import library_yaw_periods

            periods = library_yaw_periods(args.library)
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
            if parts:
                out = _given_true_parts(model, out, b, parts, args.category, code_cat, periods)
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
    given = f", category {args.category} given its true {', '.join(parts)}" if parts else ""
    print(f"{n} scenes of {args.data} [{args.split}], search rounds {args.search} {args.set or ''}{given}: nearest prior code of matched slots")
    print("| true \\ nearest code | " + " | ".join(CATS) + " | share right | median distance to nearest code |")
    print("|---|---|---|---|---|---|")
    for t in range(3):
        row = conf[t]
        print(f"| {CATS[t]} | " + " | ".join(str(v) for v in row) + f" | {row[t] / max(row.sum(), 1):.3f} | {np.median(dist[t]) if dist[t] else float('nan'):.3f} |")
    spread = torch.cdist(codes, codes)
    print(f"(for scale: median distance between two different prior codes {spread[spread > 0].median():.3f})")
    return 0


def _given_true_parts(model, out, b, parts, category, code_cat, periods):
    """``out`` drawn again with the slot of each true object of ``category`` given ``parts`` of its true pose."""
    from prismonet.model.pose_targets import match_slots, posed_at_truth
    from prismonet.model.refine import render_latents
    from prismonet.render import SceneParams

    pe = out.latents.params
    pt, _ = posed_at_truth(pe, b, periods)
    q = SceneParams(*(None if t is None else t.clone() for t in (pe.z_sh, pe.z_tex, pe.position, pe.cos_sin, pe.scale, pe.axis, pe.active)))
    K = pe.scale.shape[1]
    for i in range(len(b)):
        slots, objs = match_slots(pe.position[i], b.obj_position[i], torch.arange(K), torch.arange(int(b.obj_count[i])))
        for k, g in zip(slots.tolist(), objs.tolist()):
            if int(code_cat[int(b.obj_shape[i, g])]) != category:
                continue
            for part, name in (("position", "position"), ("yaw", "cos_sin"), ("scale", "scale")):
                if part in parts:
                    getattr(q, name)[i, k] = getattr(pt, name)[i, k]
    H, W = b.rgb.shape[-2:]
    return render_latents(model, q, out.latents.bg_color, b.K, b.T_world_cam, b.ground_z, H, W)


if __name__ == "__main__":
    raise SystemExit(main())
