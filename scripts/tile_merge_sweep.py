"""Re-merge the tiles of a tiled ``real evaluate`` run with other merge thresholds, without decoding again.

    python3 scripts/tile_merge_sweep.py runs/s52/crowd_val_t2 data/crowded_photos/val --iou 0.2,0.3,0.5 --cover 0.5,0.6,0.8

Prints box AP0.5 / AR0.5 over all photos, and the share of photos whose count is within 2 of the truth, per pair.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np


def main() -> None:
    import cv2

    from prismonet.files import read_image
    from realdata.evaluate import ap_ar, photo_measures
    from realdata.labels import load_labels
    from realdata.tiles import merge_detections

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run")
    ap.add_argument("labels")
    ap.add_argument("--iou", default="0.3")
    ap.add_argument("--cover", default="0.6")
    args = ap.parse_args()
    from prismonet.threads import use_free_cores

    use_free_cores(exit_on_error=True)  # the cores others leave free; PRISMONET_THREADS=N to choose
    summary = {Path(r["photo"]).resolve(): r for r in json.loads((Path(args.run) / "summary.json").read_text())}
    labels = load_labels(args.labels)
    shapes = {lab.photo: read_image(lab.photo, cv2.IMREAD_COLOR).shape[:2] for lab in labels}
    print("| merge IoU | cover | box AP0.5 | box AR0.5 | found / true | count within ±2 |\n|---|---|---|---|---|---|")
    for iou in (float(v) for v in args.iou.split(",")):
        for cover in (float(v) for v in args.cover.split(",")):
            scores, hits, n_true, found, close = [], [], 0, 0, 0
            for lab in labels:
                rec = summary[lab.photo.resolve()]
                boxes, sc, cut = [], [], []
                for v in rec.get("tiles", [rec]):  # a photo read whole: its own detections, none cut
                    boxes += v["detections"]["boxes"]
                    sc += v["detections"]["scores"]
                    cut += v["detections"]["cut"]
                kept = merge_detections(np.array(boxes).reshape(-1, 4), np.array(sc), np.array(cut, bool), iou, cover)
                det = {"boxes": [boxes[k] for k in kept], "scores": [sc[k] for k in kept]}
                m = photo_measures(lab, det, rec["outlines"], shapes[lab.photo])
                scores += m["scores"]
                hits += m["hits"]
                n_true += m["true_objects"]
                found += m["objects_found"]
                close += abs(m["objects_found"] - m["true_objects"]) <= 2
            a, r = ap_ar(np.array(scores), np.array(hits, bool), n_true)
            print(f"| {iou:g} | {cover:g} | {a:.3f} | {r:.3f} | {found} / {n_true} | {close / len(labels):.0%} |")


if __name__ == "__main__":
    main()
