"""The photoreal ladder's table and figure: a model evaluated on the training renderer's test scenes and on
each Blender rung of the same scenes (``prismonet data blender``), with ``prismonet evaluate``'s measures.

    python3 scripts/ladder.py --ladder data/ladder --base data/clevr3 --limit 500 --out runs/ladder_ff
    python3 scripts/ladder.py --ladder data/ladder --base data/clevr3 --limit 500 --out runs/ladder_search -- --search 3 --fit-color 50

Writes ``OUT/<rung>.json`` (each evaluation, resumable: an existing one is kept), ``OUT/table.md`` and
``OUT/ladder.png`` (a row per scene: per rung the input and the instances found, feed-forward).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch

COLUMNS = [("mAP", "mAP", 3), ("AP0.5", "AP0.5", 3), ("AR0.5", "AR0.5", 3), ("AP0.5 unf.", "AP0.5_unfiltered", 3),
           ("allObj", "allObj", 3), ("ARI-FG", "ARI-FG", 3), ("RMSE", "img_RMSE", 3), ("PSNR", "PSNR", 2), ("SSIM", "SSIM", 3),
           ("D-RMSE", "depth_RMSE", 3), ("pos", "pos_err", 3), ("rot (sym.)", "rot_err_sym", 1)]


def main() -> None:
    from prismonet.cli import main as cli

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ladder", required=True, help="folder with one dataset per rung: a, b, c, d")
    ap.add_argument("--base", required=True, help="the training renderer's dataset of the same scenes (its test split)")
    ap.add_argument("--model", default="shipped")
    ap.add_argument("--limit", type=int, default=500)
    ap.add_argument("--figure-scenes", type=int, default=6)
    ap.add_argument("--out", required=True)
    ap.add_argument("--normalize", action="store_true",
                    help="first map each rung image's table colour onto the training ground, as the real-photo path does "
                         "(realdata.color; the copies go to OUT/normalized/)")
    ap.add_argument("flags", nargs="*", help="after --: more flags for prismonet evaluate")
    args = ap.parse_args()
    from prismonet.threads import use_free_cores

    use_free_cores(exit_on_error=True)  # the cores others leave free; PRISMONET_THREADS=N to choose
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rungs = [("training renderer", Path(args.base))] + [(f"rung {r}", Path(args.ladder) / r) for r in "abcd"
                                                         if (Path(args.ladder) / r / "meta.json").is_file()]
    if args.normalize:
        rungs = [rungs[0]] + [(f"{name} + table colour map", normalized(data, out / "normalized" / data.name)) for name, data in rungs[1:]]
    rows = []
    for name, data in rungs:
        res = out / f"{name.replace(' ', '_')}.json"
        if not res.is_file():
            meta = json.loads((data / "meta.json").read_text())
            extra = ["--any-camera"] if meta.get("config", {}).get("camera_jitter", 0) > 0 else []
            code = cli(["evaluate", args.model, str(data), "--limit", str(args.limit), "--json", str(res), "--quiet", *extra, *args.flags])
            if code != 0:
                raise SystemExit(code)
        r = json.loads(res.read_text())
        meta = json.loads((data / "meta.json").read_text())
        vs = meta.get("blender", {}).get("vs_training_renderer")
        rows.append((name, r, vs))
    head = "| input | PSNR to the training renderer | " + " | ".join(c for c, _, _ in COLUMNS) + " |"
    lines = [f"model {args.model}, {rows[0][1]['scenes']} scenes, flags: {' '.join(args.flags) or '(feed-forward)'}", "",
             head, "|" + "---|" * (len(COLUMNS) + 2)]
    for name, r, vs in rows:
        cells = [f"{r[k]:.{d}f}" for _, k, d in COLUMNS]
        lines.append(f"| {name} | {'-' if vs is None else format(vs['PSNR'], '.1f')} | " + " | ".join(cells) + " |")
    (out / "table.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    figure(rungs, args.model, args.figure_scenes, out / "ladder.png")


def normalized(data: Path, dest: Path) -> Path:
    """A copy of a packed dataset whose images went through the real-photo path's colour normalisation:
    a per-channel gain maps the table colour (``realdata.color.estimate_table_color``) onto the
    training ground's colour."""
    import time

    import numpy as np

    from prismonet.data.dataset import SceneDataset
    from prismonet.data.generate import write_dataset
    from realdata.color import estimate_table_color, table_mapping

    if (dest / "meta.json").is_file():
        return dest
    meta = json.loads((data / "meta.json").read_text())
    target = np.asarray(meta["config"]["ground_color"], np.float64) / 255.0
    ds = SceneDataset(data, "test")
    arrays = {k: np.array(v) for k, v in ds.arrays.items()}
    for i, img in enumerate(arrays["rgb"]):
        x = img.astype(np.float32) / 255.0
        arrays["rgb"][i] = np.rint(table_mapping(estimate_table_color(x), target).apply(x) * 255.0).astype(np.uint8)
    dest.parent.mkdir(parents=True, exist_ok=True)
    write_dataset(dest, arrays, (0, 0, len(arrays["rgb"])), {**{k: meta[k] for k in ("generator", "config", "seed") if k in meta},
                                                              "normalized_from": str(data)}, time.perf_counter())
    return dest


@torch.no_grad()
def figure(rungs, model_name: str, n: int, path: Path) -> None:
    from prismonet.data.dataset import SceneDataset
    from prismonet.model.io import load_model
    from prismonet.viz.ladder import ladder_figure

    model, _ = load_model(model_name)
    cols = []
    for name, data in rungs:
        b = SceneDataset(data, "test").batch(list(range(n)))
        inst = model(b.rgb, b.K, b.T_world_cam, b.ground_z).composite.instance.numpy()
        cols.append((name.replace("training renderer", "training"), b.rgb.numpy(), b.instance.numpy(), inst))
    print(f"wrote {ladder_figure(cols, path)}")


if __name__ == "__main__":
    main()
