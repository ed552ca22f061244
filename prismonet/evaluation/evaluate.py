"""``prismonet evaluate CHECKPOINT DATA``: every measure of the paper's Clevr table."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import torch

from prismonet.evaluation.metrics import (
    angle_error,
    ari_metrics,
    category_shares,
    clip_breakdown,
    count_breakdown,
    count_metrics,
    depth_metrics,
    detection_metrics,
    image_metrics,
    miss_breakdown,
    recurrent_step_metrics,
    scene_detection,
    SETTING_SYMMETRY,
    symmetry_period,
)

CAMERA_TOLERANCE = 0.01
"""Relative difference of focal length or principal point (to the focal length), or of the camera
pose (rotation entries; position relative to the camera's distance from the origin), above which a
dataset's camera is taken to differ from the one the model was trained with."""

TABLE_COLUMNS = [
    ("AP0.5", "AP0.5", 3), ("AR0.5", "AR0.5", 3), ("F1_0.5", "F1", 3), ("mAP", "mAP", 3), ("allObj", "allObj", 3),
    ("AP0.5_unfiltered", "AP0.5 unf.", 3), ("AR0.5_unfiltered", "AR0.5 unf.", 3), ("mAP_unfiltered", "mAP unf.", 3),
    ("img_RMSE", "RMSE", 3), ("PSNR", "PSNR", 1), ("SSIM", "SSIM", 3),
    ("depth_RMSE", "D-RMSE", 3), ("AbsRD", "AbsRD", 4), ("SqRD", "SqRD", 4),
    ("pos_err", "pos", 3), ("rot_err", "rot", 1), ("rot_err_sym", "rot sym", 1), ("rot_err_shape", "rot shape", 1),
    ("ARI", "ARI", 3), ("ARI-FG", "ARI-FG", 3),
]


def check_compatible(model, info: dict, ds, any_camera: bool = False) -> None:
    """Raise ``ValueError`` when the dataset's image size does not match the model, its images or
    depth hold non-finite values, or (unless ``any_camera``) any scene's camera, intrinsics or pose,
    differs from the one the model was trained with (a camera-frame model, ``pose_frame = "camera"``, takes
    any camera)."""
    H, W = ds.arrays["rgb"].shape[1:3]
    s = model.cfg.image_size
    if (H, W) != (s, s):
        raise ValueError(f"dataset images are {W}x{H} but the model expects {s}x{s}")
    if not np.isfinite(ds.arrays["depth"]).all():
        raise ValueError("the dataset's depth holds NaN or infinite values")
    if any_camera or "camera_K" not in info or model.cfg.pose_frame == "camera":
        return
    K_train = np.asarray(info["camera_K"], np.float64)
    K_data = np.asarray(ds.arrays["K"], np.float64)  # (N, 3, 3)
    rel = (np.abs(K_data - K_train)[:, [0, 1, 0, 1], [0, 1, 2, 2]] / K_train[0, 0]).max(1)
    bad = np.nonzero(rel > CAMERA_TOLERANCE)[0]
    if bad.size:
        i = int(bad[0])
        raise ValueError(f"camera of {bad.size} scene(s), first scene {i} (fx={K_data[i, 0, 0]:.1f}, cx={K_data[i, 0, 2]:.1f}), differs "
                         f"from the model's training camera (fx={K_train[0, 0]:.1f}, cx={K_train[0, 2]:.1f}); crop and resize the "
                         "images to match (realdata), or pass --any-camera")
    if "camera_T_world_cam" in info:
        T_train = np.asarray(info["camera_T_world_cam"], np.float64)
        T_data = np.asarray(ds.arrays["T_world_cam"], np.float64)  # (N, 4, 4)
        dist = max(float(np.linalg.norm(T_train[:3, 3])), 1e-6)
        diff = np.maximum(np.abs(T_data[:, :3, :3] - T_train[:3, :3]).reshape(len(T_data), -1).max(1),
                          np.linalg.norm(T_data[:, :3, 3] - T_train[:3, 3], axis=1) / dist)
        bad = np.nonzero(diff > CAMERA_TOLERANCE)[0]
        if bad.size:
            i = int(bad[0])
            raise ValueError(f"camera pose of {bad.size} scene(s), first scene {i} (position {np.round(T_data[i, :3, 3], 2).tolist()}), "
                             f"differs from the model's training camera (position {np.round(T_train[:3, 3], 2).tolist()}); "
                             "pass --any-camera to evaluate anyway")


RAISED_FRACTION = 0.25
"""An object is *raised* (resting on another, or floating) when its bottom lies more than this
fraction of its scale above the ground."""


def _raised(b, j: int, k: int, specs) -> bool:
    """Whether object ``k`` of scene ``j`` of batch ``b`` is raised (a shape of ``specs`` only)."""
    sid = int(b.obj_shape[j, k])
    if not 0 <= sid < len(specs) or float(b.obj_axis[j, k, 2]) < 0.999:  # unknown, or tilted
        return False
    bottom = float(b.obj_position[j, k, 2] - b.ground_z[j]) - float(b.obj_scale[j, k]) * specs[sid].half_extents[2]
    return bottom > RAISED_FRACTION * float(b.obj_scale[j, k])


def _generator_config(ds) -> dict:
    """The generator config a dataset was written with (``meta["config"]``), or ``{}``."""
    return (getattr(ds, "meta", None) or {}).get("config", {}) or {}


def dataset_shapes(ds):
    """The ``ShapeSpec`` list a dataset's ``obj_shape`` ids index (its generator's shape library;
    Clevr's when the dataset does not say), and whether rotational symmetries are known for them."""
    from prismonet.shapes.library import CLEVR, shape_library

    cfg = _generator_config(ds)
    name = cfg.get("shapes", CLEVR)
    try:
        return shape_library(name, cfg.get("shape_split", "seen")).specs, name == CLEVR
    except ValueError:  # the import it was made from is not here: ids are not interpretable
        return (), False


def setting_symmetry(ds) -> float | None:
    """The pseudo-symmetry period of an imported setting's scenes (``SETTING_SYMMETRY``, by the setting
    its ``models.json`` names); ``None`` for Clevr shapes and a setting without one (the error up to symmetry is
    then the plain error); NaN when the import the scenes were made from is not here, so that the error up to
    symmetry reads NaN rather than the plain error under its name."""
    import json
    from pathlib import Path

    from prismonet.shapes.library import CLEVR

    name = _generator_config(ds).get("shapes", CLEVR)
    if name == CLEVR:
        return None
    try:
        return SETTING_SYMMETRY.get(json.loads((Path(name) / "models.json").read_text()).get("setting"))
    except (OSError, ValueError):
        return math.nan


def shape_periods(ds, specs, clevr_ids: bool) -> list[float] | None:
    """Each shape's own period of symmetry about z, by the ids of ``ds``'s ``obj_shape`` (``specs``: its library, from
    ``dataset_shapes``): read off the category for Clevr (``symmetry_period``), found from the mesh for an imported
    library (``prismonet.shapes.symmetry.library_yaw_periods``); ``None`` when the library is not here."""
    if clevr_ids:
        return [symmetry_period(i) for i in range(len(specs))]
    if not specs:
        return None
    from prismonet.shapes.symmetry import library_yaw_periods

    cfg = _generator_config(ds)
    return library_yaw_periods(cfg["shapes"], cfg.get("shape_split", "seen"))


def clevr_code_categories(prior) -> torch.Tensor | None:
    """Each prior code's Clevr category id (``prismonet.shapes.clevr_set.CATEGORIES``), or ``None`` when the prior's
    codes are not Clevr shapes (read from its shape names, ``sphere_3`` and so on)."""
    from prismonet.shapes.clevr_set import CATEGORIES

    names, ids = list(getattr(prior, "shape_names", [])), [int(i) for i in getattr(prior, "category_ids", [])]
    if not names or len(names) != len(ids) or not all(0 <= i < len(CATEGORIES) for i in ids):
        return None
    if any(name.rsplit("_", 1)[0] != CATEGORIES[i] for name, i in zip(names, ids)):
        return None
    return torch.tensor(ids)


def _on_cpu(params):
    """A copy of ``SceneParams`` with every tensor field on the CPU (detached): the measures read them one by one."""
    return dataclasses.replace(params, **{f.name: v.detach().cpu() for f in dataclasses.fields(params)
                                          if isinstance(v := getattr(params, f.name), torch.Tensor)})


@torch.no_grad()
def evaluate_model(model, ds, batch_size: int = 16, num_slots: int | None = None, limit: int | None = None, progress: bool = True,
                   inference=None, loss_cfg=None, supersample: int = 1, device: torch.device | str = "cpu") -> dict:
    """Run the model over a dataset split and compute the paper's measures.

    ``inference``: the test-time steps after the encoder (an ``InferenceConfig``; default: none, the
    paper's feed-forward decoding), with ``loss_cfg`` the training losses its slot selection and
    refinement use (default: ``LossConfig()``). The time per scene is reported either way.
    ``supersample``: the image measures (RMSE, PSNR, SSIM) on the decomposition rendered with ``supersample x
    supersample`` rays per pixel (``prismonet.render.supersample``; beyond the paper, whose renderer casts one); every
    other measure reads the one-ray render either way.
    ``per_step`` breaks detections down by encoder step (``recurrent_step_metrics``; with extra slots,
    steps that were not kept count as not visible), with each step's mean position error and median
    predicted / true scale over its matched objects.
    ``device``: where the model and its test-time steps run (the model is moved there, ``Module.to``; the measures are
    computed on the CPU either way).
    """
    import time

    from tqdm import tqdm

    from prismonet.model.inference import InferenceConfig, infer
    from prismonet.render.background import plane_depth
    from prismonet.render.supersample import supersampled_image

    cfg = inference or InferenceConfig()
    device = torch.device(device)
    if supersample > 1 and device.type != "cpu":
        raise ValueError("supersample renders on the CPU: evaluate with device cpu")
    n = len(ds) if limit is None else min(limit, len(ds))
    N = num_slots or model.cfg.num_slots
    step_inst, pred_inst, gt_inst, pred_img, gt_img, pred_d, gt_d, empty_d = [], [], [], [], [], [], [], []
    pos_err, rot_err, rot_sym, rot_shape, pair_step, scale_ratio, height_err, raised = [], [], [], [], [], [], [], []
    true_cat, drawn_cat = [], []  # Clevr data and a Clevr prior: each matched object's category, and its slot's nearest code's
    model.to(device).eval()
    seconds, decoded, aa_seconds = 0.0, 0.0, 0.0
    specs, clevr_ids = dataset_shapes(ds)
    pseudo = None if clevr_ids else setting_symmetry(ds)
    periods = shape_periods(ds, specs, clevr_ids)
    code_cat = clevr_code_categories(model.prior) if clevr_ids else None
    codes = model.prior.latents.detach().cpu() if code_cat is not None else None
    for s in tqdm(range(0, n, batch_size), desc="evaluate", disable=not progress):
        b = ds.batch(list(range(s, min(s + batch_size, n))))
        t0 = time.perf_counter()
        out = infer(model, b.to(device), cfg, loss_cfg, N)
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        seconds += time.perf_counter() - t0
        pi = out.composite.instance.cpu().numpy()
        gi = b.instance.numpy()
        pred_inst.append(pi)
        enc_steps = out.encoder_steps().cpu().numpy()
        steps_1 = np.concatenate([np.zeros((len(b), 1), np.int64), enc_steps + 1], 1)  # id -> 1-based step
        step_inst.append(np.take_along_axis(steps_1, pi.reshape(len(b), -1), 1).reshape(pi.shape))
        gt_inst.append(gi)
        if supersample > 1:
            H, W = b.rgb.shape[-2:]
            t0 = time.perf_counter()
            pred_img.append(supersampled_image(model.sdf_fn, model.color_fn, out.latents.params, out.latents.bg_color, b.K,
                                               b.T_world_cam, H, W, b.ground_z, supersample,
                                               model.render_settings()).numpy())
            aa_seconds += time.perf_counter() - t0
        else:
            pred_img.append(out.composite.image.cpu().numpy())
        gt_img.append(b.rgb.numpy())
        pred_d.append(out.composite.depth[:, 0].cpu().numpy())
        gt_d.append(b.depth[:, 0].numpy())
        H, W = b.depth.shape[-2:]
        empty_d.append(plane_depth(b.K, b.T_world_cam, H, W, b.ground_z, model.cfg.far_depth)[:, 0].numpy())
        p = _on_cpu(out.latents.params)
        decoded += float(p.active.sum()) if p.active is not None else float(p.scale.numel())
        yaw = torch.atan2(p.cos_sin[..., 1], p.cos_sin[..., 0])
        near = None if codes is None else torch.cdist(p.z_sh.to(codes.dtype), codes[None]).argmin(-1)  # (B, N)
        for j in range(len(b)):
            for pk, gk in scene_detection(pi[j], gi[j], 0.5)["pairs"]:
                pos_err.append(float((p.position[j, pk - 1] - b.obj_position[j, gk - 1]).norm()))
                height_err.append(float((p.position[j, pk - 1, 2] - b.obj_position[j, gk - 1, 2]).abs()))
                raised.append(_raised(b, j, gk - 1, specs))
                pair_step.append(int(steps_1[j, pk]))
                scale_ratio.append(float(p.scale[j, pk - 1] / b.obj_scale[j, gk - 1]))
                gt_yaw = float(b.obj_yaw[j, gk - 1])
                rot_err.append(angle_error(float(yaw[j, pk - 1]), gt_yaw, None))
                sid = int(b.obj_shape[j, gk - 1])
                own = periods[sid] if periods is not None and 0 <= sid < len(periods) else None
                rot_sym.append(angle_error(float(yaw[j, pk - 1]), gt_yaw, own if clevr_ids else pseudo))
                if own:  # None: not known; 0: a round shape, which has no yaw
                    rot_shape.append(angle_error(float(yaw[j, pk - 1]), gt_yaw, own))
                if near is not None and 0 <= sid < len(specs):
                    true_cat.append(specs[sid].category_id)
                    drawn_cat.append(int(code_cat[int(near[j, pk - 1])]))
    cat = np.concatenate
    results = {"scenes": n, "num_slots": N, "extra_slots": cfg.extra_slots, "inference": cfg.record(), "supersample": supersample}
    results.update(detection_metrics(cat(pred_inst), cat(gt_inst)))
    results.update(count_metrics(cat(pred_inst), cat(gt_inst)))
    results["by_count"] = count_breakdown(cat(pred_inst), cat(gt_inst))
    results["by_depth_clip"] = clip_breakdown(cat(pred_inst), cat(gt_inst), cat(gt_d), model.cfg.far_depth)
    results["misses"] = miss_breakdown(cat(pred_inst), cat(gt_inst))
    results.update(image_metrics(cat(pred_img), cat(gt_img)))
    results.update(depth_metrics(cat(pred_d), cat(gt_d)))
    results["depth_RMSE_empty"] = depth_metrics(cat(empty_d), cat(gt_d))["depth_RMSE"]  # the ground alone (the paper's 6-DoF table)
    results.update(ari_metrics(cat(pred_inst), cat(gt_inst)))
    results["pos_err"] = float(np.mean(pos_err)) if pos_err else math.nan
    results["rot_err"] = float(np.median(rot_err)) if rot_err else math.nan
    results["rot_err_sym"] = float(np.median(rot_sym)) if rot_sym else math.nan
    results["rot_err_shape"] = float(np.median(rot_shape)) if rot_shape else math.nan  # up to each shape's own symmetry
    results["matched_not_round"] = len(rot_shape)
    results["matched_objects"] = len(pos_err)
    if code_cat is not None:  # drawn as its own kind: the slot's shape latent nearest a code of the object's category
        from prismonet.shapes.clevr_set import CATEGORIES

        results["shape_category"] = category_shares(np.asarray(true_cat, np.int64), np.asarray(drawn_cat, np.int64), CATEGORIES)
    h, up = np.asarray(height_err), np.asarray(raised, dtype=bool)
    results["height_err"] = float(h.mean()) if h.size else math.nan
    results["height_err_raised"] = float(h[up].mean()) if up.any() else math.nan
    results["matched_raised"] = int(up.sum())
    steps = recurrent_step_metrics(cat(step_inst), cat(gt_inst), N + cfg.extra_slots)
    pair_step, pos_arr, ratio_arr = np.asarray(pair_step), np.asarray(pos_err), np.asarray(scale_ratio)
    for st in steps:
        sel = pair_step == st["step"]
        st["pos_err"] = float(pos_arr[sel].mean()) if sel.any() else math.nan
        st["scale_ratio"] = float(np.median(ratio_arr[sel])) if sel.any() else math.nan
    results["per_step"] = steps
    results["refine_steps"] = cfg.refine.steps
    results["search_rounds"] = cfg.search.rounds
    results["color_fit_steps"] = cfg.color_fit.steps
    results["seconds_per_scene"] = seconds / max(n, 1)
    results["device"] = str(device)
    results["supersample_seconds_per_scene"] = aa_seconds / max(n, 1)  # the anti-aliased image's render, on top
    results["slots_decoded"] = decoded / max(n, 1)
    has_depth = any(bool((g > 0).any()) for g in gt_d)  # photos have none: their depth measures are NaN, and say so
    bad = [k for k in ("AP0.5", "AR0.5", "PSNR") + (("depth_RMSE",) if has_depth else ()) if not math.isfinite(results[k])]
    if bad:
        raise ValueError(f"non-finite measures {bad}: the model or the data holds NaN or infinite values")
    return results


def format_steps(results: dict) -> str:
    """A Markdown table of ``results["per_step"]``: one row per recurrent encoder step."""
    lines = ["| step | visible | precision@0.5 | pos | scale pred/true |", "|---|---|---|---|---|"]
    for st in results["per_step"]:
        lines.append(f"| {st['step']} | {st['visible']:.3f} | {st['precision']:.3f} | {st['pos_err']:.3f} | {st['scale_ratio']:.3f} |")
    return "\n".join(lines)


def format_counts(results: dict) -> str:
    """A Markdown table of ``results["by_count"]``: one row per number of visible objects."""
    lines = ["| objects | scenes | AP0.5 | AR0.5 | AP0.5 unf. | count right | count bias |", "|---|---|---|---|---|---|---|"]
    for r in results["by_count"]:
        lines.append(f"| {r['objects']} | {r['scenes']} | {r['AP0.5']:.3f} | {r['AR0.5']:.3f} | {r['AP0.5_unfiltered']:.3f} | "
                     f"{r['count_exact']:.3f} | {r['count_bias']:+.2f} |")
    return "\n".join(lines)


def format_table(rows: list[tuple[str, dict]]) -> str:
    """A Markdown table laid out like the paper's Clevr table (one row per evaluated setting)."""
    head = "| #obj | " + " | ".join(h for _, h, _ in TABLE_COLUMNS) + " |"
    sep = "|---" * (len(TABLE_COLUMNS) + 1) + "|"
    lines = [head, sep]
    for name, r in rows:
        lines.append(f"| {name} | " + " | ".join(f"{r[k]:.{d}f}" for k, _, d in TABLE_COLUMNS) + " |")
    return "\n".join(lines)
