"""The paper's measures, as pure functions on numpy arrays (and kornia for SSIM / PSNR).

Instance measures follow the paper: an object counts as found when the IoU of its predicted and
ground-truth visible masks exceeds the threshold, and only objects with at least
``MIN_VISIBLE_PIXELS`` visible pixels count. Our reading where the paper is silent:
- the paper states the 25-pixel rule for objects, i.e. the ground truth. Applied to the predictions
  too, a predicted sliver (a slot almost hidden behind another) is never a false positive; this
  raises precision. ``detection_metrics`` reports both: ``AP0.5``, ``mAP``, ... with predictions
  filtered by the same rule, and ``AP0.5_unfiltered``, ``mAP_unfiltered``, ... counting every
  predicted instance with at least one visible pixel, the stricter reading, which EVALUATION.md
  compares with the paper;
- precision, recall and F1 are computed per scene and averaged over scenes ("AP", "AR", "F1");
- a scene with no predictions has precision 1 if it has no ground-truth objects, else 0.
With disjoint masks and thresholds >= 0.5, an object can match at most one prediction, so the
matching is unique without an assignment step.
"""

from __future__ import annotations

import math

import numpy as np

MIN_VISIBLE_PIXELS = 25
IOU_THRESHOLDS = tuple(np.round(np.arange(0.5, 0.951, 0.05), 2).tolist())


def instance_masks(instance: np.ndarray, min_pixels: int = MIN_VISIBLE_PIXELS) -> tuple[np.ndarray, np.ndarray]:
    """Ids ``(n,)`` and boolean masks ``(n, H, W)`` of the instances (id > 0) with enough pixels."""
    ids, counts = np.unique(instance[instance > 0], return_counts=True)
    keep = ids[counts >= min_pixels]
    return keep, instance[None] == keep[:, None, None]


def iou_matrix(pred: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """IoU ``(P, G)`` between boolean masks ``(P, H, W)`` and ``(G, H, W)``."""
    p = pred.reshape(len(pred), -1).astype(np.float64)
    g = gt.reshape(len(gt), -1).astype(np.float64)
    inter = p @ g.T
    union = p.sum(1)[:, None] + g.sum(1)[None] - inter
    return np.where(union > 0, inter / np.maximum(union, 1), 0.0)


def scene_detection(pred_instance: np.ndarray, gt_instance: np.ndarray, threshold: float,
                    pred_min_pixels: int = MIN_VISIBLE_PIXELS) -> dict:
    """Precision, recall, F1, counts and matched (pred id, gt id) pairs for one scene at one IoU threshold.

    ``pred_min_pixels``: predicted instances with fewer visible pixels are ignored (1: none is);
    ground-truth objects need ``MIN_VISIBLE_PIXELS`` either way."""
    pid, pm = instance_masks(pred_instance, pred_min_pixels)
    gid, gm = instance_masks(gt_instance)
    if threshold < 0.5:
        raise ValueError(f"IoU threshold must be at least 0.5 (for a unique matching), got {threshold}")
    iou = iou_matrix(pm, gm) if len(pid) and len(gid) else np.zeros((len(pid), len(gid)))
    # disjoint masks: IoU > 0.5 with two partners is impossible, so the matching is unique
    pairs = [(int(pid[p]), int(gid[g])) for p, g in zip(*np.nonzero(iou > threshold))]
    tp = len(pairs)
    precision, recall, f1 = _rates(tp, len(pid), len(gid))
    return {"precision": precision, "recall": recall, "f1": f1, "tp": tp, "n_pred": len(pid), "n_gt": len(gid), "pairs": pairs}


def _rates(tp: int, n_pred: int, n_gt: int) -> tuple[float, float, float]:
    """Precision, recall and F1 of one scene (no predictions: precision 1 only with no objects)."""
    precision = tp / n_pred if n_pred else float(n_gt == 0)
    recall = tp / n_gt if n_gt else 1.0
    f1 = 2 * precision * recall / (precision + recall) if precision + recall > 0 else 0.0
    return precision, recall, f1


def detection_metrics(pred_instances: np.ndarray, gt_instances: np.ndarray) -> dict:
    """AP0.5, AR0.5, F1_0.5, mAP over 0.5:0.95, allObj, over scenes ``(N, H, W)``: with predictions
    under ``MIN_VISIBLE_PIXELS`` ignored, and again with every prediction counted (keys ending in
    ``_unfiltered``)."""
    ts = np.asarray(IOU_THRESHOLDS)  # ts[0] = 0.5
    ways = (("", MIN_VISIBLE_PIXELS), ("_unfiltered", 1))
    rates: dict[str, list] = {suffix: [] for suffix, _ in ways}  # per scene: (thresholds, 3)
    for p, g in zip(pred_instances, gt_instances):
        gid, gm = instance_masks(g)  # masks and IoU once per scene and way, then every threshold
        for suffix, min_px in ways:
            pid, pm = instance_masks(p, min_px)
            iou = iou_matrix(pm, gm) if len(pid) and len(gid) else np.zeros((len(pid), len(gid)))
            tp = (iou[None] > ts[:, None, None]).sum((1, 2))  # unique matching, as in scene_detection
            rates[suffix].append([_rates(int(t), len(pid), len(gid)) for t in tp])
    out = {}
    for suffix, r in rates.items():
        a = np.asarray(r, dtype=np.float64).reshape(-1, len(ts), 3)
        out.update({
            f"AP0.5{suffix}": float(a[:, 0, 0].mean()),
            f"AR0.5{suffix}": float(a[:, 0, 1].mean()),
            f"F1_0.5{suffix}": float(a[:, 0, 2].mean()),
            f"mAP{suffix}": float(a[:, :, 0].mean(0).mean()),
            f"allObj{suffix}": float((a[:, 0, 1] == 1.0).mean()),
        })
    return out


def count_metrics(pred_instances: np.ndarray, gt_instances: np.ndarray) -> dict:
    """How often the number of visible predicted objects equals the number of visible objects
    (each with at least ``MIN_VISIBLE_PIXELS`` pixels), over scenes ``(N, H, W)``: ``count_exact``
    (fraction of scenes), ``count_abs_err`` (mean absolute difference) and ``count_bias`` (mean of
    predicted minus true)."""
    diff = np.asarray([len(instance_masks(p)[0]) - len(instance_masks(g)[0]) for p, g in zip(pred_instances, gt_instances)], dtype=np.float64)
    if diff.size == 0:
        return {"count_exact": math.nan, "count_abs_err": math.nan, "count_bias": math.nan}
    return {"count_exact": float((diff == 0).mean()), "count_abs_err": float(np.abs(diff).mean()), "count_bias": float(diff.mean())}


def count_breakdown(pred_instances: np.ndarray, gt_instances: np.ndarray) -> list[dict]:
    """The detection and count measures per number of visible objects: one row per count present,
    ``{"objects", "scenes", "AP0.5", "AR0.5", "AP0.5_unfiltered", "count_exact", "count_bias"}``, over
    scenes ``(N, H, W)``. For mixed-count datasets: where recall falls with crowding."""
    counts = np.asarray([len(instance_masks(g)[0]) for g in gt_instances])
    rows = []
    for n in np.unique(counts):
        sel = counts == n
        d = detection_metrics(pred_instances[sel], gt_instances[sel])
        c = count_metrics(pred_instances[sel], gt_instances[sel])
        rows.append({"objects": int(n), "scenes": int(sel.sum()), "AP0.5": d["AP0.5"], "AR0.5": d["AR0.5"],
                     "AP0.5_unfiltered": d["AP0.5_unfiltered"], "count_exact": c["count_exact"], "count_bias": c["count_bias"]})
    return rows


def clip_breakdown(pred_instances: np.ndarray, gt_instances: np.ndarray, gt_depths: np.ndarray, far_depth: float,
                   tol: float = 1e-3) -> dict:
    """Recall at IoU 0.5 of the visible objects within the depth sensor's range (``"near"``) and beyond
    it (``"beyond_clip"``: more than half of the object's pixels read ``far_depth``, where depth cannot
    tell it from the ground), over scenes ``(N, H, W)``: ``{part: {"objects", "AR0.5"}}``."""
    hit = {"near": [0, 0], "beyond_clip": [0, 0]}
    for pi, gi, d in zip(pred_instances, gt_instances, gt_depths):
        found = {g for _, g in scene_detection(pi, gi, 0.5)["pairs"]}
        gid, gm = instance_masks(gi)
        for g, m in zip(gid, gm):
            part = "beyond_clip" if (d[m] >= far_depth - tol).mean() > 0.5 else "near"
            hit[part][0] += 1
            hit[part][1] += int(g) in found
    return {k: {"objects": n, "AR0.5": (f / n) if n else math.nan} for k, (n, f) in hit.items()}


MISS_KINDS = ("uncovered", "split", "merged", "misfit")
"""Why a visible object is missed at IoU 0.5 (``miss_breakdown``), tested in this order."""


def miss_breakdown(pred_instances: np.ndarray, gt_instances: np.ndarray) -> dict:
    """Where the visible objects of scenes ``(N, H, W)`` that are not found (IoU 0.5, as AR0.5) went, as
    shares of all visible objects: ``{"objects", "found", "uncovered", "split", "merged", "misfit"}``.

    Per missed object, with every predicted pixel counted (no size filter):
    - *uncovered*: under half of its pixels belong to any predicted instance;
    - *split*: covered, but no one predicted instance holds half of it;
    - *merged*: the instance holding half of it also holds half of another visible object;
    - *misfit*: one instance holds half of it and no other object, but is the wrong size or place."""
    n = {k: 0 for k in ("objects", "found") + MISS_KINDS}
    for pi, gi in zip(pred_instances, gt_instances):
        found = {g for _, g in scene_detection(pi, gi, 0.5)["pairs"]}
        gid, gm = instance_masks(gi)
        pid = np.unique(pi[pi > 0])
        # share of each visible object held by each predicted instance: (P, G)
        held = np.array([[(pi[m] == p).mean() for m in gm] for p in pid]).reshape(len(pid), len(gid))
        for j, g in enumerate(gid):
            n["objects"] += 1
            if int(g) in found:
                n["found"] += 1
            elif held[:, j].sum() < 0.5:
                n["uncovered"] += 1
            elif held[:, j].max() < 0.5:
                n["split"] += 1
            elif (held[held[:, j].argmax()] >= 0.5).sum() > 1:
                n["merged"] += 1
            else:
                n["misfit"] += 1
    total = n.pop("objects")
    return {"objects": total, **{k: (v / total if total else math.nan) for k, v in n.items()}}


def image_metrics(pred: np.ndarray, gt: np.ndarray) -> dict:
    """RMSE, PSNR (data range 1) and SSIM (11x11 Gaussian window, sigma 1.5) of images ``(N, 3, H, W)`` in [0, 1].

    Means over scenes of the per-scene values.
    """
    import kornia
    import torch

    p = torch.as_tensor(pred, dtype=torch.float64)
    g = torch.as_tensor(gt, dtype=torch.float64)
    mse = ((p - g) ** 2).flatten(1).mean(1)
    psnr = 10 * torch.log10(1.0 / mse.clamp_min(1e-12))
    ssim = kornia.metrics.ssim(p, g, 11).flatten(1).mean(1)
    return {"img_RMSE": float(mse.sqrt().mean()), "PSNR": float(psnr.mean()), "SSIM": float(ssim.mean())}


def depth_metrics(pred: np.ndarray, gt: np.ndarray) -> dict:
    """Depth RMSE, AbsRD and SqRD (Eigen et al.) over pixels with known ground truth (> 0), per scene then
    averaged over the scenes that have any (NaN when none has: e.g. photos)."""
    rmse, absrd, sqrd = [], [], []
    for p, g in zip(np.asarray(pred, np.float64), np.asarray(gt, np.float64)):
        v = g > 0
        if not v.any():
            continue
        d = p[v] - g[v]
        rmse.append(math.sqrt(float(np.mean(d**2))))
        absrd.append(float(np.mean(np.abs(d) / g[v])))
        sqrd.append(float(np.mean(d**2 / g[v])))
    if not rmse:
        return {"depth_RMSE": math.nan, "AbsRD": math.nan, "SqRD": math.nan}
    return {"depth_RMSE": float(np.mean(rmse)), "AbsRD": float(np.mean(absrd)), "SqRD": float(np.mean(sqrd))}


def adjusted_rand_index(a: np.ndarray, b: np.ndarray) -> float:
    """Adjusted Rand index of two labelings of the same items (Hubert & Arabie)."""
    a = np.asarray(a).ravel()
    b = np.asarray(b).ravel()
    if a.shape != b.shape:
        raise ValueError(f"adjusted_rand_index: labelings differ in size, {a.size} vs {b.size}")
    n = a.size
    if n < 2:
        return 1.0
    _, ai = np.unique(a, return_inverse=True)
    _, bi = np.unique(b, return_inverse=True)
    table = np.zeros((ai.max() + 1, bi.max() + 1), dtype=np.int64)
    np.add.at(table, (ai, bi), 1)
    comb = lambda x: x * (x - 1) / 2.0
    sum_ij = comb(table).sum()
    sum_a = comb(table.sum(1)).sum()
    sum_b = comb(table.sum(0)).sum()
    expected = sum_a * sum_b / comb(n)
    max_index = (sum_a + sum_b) / 2.0
    if max_index == expected:
        return 1.0
    return float((sum_ij - expected) / (max_index - expected))


def ari_metrics(pred_instances: np.ndarray, gt_instances: np.ndarray) -> dict:
    """ARI over all pixels and ARI-FG over ground-truth foreground pixels, averaged over scenes."""
    ari, fg = [], []
    for p, g in zip(pred_instances, gt_instances):
        ari.append(adjusted_rand_index(p, g))
        m = g > 0
        if m.any():
            fg.append(adjusted_rand_index(p[m], g[m]))
    return {"ARI": float(np.mean(ari)), "ARI-FG": float(np.mean(fg)) if fg else float("nan")}


def angle_error(pred: float, gt: float, period: float | None) -> float:
    """Absolute angle difference in degrees, modulo ``period`` (radians; ``None`` = 2 pi, 0 = any angle)."""
    if period == 0:
        return 0.0
    period = 2 * math.pi if period is None else period
    d = (pred - gt) % period
    return math.degrees(min(d, period - d))


def category_shares(true_cat: np.ndarray, drawn_cat: np.ndarray, names: tuple[str, ...]) -> dict:
    """How often a matched object is drawn as its own kind: per category of ``names``, the share of matched objects of
    that true category (``true_cat``, ints) whose slot's shape latent lies nearest a prior code of the same category
    (``drawn_cat``); NaN for a category with no matched object. ``"mean"`` averages the categories that have one (each
    category weighs the same, as the sphere / cylinder / cube columns of EVALUATION.md do); ``"objects"`` counts each.

    Example:
        >>> category_shares(np.array([0, 0, 2, 2]), np.array([0, 1, 2, 2]), ("sphere", "cylinder", "cube"))["mean"]
        0.75
    """
    true_cat, drawn_cat = np.asarray(true_cat, np.int64), np.asarray(drawn_cat, np.int64)
    if true_cat.shape != drawn_cat.shape:
        raise ValueError(f"category_shares: {true_cat.shape} true categories against {drawn_cat.shape} drawn ones")
    out: dict = {"objects": {}}
    for c, name in enumerate(names):
        sel = true_cat == c
        out[name] = float((drawn_cat[sel] == c).mean()) if sel.any() else math.nan
        out["objects"][name] = int(sel.sum())
    shares = [out[n] for n in names if out["objects"][n]]
    out["mean"] = float(np.mean(shares)) if shares else math.nan
    return out


SETTING_SYMMETRY = {"cars": math.pi, "chairs": math.pi / 2}
"""Pseudo-symmetry about the vertical axis of the ShapeNet-style settings, for the rotation error "up to
symmetry": the paper's bracketed figures (a car looks alike turned by 180 degrees, an armchair by 90)."""


def symmetry_period(shape_id: int) -> float | None:
    """Rotational symmetry about the vertical axis of a Clevr shape: 0 (any angle), pi/2, pi."""
    from prismonet.shapes.clevr_set import clevr_shapes

    if shape_id < 0:
        return None
    s = clevr_shapes()[shape_id]
    hx, hy, _ = s.half_extents
    if hx == hy:
        return 0.0 if s.category in ("sphere", "cylinder") else math.pi / 2
    return math.pi


def recurrent_step_metrics(pred_instances: np.ndarray, gt_instances: np.ndarray, num_slots: int) -> list[dict]:
    """Per encoder step ``k = 1..num_slots`` (prediction id ``k``): how often it is visible, and how
    often a visible one is a detection at IoU 0.5.

    ``visible``: fraction of scenes in which step k's object has at least ``MIN_VISIBLE_PIXELS``
    pixels; ``precision``: of those, the fraction matched to a ground-truth object. Shows whether
    later steps of the recurrent encoder are worse than earlier ones.
    """
    visible = np.zeros(num_slots)
    matched = np.zeros(num_slots)
    for p, g in zip(pred_instances, gt_instances):
        pid, _ = instance_masks(p)
        for k in pid:
            if 1 <= k <= num_slots:
                visible[k - 1] += 1
        for pk, _ in scene_detection(p, g, 0.5)["pairs"]:
            if 1 <= pk <= num_slots:
                matched[pk - 1] += 1
    n = max(len(pred_instances), 1)
    return [{"step": k + 1, "visible": float(visible[k] / n),
             "precision": float(matched[k] / visible[k]) if visible[k] else math.nan} for k in range(num_slots)]
