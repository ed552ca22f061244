"""Sweep settings of the test-time pose search (``prismonet.model.search``) and colour fit
(``prismonet.model.color_fit``) on a dataset split.

    python3 scripts/search_sweep.py data/clevr3 --split val --limit 512 "rounds=0" "shifts=(),yaws=(),rounds=1"
    python3 scripts/search_sweep.py data/clevr3 --split test --limit 128 --passes 3 "rounds=0" "" "fit_color=50"

Each argument is a set of ``SearchConfig`` fields (Python literals), plus optionally ``fit_color=K``
and ``refine=K`` (default: ``--fit-color`` and ``--refine``); one JSON line of measures per setting
and pass. With ``--passes N`` the settings run N times interleaved (all settings, then all again) in
one process, and a last table gives each setting's median time per scene.
"""

from __future__ import annotations

import argparse
import ast
import json
import statistics

import torch

from prismonet.data.dataset import SceneDataset
from prismonet.evaluation.evaluate import evaluate_model
from prismonet.model.color_fit import ColorFitConfig
from prismonet.model.inference import InferenceConfig
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
    ap.add_argument("--refine", type=int, default=0, metavar="K", help="refinement steps after the search")
    ap.add_argument("--fit-color", type=int, default=0, metavar="K", help="colour-fit steps after the search and refinement")
    ap.add_argument("--passes", type=int, default=1, help="run every setting this many times, interleaved")
    ap.add_argument("--batch", type=int, default=16, help="scenes per batch (default 16, as evaluate's)")
    args = ap.parse_args()
    from prismonet.threads import use_free_cores

    use_free_cores(exit_on_error=True)  # the cores others leave free; PRISMONET_THREADS=N to choose
    runs = []
    for text in args.settings:  # validate all before running any
        try:
            fields = parse_setting(text)
            refine, fit = fields.pop("refine", args.refine), fields.pop("fit_color", args.fit_color)
            runs.append((text, SearchConfig(**fields), RefineConfig(refine), ColorFitConfig(fit)))
        except (SyntaxError, ValueError, TypeError) as e:
            ap.error(f"setting {text!r}: {str(e).splitlines()[0]}")
    model, info = load_model(args.checkpoint)
    ds = SceneDataset(args.data, split=args.split)
    times: dict[str, list[float]] = {text: [] for text, *_ in runs}
    for p in range(args.passes):
        for text, search_cfg, refine_cfg, color_cfg in runs:
            with torch.no_grad():
                r = evaluate_model(model, ds, batch_size=args.batch, limit=args.limit, progress=False, loss_cfg=training_loss_config(info),
                                   inference=InferenceConfig(search=search_cfg, refine=refine_cfg, color_fit=color_cfg))
            times[text].append(r["seconds_per_scene"])
            print(json.dumps({"setting": text, "pass": p + 1, "refine": refine_cfg.steps, "fit_color": color_cfg.steps,
                              **{k: round(r[k], 4) for k in KEYS}}), flush=True)
    if args.passes > 1:
        base = statistics.median(times[runs[0][0]])
        print(f"\n| setting | ms per scene ({args.passes} passes) | median | speed-up over {runs[0][0] or '(default)'!r} |\n|---|---|---|---|")
        for text, ts in times.items():
            med = statistics.median(ts)
            print(f"| {text or '(default)'} | {' / '.join(f'{1000 * t:.0f}' for t in ts)} | {1000 * med:.0f} | {base / med:.2f}x |")


if __name__ == "__main__":
    main()
