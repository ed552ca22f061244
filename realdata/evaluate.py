"""``prismonet real evaluate``: the model on labelled real photos (``realdata.labels``), measured.

Per photo, against the hand-drawn boxes:

- objects found (slots with >= 25 visible pixels) against the true count, in the photo and inside the
  region the model sees (boxes whose centre lies in the crop or the rectified view's footprint);
- box AP0.5 and AR0.5: each found slot's box is its instance mask mapped back to photo pixels through
  the crop or the rectification (every mask pixel's corners, through the view-to-photo homography),
  scored by its visible pixels, matched greedily at IoU >= 0.5 (all-point interpolated AP); a photo read in
  tiles (``--tiles``) is scored on its tiles' detections after merging (``realdata.tiles``), and its view is
  the union of the tiles;
- foreground IoU inside the model's view, between the union of the true boxes and the union of the
  found boxes (boxes on both sides, so a diagonal pencil counts the same way for both);
- PSNR of the reconstruction against the prepared input, never alone.

With a calibration, boxes are in undistorted photo pixels; the shipped photos have none.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from prismonet.assets import PHOTO_NAME
from prismonet.files import write_atomic
from realdata.boxes import box_iou
from realdata.color import HIGHLIGHT_PERCENTILE

IOU_THRESHOLD = 0.5
COUNT_SLACK = 2
"""A photo's count is right where the objects found are within this many of the labelled objects in view (issue 21)."""


def box_hits(pred: np.ndarray, scores: np.ndarray, truth: np.ndarray, threshold: float = IOU_THRESHOLD) -> np.ndarray:
    """``(P,)`` bool, in ``pred``'s order: predictions taken by falling score, each matched to the
    unmatched true box it overlaps most, a hit if that IoU is at least ``threshold``."""
    hits = np.zeros(len(pred), bool)
    if len(pred) == 0 or len(truth) == 0:
        return hits
    iou = box_iou(pred, truth)
    used = np.zeros(len(truth), bool)
    for i in np.argsort(-np.asarray(scores), kind="stable"):
        cand = np.where(~used, iou[i], -1.0)
        j = int(np.argmax(cand))
        hits[i] = used[j] = cand[j] >= threshold
    return hits


def ap_ar(scores: np.ndarray, hits: np.ndarray, n_true: int) -> tuple[float, float]:
    """``(AP, AR)`` of predictions with ``scores`` and ``hits`` against ``n_true`` true boxes (AP
    interpolated over all recall points). Pooling photos is concatenating their scores and hits."""
    if n_true == 0:
        return (1.0 if len(hits) == 0 else 0.0), 1.0
    if len(hits) == 0:
        return 0.0, 0.0
    hit = np.asarray(hits)[np.argsort(-np.asarray(scores), kind="stable")]
    tp = np.cumsum(hit)
    precision = tp / np.arange(1, len(hit) + 1)
    recall = tp / n_true
    envelope = np.maximum.accumulate(precision[::-1])[::-1]
    steps = np.diff(np.concatenate([[0.0], recall]))
    return float((steps * envelope).sum()), float(recall[-1])


def box_ap_ar(pred: np.ndarray, scores: np.ndarray, truth: np.ndarray, threshold: float = IOU_THRESHOLD) -> tuple[float, float]:
    """``(AP, AR)`` at one IoU threshold (``box_hits``, then ``ap_ar``)."""
    return ap_ar(scores, box_hits(pred, scores, truth, threshold), len(truth))


def _union_mask(boxes, shape) -> np.ndarray:
    m = np.zeros(shape, bool)
    for x0, y0, x1, y1 in boxes:
        m[max(0, int(round(y0))): max(0, int(round(y1))), max(0, int(round(x0))): max(0, int(round(x1)))] = True
    return m


def photo_measures(label, detections: dict, outlines: list, photo_shape: tuple[int, int]) -> dict:
    """The measures of one photo from its found objects (``detections``: ``boxes`` in photo pixels and ``scores``,
    as ``realdata.reconstruct`` records them) and the outlines of the views that read it (one, or one per tile).

    A label's ``ignore`` boxes (objects too small to label) take no part: a detection that matches no labelled box but
    overlaps an ignore box by IoU >= 0.5 is neither a hit nor a false one, and is not counted as found (its box is kept
    under ``ignored_boxes``); the ignore boxes' area is left out of the foreground IoU on both sides."""
    import cv2

    pred = np.array(detections["boxes"], np.float64).reshape(-1, 4)
    scores = np.array(detections["scores"], np.float64)
    truth = np.array(label.boxes).reshape(-1, 4)
    ignore = np.array(label.ignore, np.float64).reshape(-1, 4)
    hits = box_hits(pred, scores, truth)
    ignored = ~hits & (box_iou(pred, ignore).max(axis=1) >= IOU_THRESHOLD) if len(pred) and len(ignore) else np.zeros(len(pred), bool)
    counted = ~ignored
    ap, ar = ap_ar(scores[counted], hits[counted], len(truth))
    view = np.zeros(photo_shape, np.uint8)
    for outline in outlines:
        cv2.fillConvexPoly(view, np.round(np.asarray(outline)).astype(np.int32), 1)
    view = view.astype(bool)
    centres = (truth[:, :2] + truth[:, 2:]) / 2
    in_view = sum(bool(view[min(int(cy), photo_shape[0] - 1), min(int(cx), photo_shape[1] - 1)]) for cx, cy in centres
                  if 0 <= cx < photo_shape[1] and 0 <= cy < photo_shape[0])
    fg_view = view & ~_union_mask(ignore, photo_shape)
    gt_fg, pr_fg = _union_mask(truth, photo_shape) & fg_view, _union_mask(pred[counted], photo_shape) & fg_view
    union = (gt_fg | pr_fg).sum()
    return {"true_objects": len(truth), "true_in_view": int(in_view), "objects_found": int(counted.sum()),
            "box_AP0.5": ap, "box_AR0.5": ar, "foreground_IoU": float((gt_fg & pr_fg).sum() / union) if union else 1.0,
            "boxes": pred[counted].round(1).tolist(), "scores": scores[counted].tolist(), "hits": hits[counted].tolist(),
            "ignored_boxes": pred[ignored].round(1).tolist()}


def evaluate_photos(labels_dir, out, model=PHOTO_NAME, calibration=None, box=None, normalize="auto", gain=None,
                    objects=None, min_pixels: int = 25, inference=None, progress: bool = True, metres_per_unit=None,
                    elevation=None, label_elevations: bool = False, tiling=None, highlights=HIGHLIGHT_PERCENTILE,
                    gray_tint: str = "off", gray_inference=None) -> dict:
    """Reconstruct every labelled photo into ``out`` and measure it; returns ``{"photos": [...], "overall": {...}}``
    (also ``out/real_evaluation.json``). Overall: AP and AR over all photos' boxes pooled, counts summed.
    ``elevation`` (degrees, see ``reconstruct_photos``); or with ``label_elevations`` each label's
    ``elevation_deg`` where it gives one (for models that take the camera as an input; ignored by others)."""
    from realdata.labels import load_labels
    from realdata.reconstruct import reconstruct_photos

    labels = load_labels(labels_dir)
    hints = {lab.photo.stem: lab.elevation_deg for lab in labels if lab.elevation_deg is not None} if label_elevations else None
    recs = reconstruct_photos([str(lab.photo) for lab in labels], out, model, calibration, box, normalize, gain, objects,
                              min_pixels, inference=inference, progress=progress, metres_per_unit=metres_per_unit,
                              elevation=elevation, elevation_hints=hints or None, tiling=tiling, meshes=False,
                              highlights=highlights, gray_tint=gray_tint, gray_inference=gray_inference)
    return _measured(labels, recs, Path(out) / "real_evaluation.json")


def rescore(out, labels_dir, dest=None) -> dict:
    """Measure a finished ``real evaluate`` run in ``out`` again (its ``summary.json``: every detection before any
    label's ``ignore`` boxes were applied) against the labels in ``labels_dir``, e.g. after they changed; no model is
    run. Every labelled photo must be in the run. Writes ``dest`` (default ``out/real_evaluation.json``) and returns it."""
    from prismonet.files import read_json
    from realdata.labels import load_labels

    recs = {Path(r["photo"]).stem: r for r in read_json(Path(out) / "summary.json", list)}
    labels = load_labels(labels_dir)
    missing = [lab.photo.name for lab in labels if lab.photo.stem not in recs]
    if missing:
        raise ValueError(f"{out}: the run did not read {', '.join(missing)}")
    return _measured(labels, [recs[lab.photo.stem] for lab in labels], Path(out) / "real_evaluation.json" if dest is None else dest)


def _measured(labels, recs: list[dict], dest) -> dict:
    """``photo_measures`` of each label's reconstruction record, and the overall row, written to ``dest``."""
    import cv2

    from prismonet.files import read_image

    rows = []
    for lab, rec in zip(labels, recs):
        shape = read_image(lab.photo, cv2.IMREAD_COLOR).shape[:2]
        m = photo_measures(lab, rec["detections"], rec["outlines"], shape)
        m.update(photo=str(lab.photo), psnr=rec["psnr"], figure=rec["figure"], camera=rec["camera"],
                 reading=f"{len(rec['tiles'])} tiles" if "tiles" in rec else f"zoomed out {rec['prepare']['zoom_out']:g}x"
                 if "zoom_out" in rec.get("prepare", {}) else "whole")
        if "model" in rec:  # runs before session 93 did not record it
            m["model"] = rec["model"]
        rows.append(m)
    result = {"photos": rows, "overall": overall_measures(rows)}
    write_atomic(Path(dest), json.dumps(result, indent=1))
    return result


def overall_measures(rows: list[dict]) -> dict:
    """The overall row of ``photo_measures`` rows: AP and AR over all photos' boxes pooled, counts summed, foreground
    IoU and (where every row has its ``psnr`` readings; else None) the last PSNR reading averaged over the photos."""
    ap, ar = ap_ar(np.concatenate([np.asarray(r["scores"], np.float64) for r in rows]),
                   np.concatenate([np.asarray(r["hits"], bool) for r in rows]), sum(r["true_objects"] for r in rows))
    return {"photos": len(rows), "true_objects": sum(r["true_objects"] for r in rows), "true_in_view": sum(r["true_in_view"] for r in rows),
            "objects_found": sum(r["objects_found"] for r in rows), "box_AP0.5": ap, "box_AR0.5": ar,
            "foreground_IoU": float(np.mean([r["foreground_IoU"] for r in rows])),
            "PSNR": float(np.mean([list(r["psnr"].values())[-1] for r in rows])) if all(r.get("psnr") for r in rows) else None,
            "count_within_slack": sum(abs(r["objects_found"] - r["true_in_view"]) <= COUNT_SLACK for r in rows)}


def merge_evaluations(parts: list[tuple[dict, set[str] | None]]) -> dict:
    """One evaluation from several readings of the same labelled photos, each photo's row taken from one of them:
    ``parts`` is ``[(result, stems), ...]`` (a ``real_evaluation.json`` and the photo stems to take from it; ``None``: the
    photos no earlier part gave). Every photo must come from exactly one part; the overall row is computed again."""
    rows: dict[str, dict] = {}
    every: set[str] = set()
    for result, stems in parts:
        have = {Path(r["photo"]).stem: r for r in result["photos"]}
        every |= set(have)
        unknown = sorted((stems or set()) - set(have))
        if unknown:
            raise ValueError(f"photos not in that evaluation: {', '.join(unknown)}")
        take = set(have) - set(rows) if stems is None else stems
        twice = sorted(take & set(rows))
        if twice:
            raise ValueError(f"photos taken from two evaluations: {', '.join(twice)}")
        rows.update({s: have[s] for s in take})
    missing = sorted(every - set(rows))
    if missing:
        raise ValueError(f"photos no part gives: {', '.join(missing)}")
    ordered = [rows[s] for s in sorted(rows)]
    return {"photos": ordered, "overall": overall_measures(ordered)}


def format_real_table(result: dict) -> str:
    """A Markdown table: one row per photo and the overall row; with a column for how each photo was read (whole, or
    in how many tiles) when any was read in tiles."""
    tiled = any(r.get("reading", "whole") != "whole" for r in result["photos"])
    read = (lambda r: f" {r.get('reading', 'whole')} |") if tiled else (lambda r: "")
    lines = ["| photo |" + (" read |" if tiled else "") + " true (in view) | found | box AP0.5 | box AR0.5 | foreground IoU | PSNR |",
             "|---|" + ("---|" if tiled else "") + "---|---|---|---|---|---|"]
    for r in result["photos"]:
        lines.append(f"| {Path(r['photo']).name} |{read(r)} {r['true_objects']} ({r['true_in_view']}) | {r['objects_found']} | {r['box_AP0.5']:.3f} | "
                     f"{r['box_AR0.5']:.3f} | {r['foreground_IoU']:.3f} | {list(r['psnr'].values())[-1]:.1f} |")
    o = result["overall"]
    lines.append(f"| **all** |" + (" |" if tiled else "") + f" {o['true_objects']} ({o['true_in_view']}) | {o['objects_found']} | {o['box_AP0.5']:.3f} | "
                 f"{o['box_AR0.5']:.3f} | {o['foreground_IoU']:.3f} | {o['PSNR']:.1f} |")
    if "count_within_slack" in o:
        lines.append(f"\nfound within ±{COUNT_SLACK} of the objects in view on {o['count_within_slack']} of {o['photos']} photos")
    return "\n".join(lines)
