"""Recall per shape model: of each shape's visible objects, the share found at IoU 0.5 (and misfitted, and touched by
any prediction), feed-forward as the model ships. Optionally with one shape re-rendered in another colour first.

    python3 scripts/shape_recall.py cars data/cars_novel_val --split val
    python3 scripts/shape_recall.py cars data/cars_novel_val --split val --limit 1000 \\
        --recolor 2 0.5107,0.4659,0.2264 0.4278,0.2088,0.2044      # the Beetle's yellow made a seen car's red

``--recolor SHAPE FROM TO`` multiplies the pixels of every object of that shape (found through the *true* instance
masks: a diagnostic, not an inference mode) per channel by ``TO / FROM``. The scenes are Lambertian under white light,
so that is the scene rendered with albedo ``TO`` instead of ``FROM`` (EVALUATION.md, session 73). Shape ids are the
dataset's (``obj_shape``; for an imported set, the order of its split's models in ``models.json``).
"""
from __future__ import annotations

import argparse
import collections
import sys

import numpy as np
import torch


def _color(text: str) -> torch.Tensor:
    try:
        c = torch.tensor([float(v) for v in text.split(",")])
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected three comma-separated numbers, got {text!r}") from None
    if c.shape != (3,) or (c <= 0).any():
        raise argparse.ArgumentTypeError(f"expected three positive numbers, got {text!r}")
    return c


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("model", help="a run folder or a shipped name")
    ap.add_argument("data")
    ap.add_argument("--split", default="val")
    ap.add_argument("--limit", type=int, default=None, help="the first N scenes (default: all)")
    ap.add_argument("--batch", type=int, default=50)
    ap.add_argument("--recolor", nargs=3, metavar=("SHAPE", "FROM", "TO"), default=None)
    args = ap.parse_args(argv)
    from prismonet.threads import use_free_cores

    if argv is None:  # the command line; a caller passing argv (a test) keeps its own threads
        use_free_cores(exit_on_error=True)  # the cores others leave free; PRISMONET_THREADS=N to choose
    recolor = None
    if args.recolor is not None:
        try:
            recolor = (int(args.recolor[0]), _color(args.recolor[1]), _color(args.recolor[2]))
        except (ValueError, argparse.ArgumentTypeError) as e:
            print(f"shape_recall: error: --recolor: {e}", file=sys.stderr)
            return 2
    if (args.limit is not None and args.limit <= 0) or args.batch <= 0:
        print("shape_recall: error: --limit and --batch must be positive", file=sys.stderr)
        return 2

    from prismonet.allocator import keep_freed_memory
    from prismonet.data.dataset import DatasetError, SceneDataset
    from prismonet.evaluation.metrics import instance_masks, iou_matrix
    from prismonet.model.inference import InferenceConfig, infer
    from prismonet.model.io import CheckpointError, load_model

    keep_freed_memory()
    try:
        model = load_model(args.model)[0]
        ds = SceneDataset(args.data, args.split)
    except (CheckpointError, DatasetError, FileNotFoundError) as e:
        print(f"shape_recall: error: {e}", file=sys.stderr)
        return 2
    model.eval()
    n = len(ds) if args.limit is None else min(args.limit, len(ds))
    stat: dict[int, list[int]] = collections.defaultdict(lambda: [0, 0, 0, 0])  # objects, found, misfit, touched
    with torch.no_grad():
        for s in range(0, n, args.batch):
            b = ds.batch(list(range(s, min(s + args.batch, n))))
            if recolor is not None:
                shape, src, dst = recolor
                for j in range(len(b)):
                    for k in range(b.obj_shape.shape[1]):
                        if int(b.obj_shape[j, k]) == shape:
                            m = b.instance[j] == k + 1
                            b.rgb[j][:, m] = (b.rgb[j][:, m] * (dst / src)[:, None]).clamp(0, 1)
            out = infer(model, b, InferenceConfig(), None, model.cfg.num_slots)
            pi, gi = out.composite.instance.numpy(), b.instance.numpy()
            for j in range(len(b)):
                pid, pm = instance_masks(pi[j])
                gid, gm = instance_masks(gi[j])
                iou = iou_matrix(pm, gm) if len(pid) and len(gid) else np.zeros((1, len(gid)))
                for col, g in enumerate(gid):
                    best = float(iou[:, col].max())
                    st = stat[int(b.obj_shape[j, int(g) - 1])]
                    st[0] += 1
                    st[1] += best > 0.5
                    st[2] += 0.3 < best <= 0.5
                    st[3] += best > 0.1
    print(f"{args.model} on {n} scenes of {args.data} [{args.split}]" + (f", shape {recolor[0]} recoloured" if recolor else ""))
    print("| shape | objects | found (IoU > 0.5) | misfit (0.3-0.5) | touched (> 0.1) |")
    print("|---|---|---|---|---|")
    for shape in sorted(stat):
        o, f, m, t = stat[shape]
        print(f"| {shape} | {o} | {f / o:.3f} | {m / o:.3f} | {t / o:.3f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
