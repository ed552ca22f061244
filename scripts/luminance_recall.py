"""Where a photo reading loses, by brightness: each labelled object's luminance against its photo's table, found or not.

    python3 scripts/luminance_recall.py RUN LABELS

``RUN`` is a ``prismonet real evaluate`` output folder, ``LABELS`` the labelled photos it read. Each labelled box's median
luminance over the photo's median (most of a stand-in is table) is binned; per bin the script counts the labels found (a
predicted box at IoU >= 0.5) and missed, and the predicted boxes that are true and false. Then, for the missed labels in
three bands (darker, about as light, lighter), their best IoU with any predicted box (0: nothing touches them).
Session 85 read the grey stand-ins with it (EVALUATION.md, "Session 85").
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import cv2
import numpy as np

BINS = [0, 0.6, 0.8, 0.9, 1.1, 1.25, 1.5, 10]


def iou(a, b) -> float:
    x0, y0, x1, y1 = max(a[0], b[0]), max(a[1], b[1]), min(a[2], b[2]), min(a[3], b[3])
    i = max(0, x1 - x0) * max(0, y1 - y0)
    return i / ((a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - i + 1e-9)


def contrast(gray: np.ndarray, box, table: float) -> float:
    x0, y0, x1, y1 = (int(round(v)) for v in box)
    inner = gray[max(0, y0) : y1 + 1, max(0, x0) : x1 + 1]
    return float(np.median(inner) / table) if inner.size else float("nan")


def main() -> None:
    if len(sys.argv) != 3:
        sys.exit(__doc__.split("\n\n")[1])
    run, labels = Path(sys.argv[1]), Path(sys.argv[2])
    result = json.loads((run / "real_evaluation.json").read_text())
    found, missed, true_boxes, false_boxes, missed_iou = [], [], [], [], []
    for p in result["photos"]:
        lab = json.loads((labels / f"{Path(p['photo']).stem}.json").read_text())
        gray = cv2.imread(p["photo"], cv2.IMREAD_GRAYSCALE).astype(np.float32)
        table = float(np.median(gray))
        truth = [o["box"] for o in lab["objects"]]
        for b in truth:
            best = max([iou(b, q) for q in p["boxes"]] or [0.0])
            (found if best >= 0.5 else missed).append(contrast(gray, b, table))
            if best < 0.5:
                missed_iou.append((missed[-1], best))
        for q in p["boxes"]:
            (true_boxes if any(iou(b, q) >= 0.5 for b in truth) else false_boxes).append(contrast(gray, q, table))
    hist = lambda v: " ".join(f"{x:5d}" for x in np.histogram(v, BINS)[0])
    print("luminance / table, bins", BINS)
    for name, v in (("labels found", found), ("labels missed", missed), ("boxes true", true_boxes), ("boxes false", false_boxes)):
        print(f"{name:14s}{len(v):6d}: {hist(v)}")
    print("missed labels: best IoU with a predicted box (0 / < 0.1 / 0.1-0.3 / 0.3-0.5), by band")
    for lo, hi in ((0, 0.8), (0.8, 1.25), (1.25, 10)):
        best = [b for c, b in missed_iou if lo <= c < hi]
        print(f"  {lo}-{hi}: {len(best)} missed; {np.histogram(best, [0, 1e-9, 0.1, 0.3, 0.5])[0].tolist()}")


if __name__ == "__main__":
    main()
