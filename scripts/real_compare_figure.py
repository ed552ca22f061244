"""Two or more `prismonet real evaluate` readings of the same labelled photos, side by side.

    python3 scripts/real_compare_figure.py RUN_A RUN_B ... --names "a,b,..." --out FIG.png [--photos blox,coffee]

One row per reading, one column per photo: the photo with its labelled boxes (green) and the reading's boxes (blue
where they match a label at IoU 0.5, red where not), titled with the objects found against those labelled in view and
the photo's box AR0.5. Each reading's folder is a `real evaluate --out` folder (its `real_evaluation.json`)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from matplotlib.patches import Rectangle  # noqa: E402
from PIL import Image  # noqa: E402


def readings(run: Path) -> dict[str, dict]:
    rec = json.loads((run / "real_evaluation.json").read_text())
    return {Path(p["photo"]).stem: p for p in rec["photos"]}


def labels_for(photo: str, label_dir: Path) -> list[list[float]]:
    f = label_dir / f"{photo}.json"
    return [o["box"] for o in json.loads(f.read_text())["objects"]] if f.is_file() else []


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--names", required=True, help="comma-separated row titles, one per run")
    ap.add_argument("--labels", type=Path, default=Path("realdata/samples/labels"))
    ap.add_argument("--photos", help="comma-separated photo stems (default: every photo of the first run)")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--dpi", type=int, default=75)
    args = ap.parse_args(argv)
    names = args.names.split(",")
    if len(names) != len(args.runs):
        ap.error(f"--names: {len(names)} names for {len(args.runs)} runs")
    rows = [readings(r) for r in args.runs]
    photos = args.photos.split(",") if args.photos else sorted(rows[0])
    fig, axes = plt.subplots(len(rows), len(photos), figsize=(3.2 * len(photos), 2.9 * len(rows)), squeeze=False)
    for i, (name, rec) in enumerate(zip(names, rows)):
        for j, photo in enumerate(photos):
            ax = axes[i][j]
            ax.axis("off")
            p = rec.get(photo)
            if p is None:
                ax.set_title(f"{name}: {photo} not read", fontsize=8)
                continue
            ax.imshow(Image.open(p["photo"]).convert("RGB"))
            for x0, y0, x1, y1 in labels_for(photo, args.labels):
                ax.add_patch(Rectangle((x0, y0), x1 - x0, y1 - y0, fill=False, ec="lime", lw=1.0))
            for (x0, y0, x1, y1), hit in zip(p["boxes"], p["hits"]):
                ax.add_patch(Rectangle((x0, y0), x1 - x0, y1 - y0, fill=False, ec="deepskyblue" if hit else "red", lw=1.4))
            ax.set_title(f"{name}\n{photo}: {p['objects_found']} found / {p['true_in_view']} in view, "
                         f"AR0.5 {p['box_AR0.5']:.2f}", fontsize=8)
    fig.suptitle("labels green; found boxes blue (IoU >= 0.5 with a label) or red", fontsize=9)
    fig.tight_layout()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=args.dpi)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
