"""Where the image error of a decoding lies: object outlines, object interiors, the ground.

For each decoding (``--decodings``: ``|``-separated sets of ``evaluate`` flags, "" = feed-forward) on the first
``--limit`` scenes of a split: the image PSNR (mean over scenes, as ``evaluate``), the share of the summed squared
colour error on pixels within ``--band`` pixels of a true outline (any instance boundary, the ground's included),
inside true objects away from outlines, and on the ground away from outlines; and the PSNR each scene would have
if one part's error were zero (the most a fix of that part alone can give).

    python3 scripts/psnr_parts.py clevr3 data/clevr3 --split val --limit 256 --decodings "|--fit-color 50"
"""

from __future__ import annotations

import argparse
import json
import shlex
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from tqdm import tqdm

from prismonet.cli.common import add_inference_args, inference_config
from prismonet.data.dataset import SceneDataset
from prismonet.model.inference import InferenceConfig, infer
from prismonet.model.io import load_model


def outline_band(instance: torch.Tensor, band: int) -> torch.Tensor:
    """``(B, H, W)`` bool: pixels within ``band`` pixels (square neighbourhood) of a change of ``instance (B, H, W)``."""
    x = instance[:, None].float()
    k = 2 * band + 1
    hi = F.max_pool2d(x, k, stride=1, padding=band)
    lo = -F.max_pool2d(-x, k, stride=1, padding=band)
    return (hi != lo)[:, 0]


def decoding_config(flags: str) -> InferenceConfig:
    """``evaluate``'s test-time flags (``prismonet.cli.common.add_inference_args``) to an ``InferenceConfig``."""
    ap = argparse.ArgumentParser(prog="--decodings")
    add_inference_args(ap)
    return inference_config(ap.parse_args(shlex.split(flags)))


def psnr(se_sum: np.ndarray, pixels: int) -> float:
    """Mean over scenes of the PSNR of per-scene summed squared errors over ``pixels`` values."""
    return float(np.mean(10 * np.log10(pixels / np.maximum(se_sum, 1e-12))))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("model")
    ap.add_argument("data")
    ap.add_argument("--split", default="val")
    ap.add_argument("--limit", type=int, default=256)
    ap.add_argument("--batch", type=int, default=64)
    ap.add_argument("--band", type=int, default=1)
    ap.add_argument("--decodings", default="", help="'|'-separated evaluate flags per decoding ('' = feed-forward)")
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    from prismonet.threads import use_free_cores

    use_free_cores(exit_on_error=True)  # the cores others leave free; PRISMONET_THREADS=N to choose
    model, _ = load_model(args.model)
    ds = SceneDataset(args.data, split=args.split)
    n = min(args.limit, len(ds))
    rows = []
    for flags in args.decodings.split("|"):
        cfg = decoding_config(flags)
        parts = {"outline": [], "interior": [], "ground": []}
        for s in tqdm(range(0, n, args.batch), desc=flags or "feed-forward"):
            b = ds.batch(list(range(s, min(s + args.batch, n))))
            out = infer(model, b, cfg)
            se = ((out.composite.image.detach() - b.rgb) ** 2).sum(1)  # (B, H, W)
            edge = outline_band(b.instance, args.band)
            obj = (b.instance > 0) & ~edge
            ground = (b.instance == 0) & ~edge
            for name, m in (("outline", edge), ("interior", obj), ("ground", ground)):
                parts[name].append((se * m).sum((1, 2)).numpy())
        per = {k: np.concatenate(v) for k, v in parts.items()}
        total = sum(per.values())
        H, W = ds.batch([0]).rgb.shape[-2:]
        values = 3 * H * W
        row = {"decoding": flags or "feed-forward", "scenes": n, "PSNR": psnr(total, values)}
        for k in per:
            row[f"share_{k}"] = float(per[k].sum() / total.sum())
            row[f"PSNR_without_{k}"] = psnr(total - per[k], values)
        rows.append(row)
    print(f"| decoding | PSNR | outline share | interior share | ground share | PSNR, outlines exact | interiors exact | ground exact |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['decoding']} | {r['PSNR']:.2f} | {r['share_outline']:.2f} | {r['share_interior']:.2f} | "
              f"{r['share_ground']:.2f} | {r['PSNR_without_outline']:.2f} | {r['PSNR_without_interior']:.2f} | "
              f"{r['PSNR_without_ground']:.2f} |")
    if args.out:
        Path(args.out).write_text(json.dumps({"model": args.model, "data": args.data, "split": args.split,
                                              "band": args.band, "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
