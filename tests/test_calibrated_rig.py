"""The calibrated real-photo path: one world scale (``realdata.world``), rectification through the
table (``realdata.rectify``), and the README's three commands end to end on a rendered rig with a
known answer (``realdata.synthetic``)."""

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from prismonet.data.clevr import ClevrConfig, clevr_camera
from realdata.rectify import ground_homography, photo_footprint, rectify, rectifying_homography
from realdata.world import CameraError, WorldMapping, camera_warnings

TRAIN = clevr_camera(ClevrConfig())
T_TRAIN = TRAIN.T_world_cam.double().numpy()
K_TRAIN = TRAIN.K.double().numpy()
TRAIN_ELEVATION = math.degrees(math.asin(-T_TRAIN[2, 2]))  # 28.32


def similarity(s, yaw, t):
    c, si = math.cos(yaw), math.sin(yaw)
    M = np.eye(4)
    M[:3, :3] = s * np.array([[c, -si, 0], [si, c, 0], [0, 0, 1]])
    M[:3, 3] = t
    return M


def moved(T, M):
    """A camera pose carried by the similarity ``M`` (rotation kept, position mapped)."""
    out = M @ T
    out[:3, :3] /= np.cbrt(np.linalg.det(M[:3, :3]))
    return out


def test_world_map_recovers_a_known_similarity():
    # the photo camera is the training camera carried into a metric table frame: 4 cm per unit, turned
    # 40 degrees, shifted; the derived map must take it back exactly
    M_table_model = similarity(0.04, math.radians(40), [0.3, -0.1, 0.0])
    T_table_cam = moved(T_TRAIN, M_table_model)
    world = WorldMapping.derive(T_table_cam, T_TRAIN)
    assert world.metres_per_unit == pytest.approx(0.04, rel=1e-12) and world.scale_source == "derived"
    assert np.allclose(world.camera_in_model(T_table_cam), T_TRAIN, atol=1e-9)
    pts = np.random.default_rng(0).normal(size=(5, 3))
    assert np.allclose(world.to_table(world.to_model(pts)), pts, atol=1e-12)
    assert world.distance_ratio == pytest.approx(1.0) and camera_warnings(world) == []
    assert WorldMapping.from_dict(json.loads(json.dumps(world.to_dict()))) == world
    stated = WorldMapping.derive(T_table_cam, T_TRAIN, metres_per_unit=0.02)  # a stated scale: twice as far in model units
    assert stated.distance_ratio == pytest.approx(2.0) and stated.scale_source == "stated"
    assert any("distance" in w for w in camera_warnings(stated))


def test_world_map_refuses_cameras_it_cannot_use():
    below = T_TRAIN.copy()
    below[2, 3] = -1.0
    with pytest.raises(CameraError, match="above the table"):
        WorldMapping.derive(below, T_TRAIN)
    flat = np.eye(4)
    flat[:3, :3] = np.array([[0, 0, 1.0], [-1, 0, 0], [0, -1, 0]])  # optical axis horizontal, along world x
    flat[:3, 3] = [0, 0, 1.0]
    with pytest.raises(CameraError, match="look down"):
        WorldMapping.derive(flat, T_TRAIN)
    with pytest.raises(CameraError, match="metres per model unit"):
        WorldMapping.derive(T_TRAIN, T_TRAIN, metres_per_unit=0.0)
    steep = WorldMapping(1.0, 0.0, (0, 0, 0), (0, 0, 0), "derived", 60.0, TRAIN_ELEVATION, 1.0)
    assert any("looks 60° down" in w for w in camera_warnings(steep))


def test_ground_homography_is_the_camera_on_the_ground():
    pts = np.array([[0.3, -1.2, 0.0], [1.5, 1.5, 0.0], [-1.0, 0.4, 0.0]])
    uv = TRAIN.world_to_pixels(torch.tensor(pts)).numpy()
    G = ground_homography(K_TRAIN, T_TRAIN, 0.0)
    q = np.c_[pts[:, :2], np.ones(3)] @ G.T
    assert np.allclose(q[:, :2] / q[:, 2:], uv, atol=1e-6)


def test_rectify_is_exact_for_a_camera_with_the_same_centre():
    # a wider, shifted photo camera at the training camera's centre, looking 3 degrees off: the warp
    # must reproduce the training view of a ground texture, up to resampling
    rng = np.random.default_rng(1)
    K_photo = np.array([[300.0, 0, 170.0], [0, 300.0, 118.0], [0, 0, 1]])
    T_photo = T_TRAIN.copy()
    T_photo[:3, :3] = T_TRAIN[:3, :3] @ cv2.Rodrigues(np.array([0.03, -0.05, 0.02]))[0]
    tex = cv2.GaussianBlur(rng.uniform(0, 1, (40, 40, 3)).astype(np.float32), (0, 0), 1.5)

    def view(K, T, h, w, factor=1):  # the ground texture (1 texel = 0.25 units) seen by a camera, by ray casting
        from prismonet.geometry.camera import camera_rays

        K = K.copy()
        K[:2] *= factor
        K[:2, 2] += (factor - 1) / 2
        d = camera_rays(torch.tensor(K), h * factor, w * factor).reshape(-1, 3).numpy() @ T[:3, :3].T
        t = -T[2, 3] / d[:, 2]
        xy = T[:3, 3][:2] + t[:, None] * d[:, :2]
        img = cv2.remap(tex, ((xy[:, 0] / 0.25) + 20).reshape(h * factor, w * factor).astype(np.float32),
                        ((xy[:, 1] / 0.25) + 20).reshape(h * factor, w * factor).astype(np.float32), cv2.INTER_LINEAR)
        return cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA) if factor > 1 else img

    photo = view(K_photo, T_photo, 240, 320)
    out, coverage = rectify(photo, K_photo, T_photo, K_TRAIN, T_TRAIN, 0.0, 64)
    truth = view(K_TRAIN, T_TRAIN, 64, 64, factor=8)
    assert coverage == 1.0
    assert np.abs(out - truth).mean() < 0.01 and np.abs(out - truth).max() < 0.08
    H = rectifying_homography(K_photo, T_photo, K_TRAIN, T_TRAIN, 0.0)
    assert np.isfinite(H).all()
    # a photo camera looking elsewhere covers part of the view only
    T_away = T_TRAIN.copy()
    T_away[:3, :3] = T_TRAIN[:3, :3] @ cv2.Rodrigues(np.array([0.0, 0.35, 0.0]))[0]
    part = photo_footprint(K_photo, T_away, K_TRAIN, T_TRAIN, 0.0, 64, (240, 320))
    assert 0.2 < part.mean() < 0.95


@pytest.fixture(scope="module")
def rig(tmp_path_factory):
    """The README's three commands on a rendered rig: another heading, look-at, focal length, principal
    point, image size, table orientation and metric scale than the training camera's."""
    from prismonet.cli import main
    from realdata.synthetic import RigConfig, render_rig

    out = tmp_path_factory.mktemp("rig")
    cfg = RigConfig(elevation=TRAIN_ELEVATION)  # the training elevation: rectification is then exact for every point
    truth = render_rig(out, scenes=4, seed=0, cfg=cfg)
    board = ["--board", "9x6", "--square", str(cfg.square_m)]
    assert main(["calibrate", "intrinsics", *map(str, sorted((out / "boards").glob("*.png"))), *board, "--out", str(out / "cam.yml")]) == 0
    assert main(["calibrate", "ground", str(out / "ground.png"), "--camera", str(out / "cam.yml"), *board, "--out", str(out / "ground.yml")]) == 0
    photos = [str(out / s["photo"]) for s in truth["scenes"]]
    # a fixed model, the one the thresholds below were set with: these tests are of the calibrated geometry, and a
    # new default model (which finds more, and harder, objects) must not move them; its rig figures are in EVALUATION.md
    assert main(["real", "reconstruct", *photos, "--camera", str(out / "ground.yml"), "--out", str(out / "recon"),
                 "--model", "clevr3_distilled", "--quiet"]) == 0
    return out, cfg, truth, json.loads((out / "recon" / "summary.json").read_text())


def test_rig_calibration_recovers_the_camera_and_the_scale(rig):
    from calibration.storage import load_calibration

    out, cfg, truth, summary = rig
    _, T = load_calibration(out / "ground.yml")
    T_true = np.asarray(truth["T_table_cam"])
    assert np.abs(T[:3, 3] - T_true[:3, 3]).max() < 2e-3  # metres
    assert np.degrees(np.arccos(np.clip((np.trace(T[:3, :3].T @ T_true[:3, :3]) - 1) / 2, -1, 1))) < 0.3
    world = WorldMapping.from_dict(summary[0]["prepare"]["world"])
    assert world.metres_per_unit == pytest.approx(cfg.metres_per_unit, rel=0.01)
    assert all(r["prepare"]["coverage"] == 1.0 and r["warnings"] == [] for r in summary)
    # the path's own position error: every true object carried into the model's world by the recovered
    # calibration and map, against the same object carried by the exact ones (model units)
    exact = WorldMapping.derive(T_true, T_TRAIN)
    table = np.asarray([o["position_table_m"] for sc in truth["scenes"] for o in sc["objects"]])
    err = np.linalg.norm(world.to_model(table) - exact.to_model(table), axis=1)
    assert err.max() < 0.05, err  # measured 0.01; the budget for the whole path is 0.2


def test_rig_true_objects_land_on_their_rectified_pixels(rig):
    """Geometry alone: the true objects, carried into the model's world by the *recovered* map and
    rendered by the training camera, cover the same pixels as their instance masks warped like the photo."""
    from dataclasses import replace

    from prismonet.data.clevr import ObjectSpec, sample_scene
    from prismonet.data.raycast_gt import render_scene
    from realdata.synthetic import write_rig_datasets

    out, cfg, truth, summary = rig
    rect, _ = write_rig_datasets(out, out / "recon", out / "eval")
    clevr = ClevrConfig()
    for sc in truth["scenes"]:
        ann = json.loads((rect / "annotations" / f"{sc['photo'][7:-4]}.json").read_text())
        spec = sample_scene(np.random.default_rng(sc["seed"]), clevr)
        objs = tuple(ObjectSpec(o.shape_id, o.category_id, o.color_id, a["scale"], tuple(a["position"]), a["yaw"])
                     for o, a in zip(spec.objects, ann["objects"]))
        direct = render_scene(replace(spec, objects=objs, camera=TRAIN), clevr).instance
        warped = cv2.imread(str(rect / "instance" / f"{sc['photo'][7:-4]}.png"), cv2.IMREAD_UNCHANGED)
        for k in range(1, len(objs) + 1):
            a, b = direct == k, warped == k
            if a.sum() >= 25:
                assert (a & b).sum() / (a | b).sum() > 0.85, (sc["photo"], k)


def test_rig_reconstructed_positions_against_the_truth(rig):
    """The model's position error through the three commands, scored by ``prismonet evaluate`` beside its
    error on the same layouts seen by its own camera. EVALUATION.md reports the larger run
    (scripts/calibrated_rig.py); here: the calibrated path adds little to the model's own error."""
    from prismonet.cli import main
    from realdata.synthetic import write_rig_datasets

    out, cfg, truth, summary = rig
    rect, direct = write_rig_datasets(out, out / "recon", out / "eval")
    r = {}
    for name, data in (("calibrated", rect), ("direct", direct)):
        assert main(["evaluate", "shipped", str(data), "--color-only", "--quiet", "--json", str(out / f"{name}.json")]) == 0
        r[name] = json.loads((out / f"{name}.json").read_text())
    # 4 scenes are few: the model's own error varies by +-0.1 between views of one layout, so this checks
    # the path works (objects found and placed near the truth), not the 0.2 target (EVALUATION.md: 64 scenes)
    assert r["calibrated"]["matched_objects"] >= 8  # of 12
    assert r["calibrated"]["pos_err"] <= 0.35, r["calibrated"]["pos_err"]
    assert r["calibrated"]["AP0.5"] >= 0.6
    assert all(len(rec["objects"]) == rec["objects_found"] and all("position_table_m" in o for o in rec["objects"]) for rec in summary)


def test_rig_objects_found_where_they_are(rig):
    """The issue's end-to-end figure on the rig: each true object against the found object nearest to it
    (one to one, Hungarian on the ground distance, in model units, through the recovered calibration);
    the matched objects' mean position error must be within 0.2 model units."""
    from scipy.optimize import linear_sum_assignment

    out, cfg, truth, summary = rig
    world = WorldMapping.from_dict(summary[0]["prepare"]["world"])
    errors = []
    for sc, rec in zip(truth["scenes"], summary):
        true = world.to_model(np.asarray([o["position_table_m"] for o in sc["objects"]]))
        found = np.asarray([o["position"] for o in rec["objects"]])
        if not len(found):
            continue
        cost = np.linalg.norm(true[:, None, :2] - found[None, :, :2], axis=2)
        rows, cols = linear_sum_assignment(cost)
        errors += [np.linalg.norm(true[r] - found[c]) for r, c in zip(rows, cols) if cost[r, c] < 0.5]
    print(f"rig: {len(errors)} objects matched, mean position error {np.mean(errors):.3f} model units")
    assert len(errors) >= 8 and np.mean(errors) <= 0.2


def test_rig_photos_keep_their_own_camera_for_camera_frame_models(rig, tmp_path):
    """``own_camera``: the prepared photo's camera (cropped, resized, in model units) sees every true object
    where the calibrated photo camera (metres) sees it in the photo, carried through the same crop and resize."""
    from calibration.storage import load_calibration
    from prismonet.data.dataset import SceneDataset
    from prismonet.model.io import load_model, training_camera
    from realdata.pipeline import prepare_photos

    out, cfg, truth, summary = rig
    net, info = load_model("shipped")
    photos = [str(out / s["photo"]) for s in truth["scenes"]]
    recs = prepare_photos(photos, tmp_path / "own", 64, out / "ground.yml", view=training_camera(net, info), own_camera=True)
    cal, T = load_calibration(out / "ground.yml")
    ds = SceneDataset(tmp_path / "own")
    for i, (sc, rec) in enumerate(zip(truth["scenes"], recs)):
        assert rec["own_camera"] and rec["warnings"] == []
        world = WorldMapping.from_dict(rec["world"])
        table = np.asarray([o["position_table_m"] for o in sc["objects"]])
        x_cam = (table - T[:3, 3]) @ T[:3, :3]  # the photo camera (metres)
        uv = (x_cam @ np.asarray(cal.K).T)[:, :2] / x_cam[:, 2:]
        x0, y0, side, _ = rec["crop_box"]
        expect = (uv - [x0, y0] + 0.5) * (64 / side) - 0.5  # through the crop and the resize
        b = ds.batch([ds.names.index(Path(sc["photo"]).stem)])
        Tm = b.T_world_cam[0].double().numpy()
        xm = (world.to_model(table) - Tm[:3, 3]) @ Tm[:3, :3]  # the prepared camera (model units)
        got = (xm @ b.K[0].double().numpy().T)[:, :2] / xm[:, 2:]
        assert np.abs(got - expect).max() < 1e-3, (got, expect)
        assert ((got > 0) & (got < 63)).all()  # the crop around the model's view keeps every object


def test_reconstruct_hands_a_camera_frame_model_the_photo_camera(rig, tmp_path):
    """``real reconstruct`` with a camera-frame model (here the shipped weights under ``pose_frame = "camera"``)
    decodes each photo with its own calibrated camera (the latent scene records the prepared photo camera, not
    the training camera)."""
    from dataclasses import replace

    from prismonet.cli import main
    from prismonet.model.io import load_model, save_model
    from prismonet.model.prismonet import PriSMONet

    out, cfg, truth, summary = rig
    net, info = load_model("shipped")
    cam_net = PriSMONet(replace(net.cfg, pose_frame="camera"))
    cam_net.load_state_dict(net.state_dict())
    save_model(cam_net, tmp_path / "cam_model", {k: v for k, v in info.items() if k.startswith("camera") or k == "ground_z"})
    photos = [str(out / s["photo"]) for s in truth["scenes"][:2]]
    assert main(["real", "reconstruct", *photos, "--camera", str(out / "ground.yml"), "--model", str(tmp_path / "cam_model"),
                 "--out", str(tmp_path / "recon"), "--quiet"]) == 0
    rows = json.loads((tmp_path / "recon" / "summary.json").read_text())
    assert all(r["camera"] == "the photo's own calibrated camera" and r["prepare"]["own_camera"] and r["finite"] for r in rows)
    scene = json.loads((tmp_path / "recon" / f"{Path(photos[0]).stem}.json").read_text())
    assert np.allclose(np.asarray(scene["camera"]["T_world_cam"]), np.asarray(rows[0]["prepare"]["camera"]["T_world_cam"]), atol=1e-5)
    assert all(r["warnings"] == [] for r in rows)
    # an elevation by eye does not override a calibrated camera, and the run says so per photo
    assert main(["real", "reconstruct", photos[0], "--camera", str(out / "ground.yml"), "--model", str(tmp_path / "cam_model"),
                 "--out", str(tmp_path / "recon_elev"), "--elevation", "70", "--quiet"]) == 0
    row, = json.loads((tmp_path / "recon_elev" / "summary.json").read_text())
    assert row["camera"] == "the photo's own calibrated camera"
    assert row["warnings"] == ["elevation 70 deg ignored: this photo's calibrated camera is used as it is"]
