"""Sweep settings of the test-time pose search (``prismonet.model.search``) on a dataset split.

    python3 scripts/search_sweep.py data/clevr3 --split val --limit 512 "rounds=0" "shifts=(),yaws=(),rounds=1,decay=1"

Each argument is a set of ``SearchConfig`` fields (Python literals); one line of measures per setting.
"""

from __future__ import annotations

import argparse
import ast
import json

import torch

from prismonet.data.dataset import SceneDataset
from prismonet.evaluation.evaluate import evaluate_model
from prismonet.model.io import load_model, training_loss_config
from prismonet.model.refine import RefineConfig
from prismonet.model.search import SearchConfig

KEYS = ["AP0.5", "AR0.5", "F1_0.5", "allObj", "mAP", "PSNR", "SSIM", "depth_RMSE", "pos_err", "seconds_per_scene"]


def parse_setting(text: str) -> dict:
    """``"shifts=(-0.2,0.2),rounds=3"`` -> ``{"shifts": (-0.2, 0.2), "rounds": 3}`` (literals only)."""
    call = ast.parse(f"f({text})", mode="eval").body
    return {kw.arg: ast.literal_eval(kw.value) for kw in call.keywords}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("data")
    ap.add_argument("settings", nargs="+")
    ap.add_argument("--checkpoint", default="shipped")
    ap.add_argument("--split", default="val")
    ap.add_argument("--limit", type=int, default=512)
    ap.add_argument("--refine", type=int, default=0)
    args = ap.parse_args()
    cfgs = [SearchConfig(**parse_setting(s)) for s in args.settings]  # validate all before running any
    model, info = load_model(args.checkpoint)
    ds = SceneDataset(args.data, split=args.split)
    for text, cfg in zip(args.settings, cfgs):
        with torch.no_grad():
            r = evaluate_model(model, ds, limit=args.limit, progress=False, loss_cfg=training_loss_config(info),
                               refine_cfg=RefineConfig(args.refine), search_cfg=cfg)
        print(json.dumps({"setting": text, "refine": args.refine, **{k: round(r[k], 4) for k in KEYS}}), flush=True)


if __name__ == "__main__":
    main()
