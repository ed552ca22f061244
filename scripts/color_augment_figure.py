"""What the training colour augmentations do, one labelled figure: per scene (of the training split unless ``--split``), the image as rendered, turned
about the grey axis (``TrainConfig.hue_rotate``) and with its objects recoloured from depth (``TrainConfig.recolor_objects``).

    python3 scripts/color_augment_figure.py data/cars --scenes 6 --out benchmarks/color_augment_cars.png
"""
from __future__ import annotations

import argparse
import sys

import numpy as np
import torch


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("data", help="a dataset folder")
    ap.add_argument("--split", default="train")
    ap.add_argument("--scenes", type=int, default=6, help="how many of the first training scenes")
    ap.add_argument("--hue", type=float, default=180.0, help="the largest turn, degrees")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", required=True, help="PNG path")
    args = ap.parse_args(argv)
    from prismonet.threads import use_free_cores

    if argv is None:  # the command line; a caller passing argv (a test) keeps its own threads
        use_free_cores(exit_on_error=True)  # the cores others leave free; PRISMONET_THREADS=N to choose
    if args.scenes <= 0 or not 0 < args.hue <= 180:
        print(f"color_augment_figure: error: --scenes must be positive and --hue in (0, 180], got {args.scenes} and {args.hue}",
              file=sys.stderr)
        return 2

    from prismonet.data.dataset import DatasetError, SceneDataset
    from prismonet.data.hue import random_angles, rotate_hue
    from prismonet.data.recolor import batch_regions, recolor_regions
    from prismonet.files import write_image
    from prismonet.model.config import ModelConfig
    from prismonet.viz.decomposition import labelled_panel

    try:
        ds = SceneDataset(args.data, args.split)
    except DatasetError as e:
        print(f"color_augment_figure: error: {e}", file=sys.stderr)
        return 2
    b = ds.batch(list(range(min(args.scenes, len(ds)))))
    g = torch.Generator().manual_seed(args.seed)
    turned = rotate_hue(b.rgb, random_angles(len(b), args.hue, g))
    recoloured = recolor_regions(b.rgb, batch_regions(b, ModelConfig().far_depth), g)  # the models' far clip
    to8 = lambda t: (t.clamp(0, 1).permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)
    rows = [np.concatenate([labelled_panel(to8(img[i]), name, (160, 160)) for name, img in
                            (("as rendered", b.rgb), (f"hue turned (<= {args.hue:g} deg)", turned), ("objects recoloured", recoloured))], 1)
            for i in range(len(b))]
    write_image(args.out, np.concatenate(rows, 0)[..., ::-1])
    print(f"wrote {args.out} ({len(b)} scenes)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
