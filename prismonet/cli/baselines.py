"""``prismonet baselines``: the paper's 2-D baselines on the same data, scored by the same measures."""

from __future__ import annotations

import json
from pathlib import Path


def cmd_train(args) -> int:
    from prismonet.baselines.train import BaselineTrainConfig, train_baseline
    from prismonet.config import load_config

    cfg = load_config(BaselineTrainConfig, args.config, [f"name={args.name}", *args.set])
    s = train_baseline(cfg, args.out, progress=not args.quiet)
    print(json.dumps(s))
    print(f"run folder: {args.out}  (checkpoint.safetensors, log.jsonl, tb/); rerun the same command to resume")
    return 0


def cmd_evaluate(args) -> int:
    from prismonet.baselines.train import evaluate_baseline

    r = evaluate_baseline(args.run, args.data, args.split, args.limit)
    keys = ("AP0.5", "AR0.5", "AP0.5_unfiltered", "ARI", "ARI-FG", "img_RMSE")
    print("| baseline | " + " | ".join(keys) + " |\n" + "|---" * (len(keys) + 1) + "|")
    print(f"| {r['baseline']} | " + " | ".join(f"{r[k]:.3f}" for k in keys) + " |")
    print(f"({r['scenes']} scenes of {args.data} [{args.split}]; instances: argmax of the slot masks, the slot covering most ground is the background)")
    if args.json:
        from prismonet.files import write_atomic

        write_atomic(args.json, json.dumps(r, indent=2))
        print(f"wrote {args.json}")
    return 0


def cmd_figure(args) -> int:
    from prismonet.baselines.compare import compare_masks

    print(f"wrote {compare_masks(args.runs, args.data, args.out, args.split, args.scenes, args.model)}")
    return 0


def add_parsers(sub) -> None:
    from prismonet.baselines.train import BASELINES
    from prismonet.files import arg_int

    bl = sub.add_parser("baselines", help="the paper's 2-D baselines (Slot Attention, MONet, GENESIS): train, evaluate")
    bsub = bl.add_subparsers(dest="baselines_command", required=True)
    tr = bsub.add_parser("train", help="train a baseline on a dataset's training split (resumable)")
    tr.add_argument("name", choices=BASELINES)
    tr.add_argument("--out", required=True, help="run folder; rerunning resumes from its checkpoint")
    tr.add_argument("--config", help="JSON file of BaselineTrainConfig fields")
    tr.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override, e.g. steps=2000 or data=data/clevr3")
    tr.add_argument("--quiet", action="store_true")
    tr.set_defaults(func=cmd_train, outputs=[("out", "dir")])
    ev = bsub.add_parser("evaluate", help="AP0.5, AR0.5, ARI, ARI-FG and image RMSE of a trained baseline")
    ev.add_argument("run", help="the baseline's run folder")
    ev.add_argument("data", help="packed or folder dataset")
    ev.add_argument("--split", default="test")
    ev.add_argument("--limit", type=arg_int(1), help="only the first N scenes")
    ev.add_argument("--json", help="also write the results here")
    ev.set_defaults(func=cmd_evaluate, outputs=[("json", "file")])
    fig = bsub.add_parser("figure", help="each baseline's slot masks beside PriSMONet's instances on the same scenes")
    fig.add_argument("runs", nargs="+", help="baseline run folders")
    fig.add_argument("--data", required=True, help="packed or folder dataset")
    fig.add_argument("--split", default="test")
    fig.add_argument("--scenes", type=arg_int(1, 64), default=6)
    fig.add_argument("--model", default="shipped", help="PriSMONet model: a name, run folder or stem (default: the shipped one)")
    fig.add_argument("--out", required=True, help="PNG to write")
    fig.set_defaults(func=cmd_figure, outputs=[("out", "image")])
