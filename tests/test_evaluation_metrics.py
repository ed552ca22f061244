"""The paper's measures on hand-computed cases, and against scikit-learn and scikit-image."""

import math

import numpy as np
import pytest

from prismonet.evaluation.metrics import (
    adjusted_rand_index,
    angle_error,
    ari_metrics,
    clip_breakdown,
    count_breakdown,
    depth_metrics,
    detection_metrics,
    image_metrics,
    iou_matrix,
    miss_breakdown,
    scene_detection,
    symmetry_period,
)


def scene(boxes, size=32):
    inst = np.zeros((size, size), np.int64)
    for k, (y0, y1, x0, x1) in enumerate(boxes, 1):
        inst[y0:y1, x0:x1] = k
    return inst


def test_perfect_prediction_gives_ap_ar_one():
    gt = np.stack([scene([(0, 10, 0, 10), (15, 25, 15, 25)]), scene([(2, 12, 2, 12)])])
    pred = gt.copy()
    pred[pred == 1] = 7  # ids need not agree
    m = detection_metrics(pred, gt)
    keys = ("AP0.5", "AR0.5", "F1_0.5", "mAP", "allObj")
    assert m == {k + suffix: 1.0 for k in keys for suffix in ("", "_unfiltered")}


def test_known_iou_cases():
    gt = scene([(0, 10, 0, 10)])  # 100 px
    shifted = scene([(0, 10, 4, 14)])  # overlap 60, union 140 -> IoU 3/7 < 0.5
    assert iou_matrix(shifted[None] == 1, gt[None] == 1)[0, 0] == pytest.approx(60 / 140)
    s = scene_detection(shifted, gt, 0.5)
    assert (s["tp"], s["precision"], s["recall"], s["f1"]) == (0, 0.0, 0.0, 0.0)
    closer = scene([(0, 10, 2, 12)])  # overlap 80, union 120 -> IoU 2/3
    s = scene_detection(closer, gt, 0.5)
    assert s["tp"] == 1 and s["pairs"] == [(1, 1)]
    assert scene_detection(closer, gt, 0.65)["tp"] == 1 and scene_detection(closer, gt, 0.7)["tp"] == 0
    # mAP over 0.5..0.95: found at 0.5, 0.55, 0.6, 0.65 -> 4 of 10 thresholds
    assert detection_metrics(closer[None], gt[None])["mAP"] == pytest.approx(0.4)


def test_one_of_two_found_and_small_objects_ignored():
    gt = scene([(0, 10, 0, 10), (20, 30, 20, 30), (0, 4, 28, 32)])  # third: 16 px < 25, ignored
    pred = scene([(0, 10, 0, 10), (20, 30, 0, 10)])  # finds object 1, plus a false detection
    s = scene_detection(pred, gt, 0.5)
    assert (s["n_gt"], s["n_pred"], s["tp"]) == (2, 2, 1)
    m = detection_metrics(pred[None], gt[None])
    assert m["AP0.5"] == 0.5 and m["AR0.5"] == 0.5 and m["F1_0.5"] == 0.5 and m["allObj"] == 0.0
    with pytest.raises(ValueError, match="at least 0.5"):
        scene_detection(pred, gt, 0.3)


def test_unfiltered_counts_predicted_slivers():
    gt = scene([(0, 10, 0, 10), (20, 30, 20, 30)])
    pred = scene([(0, 10, 0, 10), (20, 30, 20, 30), (12, 16, 12, 16)])  # both found, plus a 16-px sliver
    m = detection_metrics(pred[None], gt[None])
    assert m["AP0.5"] == 1.0 and m["AR0.5"] == 1.0  # the sliver is under 25 px: ignored
    assert m["AP0.5_unfiltered"] == pytest.approx(2 / 3) and m["AR0.5_unfiltered"] == 1.0
    assert m["F1_0.5_unfiltered"] == pytest.approx(0.8) and m["allObj_unfiltered"] == 1.0
    assert m["mAP_unfiltered"] == pytest.approx(2 / 3)
    assert scene_detection(pred, gt, 0.5, pred_min_pixels=1)["n_pred"] == 3


def test_count_breakdown_hand_computed():
    """Rows by the number of visible true objects: a 1-object scene found, and two 2-object scenes with
    one and both found (one with a false detection)."""
    one = scene([(0, 10, 0, 10)])
    two = scene([(0, 10, 0, 10), (20, 30, 20, 30)])
    pred = np.stack([one, scene([(0, 10, 0, 10)]), scene([(0, 10, 0, 10), (20, 30, 20, 30), (12, 18, 0, 8)])])
    rows = count_breakdown(pred, np.stack([one, two, two]))
    assert [(r["objects"], r["scenes"]) for r in rows] == [(1, 1), (2, 2)]
    assert rows[0]["AP0.5"] == 1.0 and rows[0]["AR0.5"] == 1.0 and rows[0]["count_exact"] == 1.0
    assert rows[1]["AR0.5"] == pytest.approx(0.75) and rows[1]["AP0.5"] == pytest.approx((1.0 + 2 / 3) / 2)
    assert rows[1]["count_exact"] == 0.0 and rows[1]["count_bias"] == 0.0  # one short, one over


def test_clip_breakdown_hand_computed():
    """Three objects, one found of the two within the depth range and the one beyond the clip found; an
    object with exactly half its pixels at the clip counts as within range."""
    gt = scene([(0, 10, 0, 10), (20, 30, 20, 30), (40, 50, 40, 50)], size=64)
    pred = scene([(0, 10, 0, 10), (40, 50, 40, 50)], size=64)
    depth = np.full(gt.shape, 5.0)
    depth[40:50, 40:50] = 12.0  # object 3: all at the clip
    depth[20:25, 20:30] = 12.0  # object 2: half
    r = clip_breakdown(pred[None], gt[None], depth[None], 12.0)
    assert r == {"near": {"objects": 2, "AR0.5": 0.5}, "beyond_clip": {"objects": 1, "AR0.5": 1.0}}
    none = clip_breakdown(pred[None], gt[None], np.full((1, *gt.shape), 5.0), 12.0)
    assert none["beyond_clip"]["objects"] == 0 and math.isnan(none["beyond_clip"]["AR0.5"])


def test_miss_breakdown_hand_computed():
    """Six visible objects of 10x10 px: one found, one uncovered, one split, two merged, one misfit."""
    gt = scene([(0, 10, 0, 10), (0, 10, 20, 30), (20, 30, 0, 10), (20, 30, 20, 30), (20, 30, 30, 40), (40, 50, 0, 10)], size=64)
    pred = np.zeros_like(gt)
    pred[0:10, 0:10] = 1  # object 1 found
    pred[0:4, 20:30] = 2  # object 2: 40 % covered -> uncovered
    pred[20:24, 0:10] = 3  # object 3: 40 % in one instance ...
    pred[25:29, 0:10] = 4  # ... and 40 % in another: 80 % covered, no instance holds half -> split
    pred[20:30, 20:40] = 5  # one instance over objects 4 and 5 (IoU 0.5, not above) -> both merged
    pred[40:50, 0:10] = 6
    pred[40:50, 10:20] = 6  # object 6 held whole by an instance twice its size: IoU 0.5 -> misfit
    r = miss_breakdown(pred[None], gt[None])
    assert r == {"objects": 6, "found": 1 / 6, "uncovered": 1 / 6, "split": 1 / 6, "merged": 2 / 6, "misfit": 1 / 6}
    assert sum(v for k, v in r.items() if k != "objects") == pytest.approx(1.0)
    nothing = miss_breakdown(np.zeros((1, 8, 8), np.int64), np.zeros((1, 8, 8), np.int64))
    assert nothing["objects"] == 0 and math.isnan(nothing["found"])


def test_ari_matches_scikit_learn():
    from sklearn.metrics import adjusted_rand_score

    rng = np.random.default_rng(0)
    for _ in range(20):
        a = rng.integers(0, 4, 300)
        b = np.where(rng.random(300) < 0.7, a, rng.integers(0, 5, 300))
        assert adjusted_rand_index(a, b) == pytest.approx(adjusted_rand_score(a, b), abs=1e-12)
    assert adjusted_rand_index([0, 0, 1, 1], [5, 5, 3, 3]) == 1.0
    gt = scene([(0, 10, 0, 10)])
    pred = gt.copy()
    pred[0, 0] = 0
    m = ari_metrics(pred[None], gt[None])
    assert m["ARI"] == pytest.approx(adjusted_rand_score(gt.ravel(), pred.ravel()))
    assert m["ARI-FG"] == pytest.approx(adjusted_rand_score(gt[gt > 0], pred[gt > 0]))


def test_psnr_and_ssim_agree_with_scikit_image():
    from skimage.metrics import peak_signal_noise_ratio, structural_similarity

    rng = np.random.default_rng(1)
    gt = rng.random((2, 3, 32, 32))
    pred = np.clip(gt + rng.normal(0, 0.05, gt.shape), 0, 1)
    m = image_metrics(pred, gt)
    psnr = np.mean([peak_signal_noise_ratio(g, p, data_range=1.0) for p, g in zip(pred, gt)])
    ssim = np.mean([structural_similarity(g, p, channel_axis=0, data_range=1.0, gaussian_weights=True, sigma=1.5,
                                          use_sample_covariance=False) for p, g in zip(pred, gt)])
    assert m["PSNR"] == pytest.approx(psnr, abs=1e-9)
    assert m["SSIM"] == pytest.approx(ssim, abs=2e-3)  # border handling differs slightly
    assert m["img_RMSE"] == pytest.approx(np.mean([np.sqrt(((p - g) ** 2).mean()) for p, g in zip(pred, gt)]))


def test_depth_metrics_hand_computed():
    gt = np.array([[[2.0, 4.0], [0.0, 1.0]]])  # one unknown pixel
    pred = np.array([[[3.0, 4.0], [9.0, 1.5]]])
    m = depth_metrics(pred, gt)
    assert m["depth_RMSE"] == pytest.approx(math.sqrt((1 + 0 + 0.25) / 3))
    assert m["AbsRD"] == pytest.approx((0.5 + 0 + 0.5) / 3)
    assert m["SqRD"] == pytest.approx((0.5 + 0 + 0.25) / 3)


def test_rotation_error_up_to_symmetry():
    assert angle_error(0.1, 2 * math.pi - 0.1, None) == pytest.approx(math.degrees(0.2))
    assert angle_error(math.pi + 0.1, 0.0, math.pi) == pytest.approx(math.degrees(0.1))
    assert angle_error(1.0, 0.0, 0.0) == 0.0
    assert symmetry_period(0) == 0.0  # sphere (1, 1, 1)
    assert symmetry_period(18) == pytest.approx(math.pi / 2)  # cube (1, 1, 1)
    assert symmetry_period(19) == pytest.approx(math.pi)  # box (1, 0.75, 1)


def test_recurrent_step_metrics_hand_computed():
    from prismonet.evaluation.metrics import recurrent_step_metrics

    gt = np.stack([scene([(0, 10, 0, 10), (15, 25, 15, 25)]), scene([(0, 10, 0, 10), (15, 25, 15, 25)])])
    # scene 0: step 1 on gt 1, step 2 misplaced (IoU 0), step 3 hidden (4 px < 25);
    # scene 1: step 2 on gt 2, step 1 hidden entirely, step 3 on gt 1
    p0 = scene([(0, 10, 0, 10), (26, 31, 0, 10)])
    p0[30:32, 30:32] = 3
    p1 = scene([(0, 0, 0, 0), (15, 25, 15, 25), (0, 10, 0, 10)])
    steps = recurrent_step_metrics(np.stack([p0, p1]), gt, 3)
    assert [s["visible"] for s in steps] == [0.5, 1.0, 0.5]
    assert [s["precision"] for s in steps] == [1.0, 0.5, 1.0]
    assert math.isnan(recurrent_step_metrics(np.zeros((1, 32, 32), np.int64), gt[:1], 1)[0]["precision"])


def test_category_shares_hand_computed():
    from prismonet.evaluation.metrics import category_shares

    names = ("sphere", "cylinder", "cube")
    # 3 spheres (2 drawn as spheres), 1 cylinder drawn as a cube, no cube at all
    r = category_shares(np.array([0, 0, 0, 1]), np.array([0, 2, 0, 2]), names)
    assert r["sphere"] == pytest.approx(2 / 3) and r["cylinder"] == 0.0 and math.isnan(r["cube"])
    assert r["objects"] == {"sphere": 3, "cylinder": 1, "cube": 0}
    assert r["mean"] == pytest.approx((2 / 3 + 0.0) / 2)  # categories without objects do not count
    assert math.isnan(category_shares(np.zeros(0), np.zeros(0), names)["mean"])
    with pytest.raises(ValueError, match="true categories"):
        category_shares(np.array([0, 1]), np.array([0]), names)


def test_clevr_code_categories_of_the_shipped_priors():
    from prismonet.evaluation.evaluate import clevr_code_categories
    from prismonet.shapes.prior import load_prior

    cats = clevr_code_categories(load_prior("shipped"))
    assert cats is not None and cats.tolist() == [0] * 9 + [1] * 9 + [2] * 9  # sphere_0..8, cylinder_0..8, cube_0..8
    assert clevr_code_categories(load_prior("cars")) is None  # not Clevr shapes: no category measure


def test_evaluate_reports_the_shape_category_shares():
    """On Clevr scenes with the Clevr prior the shares are those of each matched slot's nearest code, recomputed here."""
    import torch

    from prismonet.assets import asset_path
    from prismonet.data.dataset import SceneDataset
    from prismonet.evaluation.evaluate import evaluate_model
    from prismonet.model.io import load_model

    model, _ = load_model("shipped")
    ds = SceneDataset(asset_path("samples/clevr3"), split="test")
    r = evaluate_model(model, ds, batch_size=16, progress=False)
    sc = r["shape_category"]
    assert sum(sc["objects"].values()) == r["matched_objects"] > 0
    b = ds.batch(list(range(len(ds))))
    with torch.no_grad():
        out = model.eval()(b.rgb, b.K, b.T_world_cam, b.ground_z)
    near = torch.cdist(out.latents.params.z_sh, model.prior.latents.detach()[None]).argmin(-1)
    right = {0: [], 1: [], 2: []}
    for j in range(len(b)):
        for pk, gk in scene_detection(out.composite.instance[j].numpy(), b.instance[j].numpy(), 0.5)["pairs"]:
            true = int(b.obj_shape[j, gk - 1]) // 9  # Clevr shape ids: 9 per category, spheres first
            right[true].append(int(model.prior.category_ids[int(near[j, pk - 1])]) == true)
    for c, name in enumerate(("sphere", "cylinder", "cube")):
        assert sc["objects"][name] == len(right[c])
        if right[c]:
            assert sc[name] == pytest.approx(np.mean(right[c]))
