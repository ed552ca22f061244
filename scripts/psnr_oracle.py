"""How much of a decoding's image error is its geometry and how much its colours: the truth swapped into matched slots.

A diagnosis, not a decoding: it reads the true poses and shapes. Each slot matched to a true object at mask IoU 0.5
gets some of that object's true fields (its shape's prior code, position, scale, yaw); the others keep the model's,
the texture latents and the background always the model's. The scene is rendered again with the model's renderer,
and with ``--fit-color`` the test-time colour fit runs on each row as well (the colours a perfect texture step could
reach for that geometry).

    python3 scripts/psnr_oracle.py clevr3 data/clevr3 --split val --limit 256 [--fit-color] [--rows model,shape,pose,all]

Rows: ``model`` (nothing swapped), ``shape``, ``position``, ``scale``, ``yaw``, ``pose`` (position, scale and yaw),
``all`` (shape and pose). Needs a dataset of Clevr shapes (a prior code per true shape id).
"""

from __future__ import annotations

import argparse
import sys

import numpy as np
import torch
from tqdm import tqdm

ROWS = {"model": (), "shape": ("shape",), "position": ("position",), "scale": ("scale",), "yaw": ("yaw",),
        "pose": ("position", "scale", "yaw"), "all": ("shape", "position", "scale", "yaw")}


def swap_truth(params, batch, pairs: list[list[tuple[int, int]]], fields: tuple[str, ...], codes: torch.Tensor):
    """A copy of ``params`` with ``fields`` of each matched slot (``pairs[j]``: 1-based (slot, object) ids of scene j)
    replaced by the truth of its object."""
    from prismonet.render import SceneParams

    q = SceneParams(params.z_sh.clone(), params.z_tex.clone(), params.position.clone(), params.cos_sin.clone(),
                    params.scale.clone(), params.axis, params.active)
    for j, scene_pairs in enumerate(pairs):
        for pk, gk in scene_pairs:
            s, g = pk - 1, gk - 1
            if "shape" in fields:
                q.z_sh[j, s] = codes[int(batch.obj_shape[j, g])]
            if "position" in fields:
                q.position[j, s] = batch.obj_position[j, g]
            if "scale" in fields:
                q.scale[j, s] = batch.obj_scale[j, g]
            if "yaw" in fields:
                y = batch.obj_yaw[j, g]
                q.cos_sin[j, s] = torch.stack([torch.cos(y), torch.sin(y)])
    return q


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("model")
    ap.add_argument("data")
    ap.add_argument("--split", default="val")
    ap.add_argument("--limit", type=int, default=256)
    ap.add_argument("--batch", type=int, default=64)
    ap.add_argument("--fit-color", action="store_true", help="run the test-time colour fit (50 steps) on every row")
    ap.add_argument("--rows", default="model,shape,pose,all", help=f"comma-separated, of {','.join(ROWS)}")
    a = ap.parse_args(argv)
    from prismonet.threads import use_free_cores

    if argv is None:  # the command line; a caller passing argv (a test) keeps its own threads
        use_free_cores(exit_on_error=True)  # the cores others leave free; PRISMONET_THREADS=N to choose
    rows = [r.strip() for r in a.rows.split(",") if r.strip()]
    bad = [r for r in rows if r not in ROWS]
    if bad or not rows or a.limit <= 0 or a.batch <= 0:
        print(f"psnr_oracle: error: rows must be of {', '.join(ROWS)} and --limit, --batch positive (got {a.rows!r})", file=sys.stderr)
        return 2

    from prismonet.data.dataset import SceneDataset
    from prismonet.evaluation.evaluate import dataset_shapes
    from prismonet.evaluation.metrics import detection_metrics, image_metrics, scene_detection
    from prismonet.model.color_fit import fit_colors
    from prismonet.model.inference import InferenceConfig, infer
    from prismonet.model.io import load_model, training_loss_config
    from prismonet.model.refine import render_latents

    model, info = load_model(a.model)
    ds = SceneDataset(a.data, split=a.split)
    if not dataset_shapes(ds)[1]:
        print(f"psnr_oracle: error: {a.data} is not made of the Clevr shapes, so its true shapes have no prior codes", file=sys.stderr)
        return 2
    codes = model.prior.latents.detach()
    n = min(a.limit, len(ds))
    got = {r: ([], []) for r in rows}
    gt_img, gt_inst = [], []
    model.eval()
    with torch.no_grad():
        for s in tqdm(range(0, n, a.batch), desc="psnr_oracle"):
            b = ds.batch(list(range(s, min(s + a.batch, n))))
            out = infer(model, b, InferenceConfig(), training_loss_config(info), None)
            pi, gi = out.composite.instance.numpy(), b.instance.numpy()
            pairs = [scene_detection(pi[j], gi[j], 0.5)["pairs"] for j in range(len(b))]
            H, W = b.rgb.shape[-2:]
            for r in rows:
                q = swap_truth(out.latents.params, b, pairs, ROWS[r], codes)
                o = render_latents(model, q, out.latents.bg_color, b.K, b.T_world_cam, b.ground_z, H, W)
                if a.fit_color:
                    o = fit_colors(model, o, b)
                got[r][0].append(o.composite.image.numpy())
                got[r][1].append(o.composite.instance.numpy())
            gt_img.append(b.rgb.numpy())
            gt_inst.append(gi)
    G, GI = np.concatenate(gt_img), np.concatenate(gt_inst)
    print(f"{n} scenes of {a.data} [{a.split}], {a.model}{' + colour fit 50' if a.fit_color else ''}; matched slots given the truth of:")
    print("| swapped in | PSNR | AP0.5 | mAP |\n|---|---|---|---|")
    for r in rows:
        im = image_metrics(np.concatenate(got[r][0]), G)
        d = detection_metrics(np.concatenate(got[r][1]), GI)
        print(f"| {r} | {im['PSNR']:.2f} | {d['AP0.5']:.3f} | {d['mAP']:.3f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
