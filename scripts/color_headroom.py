"""How much of a model's feed-forward image error is colour: its PSNR as it is, with the ground colour replaced by the
least-squares one (the image's mean over the pixels no object wins), and after the test-time colour fit (50 Adam steps
on the texture latents and the ground colour, the geometry held). A diagnosis; it reads the images only.

    python3 scripts/color_headroom.py runs/s57/c3x20k_fit9000_2p data/clevr3 --split val --limit 300
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from prismonet.allocator import keep_freed_memory
from prismonet.data.dataset import SceneDataset
from prismonet.model.color_fit import ColorFitConfig, fit_colors
from prismonet.model.inference import InferenceConfig, infer
from prismonet.model.io import load_model, training_loss_config


def psnr(pred: torch.Tensor, truth: torch.Tensor) -> list[float]:
    return (10 * torch.log10(1 / ((pred.double() - truth.double()) ** 2).flatten(1).mean(1))).tolist()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("model")
    ap.add_argument("data")
    ap.add_argument("--split", default="val")
    ap.add_argument("--limit", type=int, default=300)
    ap.add_argument("--batch", type=int, default=50)
    args = ap.parse_args()
    from prismonet.threads import use_free_cores

    use_free_cores(exit_on_error=True)  # the cores others leave free; PRISMONET_THREADS=N to choose
    keep_freed_memory()
    model, info = load_model(args.model)
    model.eval()
    ds = SceneDataset(args.data, split=args.split)
    n = min(args.limit, len(ds))
    rows: dict[str, list[float]] = {"model": [], "least-squares ground colour": [], "colour fit": []}
    with torch.no_grad():
        for s in range(0, n, args.batch):
            b = ds.batch(list(range(s, min(s + args.batch, n))))
            out = infer(model, b, InferenceConfig(), training_loss_config(info), model.cfg.num_slots)
            img, hit = out.composite.image, out.composite.mask.bool()
            ground = (~hit).to(img.dtype)
            mean = (b.rgb * ground).sum((2, 3)) / ground.sum((2, 3)).clamp_min(1)
            rows["model"] += psnr(img, b.rgb)
            rows["least-squares ground colour"] += psnr(torch.where(hit, img, mean[:, :, None, None].expand_as(img)), b.rgb)
            rows["colour fit"] += psnr(fit_colors(model, out, b, ColorFitConfig()).composite.image, b.rgb)
    for k, v in rows.items():
        print(f"{k:30s} PSNR {np.mean(v):.3f}  ({n} scenes of {args.data} [{args.split}])")


if __name__ == "__main__":
    main()
