"""``prismonet distill RUN DATA --out DIR``: self-distillation targets (``prismonet.model.distill``)."""

from __future__ import annotations

import argparse


def cmd_distill(args) -> int:
    from prismonet.data.dataset import SceneDataset
    from prismonet.evaluation.evaluate import check_compatible
    from prismonet.model.color_fit import ColorFitConfig
    from prismonet.model.distill import fit_targets, weights_digest
    from prismonet.model.io import load_model
    from prismonet.model.search import SearchConfig

    if args.batch <= 0:
        raise ValueError(f"--batch must be positive, got {args.batch}")
    search_cfg, color_cfg = SearchConfig(rounds=args.search), ColorFitConfig(args.fit_color)  # validate first
    model, info = load_model(args.checkpoint)
    ds = SceneDataset(args.data, split=args.split)
    check_compatible(model, info, ds)
    count = len(ds) if args.count is None else args.count
    meta = {"model": str(args.checkpoint), "model_digest": weights_digest(model), "data": str(args.data), "split": args.split}
    s = fit_targets(model, ds, args.out, count, search_cfg, color_cfg, batch_size=args.batch, progress=not args.quiet, meta=meta)
    extra = f"; fit score {s['score_before']:.4f} -> {s['score_after']:.4f} on the chunks made now" if "score_before" in s else ""
    print(f"distillation targets for {s['scenes']} scenes of {args.data} [{args.split}] in {args.out}{extra}")
    return 0


def add_parsers(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("distill", help="self-distillation targets: the test-time search and colour fit on training scenes (resumable)")
    p.add_argument("checkpoint", help="trained model: run folder, .safetensors, or 'shipped'")
    p.add_argument("data", help="dataset whose scenes to fit (RGB-D only is read)")
    p.add_argument("--out", required=True, help="folder of target chunks; rerun the same command to resume")
    p.add_argument("--split", default="train")
    p.add_argument("--count", type=int, default=None, help="fit the first N scenes of the split (default: all)")
    p.add_argument("--search", type=int, default=3, help="pose-search rounds (as evaluate --search)")
    p.add_argument("--fit-color", type=int, default=50, help="colour-fit steps (as evaluate --fit-color)")
    p.add_argument("--batch", type=int, default=16)
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=cmd_distill, outputs=[("out", "dir")])
