"""Turn a split of a synthetic dataset into labelled "photos" (PNG + label JSON, ``realdata.labels``'s format).

The real-photo path (``prismonet real evaluate``) has five labelled photos and no validation set: nothing may be
chosen on them. Synthetic scenes rendered larger than the model's input and more crowded than its training
scenes stand in for them. Each becomes a PNG and a label with one box per object whose visible part is at least
``--min-fraction`` of the image (boxes from the instance mask, the outermost pixels' corners, as the hand labels);
every smaller visible object gets an ``ignore`` box (a detection there is neither a hit nor a false one: before
session 86 these objects were simply left out, so finding them counted against the model and its count), and the camera's true elevation above the table (``elevation_deg``). ``--uneven S`` darkens and brightens each photo
by a smooth field, as uneven light and lens vignetting do in real photos: a linear gradient of ±S in a random
direction times a radial fall-off to 1 - S/2 in the corners (seeded per photo). ``--exposure LO,HI`` makes each photo
darker or brighter by one factor, log-uniform in [LO, HI] (clipped), as a camera's exposure does. ``--ground-gray
LO,HI`` repaints the table of each photo (every pixel no object covers, shadows kept) to a grey level uniform in
[LO, HI] of full scale, keeping its tint, while the objects keep their own: a dark table under bright objects (coins
on black velvet) asks the colour normalisation for a gain that an even exposure change never does. ``--gray`` makes
each photo grey (its luminance, Rec. 601 weights), last: objects that share the table's hue, as coins do.

    python3 -m prismonet data clevr --randomize --randomize-range focal_scale=0.8,1.8 \
        --randomize-range camera_elevation_deg=18,85 --objects 20 --min-objects 8 --area 4 --size 192 --shadows \
        --split 0,80,80 --seed 52 --out data/crowded
    python3 scripts/labelled_photos.py data/crowded --split val --out data/crowded_photos/val
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np

from prismonet.data.gray import LUMA


def camera_elevation_deg(T_world_cam: np.ndarray) -> float:
    """Degrees below the horizon of the camera's optical axis (world z up)."""
    f = T_world_cam[:3, 2]
    return math.degrees(math.asin(max(-1.0, min(1.0, -float(f[2]) / float(np.linalg.norm(f))))))


def scene_label(instance: np.ndarray, min_fraction: float) -> tuple[list[list[float]], list[list[float]]]:
    """Boxes ``[x0, y0, x1, y1]`` (pixel corners) of the visible objects: those with at least ``min_fraction`` of the
    image, and the smaller ones (to be ignored)."""
    boxes, small = [], []
    for k in np.unique(instance[instance > 0]):
        v, u = np.nonzero(instance == k)
        box = [float(u.min()) - 0.5, float(v.min()) - 0.5, float(u.max()) + 0.5, float(v.max()) + 0.5]
        (boxes if len(u) >= min_fraction * instance.size else small).append(box)
    return boxes, small


def uneven_light(shape: tuple[int, int], strength: float, rng: np.random.Generator) -> np.ndarray:
    """``(H, W, 1)`` multiplicative field: ``(1 + S (cos t x + sin t y)) (1 - S / 4 (x^2 + y^2))`` on ``[-1, 1]^2``."""
    H, W = shape
    y, x = np.meshgrid(np.linspace(-1, 1, H), np.linspace(-1, 1, W), indexing="ij")
    t = rng.uniform(0, 2 * np.pi)
    return ((1 + strength * (np.cos(t) * x + np.sin(t) * y)) * (1 - strength / 4 * (x**2 + y**2)))[..., None]


def main() -> None:
    import cv2

    from prismonet.data.dataset import SceneDataset

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("data")
    ap.add_argument("--split", default="val")
    ap.add_argument("--out", required=True)
    ap.add_argument("--limit", type=int, default=None)
    ap.add_argument("--min-fraction", type=float, default=0.003, help="least visible part of the image for a labelled object")
    ap.add_argument("--uneven", type=float, default=0.0, help="strength of the uneven light field (default 0: none)")
    ap.add_argument("--exposure", default=None, metavar="LO,HI",
                    help="multiply each photo by an exposure drawn log-uniformly in [LO, HI], then clip (default: none)")
    ap.add_argument("--ground-gray", default=None, metavar="LO,HI",
                    help="repaint the table to a grey level uniform in [LO, HI] (0-1), keeping its tint and shadows")
    ap.add_argument("--gray", action="store_true", help="make each photo grey (its luminance), last")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    from prismonet.threads import use_free_cores

    use_free_cores(exit_on_error=True)  # the cores others leave free; PRISMONET_THREADS=N to choose
    ds = SceneDataset(args.data, args.split)
    out = Path(args.out)
    (out / "photos").mkdir(parents=True, exist_ok=True)
    n = len(ds) if args.limit is None else min(args.limit, len(ds))
    counts = []
    for i in range(n):
        b = ds.batch([i])
        rgb = b.rgb[0].permute(1, 2, 0).numpy()
        rng = np.random.default_rng([args.seed, i])
        if args.ground_gray:
            lo, hi = (float(v) for v in args.ground_gray.split(","))
            table = b.instance[0].numpy() == 0
            rgb[table] *= float(rng.uniform(lo, hi)) / max(float(b.ground_color[0].mean()), 1e-3)
        if args.uneven:
            rgb = rgb * uneven_light(rgb.shape[:2], args.uneven, rng)
        if args.exposure:
            lo, hi = (float(v) for v in args.exposure.split(","))
            rgb = rgb * float(np.exp(rng.uniform(np.log(lo), np.log(hi))))
        if args.gray:
            rgb = np.repeat((np.clip(rgb, 0, 1) @ np.array(LUMA))[..., None], 3, -1)
        rgb = (np.clip(rgb, 0, 1) * 255).round().astype(np.uint8)
        cv2.imwrite(str(out / "photos" / f"scene_{i:04d}.png"), rgb[..., ::-1])
        boxes, small = scene_label(b.instance[0].numpy(), args.min_fraction)
        counts.append(len(boxes))
        label = {"photo": f"photos/scene_{i:04d}.png", "source": f"{args.data} {args.split} scene {i}",
                 "elevation_deg": round(camera_elevation_deg(b.T_world_cam[0].double().numpy()), 2),
                 "objects": [{"box": bx, "colour": "synthetic", "kind": "object"} for bx in boxes], "ignore": small}
        (out / f"scene_{i:04d}.json").write_text(json.dumps(label, indent=1))
    print(f"wrote {n} labelled photos to {out}: {sum(counts)} objects, {min(counts)}-{max(counts)} per photo")


if __name__ == "__main__":
    main()
