"""``prismonet train`` (the scene model from RGB-D) and ``prismonet distill`` (self-distillation
targets: the test-time steps run on training scenes, ``prismonet.model.distill``)."""

from __future__ import annotations

import json
import os
from pathlib import Path

from prismonet.cli.common import add_inference_args, inference_config


def cmd_train(args) -> int:
    from prismonet.config import load_config
    from prismonet.model.trainer import TrainConfig, train

    cfg = load_config(TrainConfig, args.config, args.set)
    summary = train(cfg, Path(args.out), progress=not args.quiet)
    if summary.get("world_size", 1) == 1 or int(os.environ.get("RANK", "0")) == 0:
        print(json.dumps(summary))
        print(f"run folder: {args.out}  (model.safetensors + model.json, checkpoint.safetensors, tb/, images/, log.jsonl)")
    return 0


def cmd_distill(args) -> int:
    from prismonet.data.dataset import SceneDataset
    from prismonet.evaluation.evaluate import check_compatible
    from prismonet.model.distill_fit import fit_targets, weights_digest
    from prismonet.model.io import load_model, training_loss_config

    if args.batch <= 0:
        raise ValueError(f"--batch must be positive, got {args.batch}")
    cfg = inference_config(args)  # validate first
    model, info = load_model(args.checkpoint)
    ds = SceneDataset(args.data, split=args.split)
    check_compatible(model, info, ds)
    count = len(ds) if args.count is None else args.count
    meta = {"model": str(args.checkpoint), "model_digest": weights_digest(model), "data": str(args.data), "split": args.split}
    s = fit_targets(model, ds, args.out, count, cfg, batch_size=args.batch, progress=not args.quiet, meta=meta,
                    loss_cfg=training_loss_config(info))
    extra = f"; fit score {s['score_before']:.4f} -> {s['score_after']:.4f} on the chunks made now" if "score_before" in s else ""
    print(f"distillation targets for {s['scenes']} scenes of {args.data} [{args.split}] in {args.out}{extra}")
    return 0


def add_parsers(sub) -> None:
    tr = sub.add_parser("train", help="train the scene model from RGB-D (resumable; works under torchrun)")
    tr.add_argument("config", help="JSON file of TrainConfig fields (e.g. configs/clevr3.json)")
    tr.add_argument("--out", required=True, help="run folder; rerunning resumes from its checkpoint")
    tr.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override, e.g. loss.blur=false")
    tr.add_argument("--quiet", action="store_true")
    tr.set_defaults(func=cmd_train, outputs=[("out", "dir")])

    p = sub.add_parser("distill", help="self-distillation targets: the test-time steps on training scenes (resumable)")
    p.add_argument("checkpoint", help="trained model: run folder, .safetensors, or 'shipped'")
    p.add_argument("data", help="dataset whose scenes to fit (RGB-D only is read)")
    p.add_argument("--out", required=True, help="folder of target chunks; rerun the same command to resume")
    p.add_argument("--split", default="train")
    p.add_argument("--count", type=int, default=None, help="fit the first N scenes of the split (default: all)")
    p.add_argument("--batch", type=int, default=16)
    p.add_argument("--quiet", action="store_true")
    add_inference_args(p, search=3, fit_color=50)
    p.set_defaults(func=cmd_distill, outputs=[("out", "dir")])
