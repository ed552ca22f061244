"""Re-merge the tiles of a tiled ``real evaluate`` run with other merge thresholds, without decoding again.

    python3 scripts/tile_merge_sweep.py runs/s52/crowd_val_t2 data/crowded_photos/val --iou 0.2,0.3,0.5 --cover 0.5,0.6,0.8

Prints box AP0.5 / AR0.5 over all photos, and the photos whose count is within 2 of the objects in view, per setting.
``--whole-first PX,...`` (a run with ``--tile-below``, which read every photo whole first, into ``RUN/whole``): in the
photos read in tiles, the whole reading's detections of at least PX visible pixels join the merge first, as whole
detections that no tile detection can displace (their scores, view pixels, scaled to a tile's pixels by the squared
ratio of the two views' sides); ``none``: the merge as it is.
"""

from __future__ import annotations

import argparse
import itertools
import json
from pathlib import Path

import numpy as np


def main() -> None:
    import cv2

    from prismonet.files import read_image
    from realdata.evaluate import overall_measures, photo_measures
    from realdata.labels import load_labels
    from realdata.tiles import merge_detections

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run")
    ap.add_argument("labels")
    ap.add_argument("--iou", default="0.3")
    ap.add_argument("--cover", default="0.6")
    ap.add_argument("--whole-first", default="none", help="PX[,PX...] or none (see above)")
    args = ap.parse_args()
    from prismonet.threads import use_free_cores

    use_free_cores(exit_on_error=True)  # the cores others leave free; PRISMONET_THREADS=N to choose
    summary = {Path(r["photo"]).resolve(): r for r in json.loads((Path(args.run) / "summary.json").read_text())}
    firsts = [None if v == "none" else float(v) for v in args.whole_first.split(",")]
    whole = {}
    if any(f is not None for f in firsts):
        whole = {Path(r["photo"]).resolve(): r for r in json.loads((Path(args.run) / "whole" / "summary.json").read_text())}
    labels = load_labels(args.labels)
    shapes = {lab.photo: read_image(lab.photo, cv2.IMREAD_COLOR).shape[:2] for lab in labels}
    print("| merge IoU | cover | whole first | box AP0.5 | box AR0.5 | found / true | count within ±2 |\n|---|---|---|---|---|---|---|")
    for iou, cover, first in itertools.product([float(v) for v in args.iou.split(",")], [float(v) for v in args.cover.split(",")], firsts):
        rows = []
        for lab in labels:
            rec = summary[lab.photo.resolve()]
            boxes, sc, cut = [], [], []
            if first is not None and "tiles" in rec:  # the whole reading's large detections, taken before any tile's
                w = whole[lab.photo.resolve()]
                ratio = (w["prepare"]["crop_box"][2] / rec["tiles"][0]["prepare"]["crop_box"][2]) ** 2
                big = [k for k, v in enumerate(w["detections"]["scores"]) if v >= first]
                boxes += [w["detections"]["boxes"][k] for k in big]
                sc += [w["detections"]["scores"][k] * ratio for k in big]
                cut += [False] * len(big)
            n_first = len(boxes)
            for v in rec.get("tiles", [rec]):  # a photo read whole: its own detections
                boxes += v["detections"]["boxes"]
                sc += v["detections"]["scores"]
                cut += v["detections"]["cut"]
            rank = np.array(sc) + np.where(np.arange(len(sc)) < n_first, 1e12, 0.0)  # the whole ones first
            kept = (merge_detections(np.array(boxes).reshape(-1, 4), rank, np.array(cut, bool), iou, cover)
                    if "tiles" in rec else range(len(boxes)))  # a photo read whole is not merged (as in the pipeline)
            det = {"boxes": [boxes[k] for k in kept], "scores": [sc[k] for k in kept]}
            rows.append(photo_measures(lab, det, rec["outlines"], shapes[lab.photo]))
        o = overall_measures(rows)
        print(f"| {iou:g} | {cover:g} | {'-' if first is None else f'{first:g}'} | {o['box_AP0.5']:.3f} | {o['box_AR0.5']:.3f} | "
              f"{o['objects_found']} / {o['true_objects']} | {o['count_within_slack']} of {len(labels)} |")


if __name__ == "__main__":
    main()
