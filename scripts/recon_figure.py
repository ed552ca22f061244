"""Several models' reconstructions of the same scenes, one labelled figure: a row per scene; the input image and its
depth (shaded, so that flat faces and corners show) first, then each model's rendered image and shaded depth. The scenes
are the first ``--rows`` of the split (of the first ``--limit``) holding an object of ``--category``. Feed-forward, unless
``--steps`` gives each column its test-time steps (the flags of ``prismonet evaluate``, one quoted string per model).

    python3 scripts/recon_figure.py clevr3_fit13k runs/s76/c3_fp9k_fit6000_2p --names "shipped stage 1,footprint targets" \\
        --data data/clevr3 --split val --category 2 --rows 6 --out benchmarks/cubes_s76_ff.png
    python3 scripts/recon_figure.py shipped shipped --names "search,search with shape trials" \\
        --steps "--search 3 --fit-color 50" "--search 3 --fit-color 50 --shape-trials" --data data/clevr3_v78 --out F.png
"""
from __future__ import annotations

import argparse

import numpy as np
import torch

from prismonet.data.dataset import SceneDataset
from prismonet.model.inference import infer
from prismonet.model.io import load_model, training_loss_config
from prismonet.viz.decomposition import labelled_panel
from prismonet.viz.mask_comparison import PANEL, chw_to_u8, panel_grid


def shaded_depth(depth: np.ndarray, fx: float, light=(-0.4, -0.5, -1.0)) -> np.ndarray:
    """``(H, W)`` depth along the optical axis to ``(H, W, 3)`` uint8 grey shading of its surface normals, lit from
    the direction ``light`` (OpenCV camera: x right, y down, z forward; the default is up, left and towards the
    camera, so that the ground and tops are bright). 0 depth = black."""
    d = np.asarray(depth, np.float64).squeeze()
    gy, gx = np.gradient(d)
    step = np.maximum(d, 1e-6) / fx  # metres per pixel at that depth
    n = np.stack([gx / step, gy / step, -np.ones_like(d)], -1)  # d/du x d/dv, turned to face the camera (-z)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    to_light = np.asarray(light, np.float64) / np.linalg.norm(light)
    shade = np.clip((n * to_light).sum(-1), 0, 1) * 0.8 + 0.2
    return np.where(d[..., None] > 0, np.rint(shade[..., None] * 255), 0).repeat(3, -1).astype(np.uint8)


def _steps(flags: str):
    """An ``InferenceConfig`` from a string of ``prismonet evaluate``'s test-time flags (validated)."""
    import shlex

    from prismonet.cli.common import Parser, add_inference_args, inference_config

    p = Parser(prog="recon_figure --steps")
    add_inference_args(p)
    return inference_config(p.parse_args(shlex.split(flags)))


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("models", nargs="+", help="run folders or shipped names")
    ap.add_argument("--names", default=None, help="comma-separated column labels (default: the model arguments)")
    ap.add_argument("--data", required=True)
    ap.add_argument("--split", default="val")
    ap.add_argument("--category", type=int, default=2, help="show scenes with an object of this category id (Clevr: 2, cubes)")
    ap.add_argument("--rows", type=int, default=6)
    ap.add_argument("--limit", type=int, default=200, help="scenes searched for --category")
    ap.add_argument("--out", required=True, help="PNG path")
    ap.add_argument("--steps", nargs="+", metavar="FLAGS",
                    help="per model, its test-time steps as one string of prismonet evaluate's flags (default: none)")
    args = ap.parse_args(argv)
    from prismonet.threads import use_free_cores

    if argv is None:  # the command line; a caller passing argv (a test) keeps its own threads
        use_free_cores(exit_on_error=True)  # the cores others leave free; PRISMONET_THREADS=N to choose
    names = args.names.split(",") if args.names else args.models
    if len(names) != len(args.models):
        raise SystemExit(f"--names: {len(names)} labels for {len(args.models)} models")
    if args.rows < 1:
        raise SystemExit(f"--rows must be at least 1, got {args.rows}")
    if args.steps is not None and len(args.steps) != len(args.models):
        raise SystemExit(f"--steps: {len(args.steps)} strings for {len(args.models)} models")
    try:
        ds = SceneDataset(args.data, split=args.split)
        models = [load_model(m) for m in args.models]
        steps = [_steps(f) for f in (args.steps or [""] * len(models))]  # "": feed-forward, as `evaluate` decodes it
    except (OSError, ValueError) as e:  # DatasetError, CheckpointError and InputError are ValueErrors
        raise SystemExit(f"recon_figure: {e}") from None
    cats = np.asarray(ds.arrays["obj_category"][: min(args.limit, len(ds))])
    idx = [i for i in range(len(cats)) if (cats[i] == args.category).any()][: args.rows]
    if not idx:
        raise SystemExit(f"no scene among the first {len(cats)} of {args.data} ({args.split}) has an object of category {args.category}")
    b = ds.batch(idx)
    outs = []
    with torch.no_grad():
        for (m, info), cfg in zip(models, steps):
            o = infer(m.eval(), b, cfg, training_loss_config(info)).composite
            outs.append((o.image.numpy(), o.depth.numpy()))
    fx = b.K[:, 0, 0].numpy()
    rows = []
    for r, i in enumerate(idx):
        tiles = [labelled_panel(chw_to_u8(b.rgb[r].numpy()), f"input ({args.split} {i})", PANEL),
                 labelled_panel(shaded_depth(b.depth[r].numpy(), fx[r]), "input depth", PANEL)]
        for name, (image, depth) in zip(names, outs):
            tiles += [labelled_panel(chw_to_u8(image[r]), name, PANEL),
                      labelled_panel(shaded_depth(depth[r], fx[r]), f"{name}: depth", PANEL)]
        rows.append(tiles)
    from prismonet.files import write_image

    path = write_image(args.out, panel_grid(rows)[..., ::-1])  # RGB -> OpenCV's BGR
    print(f"wrote {path}: scenes {idx}")


if __name__ == "__main__":
    main()
