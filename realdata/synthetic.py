"""A calibrated rig with a known answer: the photos a user would take, rendered, and the truth.

``render_rig`` writes, for one metric camera that is *not* the model's training camera (another
heading, elevation, look-at point, focal length, principal point and image size):

- ``boards/board_NN.png``: chessboard views for ``calibrate intrinsics``;
- ``ground.png``: the board lying on the table, seen by the camera (for ``calibrate ground``);
- ``scenes/scene_NN.png``: Clevr-style scenes on the same table from the same camera (a tripod:
  the board is lifted before the objects are placed), rendered by the ground-truth raycaster, with
  their instance masks in ``instance/scene_NN.png`` (0 = table, k = object k);
- ``truth.json``: the board, the true camera, the scale (metres per model unit) and every
  object's position in model units and on the table (metres, the frame ``calibrate ground`` gives:
  origin at the board's first inner corner, z up).

The scenes are the Clevr generator's (same sampler, shapes, colours and light); only the camera and
the metric frame differ, so the model's error through the calibrated path can be compared with its
error on the same scenes seen by its own camera.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np


@dataclass(frozen=True)
class RigConfig:
    """The true rig. Angles in degrees; lengths in model units unless named ``_m``."""

    metres_per_unit: float = 0.04
    """True scale: a Clevr object of half-size 0.5 units is 2 cm."""
    heading_offset: float = 35.0
    """The camera's heading, turned this much from the training camera's."""
    elevation: float = 33.0
    """Degrees below the horizon (the training camera: 28.3)."""
    distance: float | None = None
    """From the look-at point (default: the training camera's, 11.26)."""
    look_at: tuple[float, float] = (0.3, -0.2)
    """Where the optical axis meets the table, model units (the training camera: the origin)."""
    table_yaw: float = 20.0
    """The board's (table frame's) x axis, turned this much from the model's x axis."""
    size: tuple[int, int] = (640, 480)
    """Photo width, height."""
    focal: float = 600.0
    principal: tuple[float, float] = (326.0, 236.0)
    board: tuple[int, int] = (9, 6)
    square_m: float = 0.02
    board_views: int = 8


def _look_at(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    import torch

    from prismonet.geometry.camera import look_at

    return look_at(torch.tensor(eye, dtype=torch.float64), torch.tensor(target, dtype=torch.float64)).numpy()


def rig_camera(cfg: RigConfig, train_T: np.ndarray) -> np.ndarray:
    """The photo camera's ``T_world_cam`` in model units."""
    c, a = train_T[:3, 3], train_T[:3, 2]
    heading = math.atan2(a[1], a[0]) + math.radians(cfg.heading_offset)
    dist = cfg.distance if cfg.distance is not None else float(c[2] / -a[2])
    e = math.radians(cfg.elevation)
    target = np.array([cfg.look_at[0], cfg.look_at[1], 0.0])
    eye = target - dist * np.array([math.cos(e) * math.cos(heading), math.cos(e) * math.sin(heading), -math.sin(e)])
    return _look_at(eye, target)


def table_from_model(cfg: RigConfig) -> np.ndarray:
    """``(4, 4)`` true similarity model units -> table metres; the model's origin lies under the board's centre."""
    cols, rows = cfg.board
    centre = np.array([(cols - 1) / 2 * cfg.square_m, -(rows - 1) / 2 * cfg.square_m, 0.0])
    y = math.radians(cfg.table_yaw)
    R = np.array([[math.cos(y), -math.sin(y), 0], [math.sin(y), math.cos(y), 0], [0, 0, 1.0]])
    M = np.eye(4)
    M[:3, :3] = cfg.metres_per_unit * R.T  # the table's x axis is the model's turned by table_yaw
    M[:3, 3] = centre
    return M


def _board_views(cfg: RigConfig, board, K: np.ndarray, rng: np.random.Generator) -> list[np.ndarray]:
    import cv2

    from calibration.synthetic import render_board

    cols, rows = cfg.board
    centre = np.array([(cols - 1) / 2 * cfg.square_m, (rows - 1) / 2 * cfg.square_m, 0.0])
    dist = cfg.focal * (cols + 1) * cfg.square_m / (0.55 * cfg.size[0])  # the board fills about half the width
    views = []
    for _ in range(cfg.board_views):
        R = cv2.Rodrigues(rng.uniform(-0.45, 0.45, 3))[0]
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = np.array([0.0, 0.0, dist]) + rng.uniform(-0.15, 0.15, 3) * dist - R @ centre
        views.append(render_board(board, K, T, cfg.size))
    return views


def render_rig(out: str | Path, scenes: int = 4, seed: int = 0, cfg: RigConfig = RigConfig(), num_objects: int = 3) -> dict:
    """Write the rig's photos and ``truth.json`` into ``out``; returns the truth."""
    import torch

    from calibration.board import Chessboard
    from calibration.ground import T_WORLD_BOARD
    from calibration.synthetic import render_board
    from prismonet.data.clevr import ClevrConfig, clevr_camera, sample_scene
    from prismonet.data.raycast_gt import render_scene
    from prismonet.files import write_image
    from prismonet.geometry.camera import Camera, intrinsics_matrix

    out = Path(out)
    for sub in ("boards", "scenes", "instance"):
        (out / sub).mkdir(parents=True, exist_ok=True)
    clevr = ClevrConfig(num_objects=num_objects)
    train_T = clevr_camera(clevr).T_world_cam.double().numpy()
    T_model_cam = rig_camera(cfg, train_T)
    M = table_from_model(cfg)
    T_table_cam = M @ T_model_cam
    T_table_cam[:3, :3] /= cfg.metres_per_unit  # a similarity: rotation kept, position scaled
    K = intrinsics_matrix(cfg.focal, cfg.focal, *cfg.principal, dtype=torch.float64).numpy()
    board = Chessboard(*cfg.board, cfg.square_m)
    rng = np.random.default_rng([seed, 7])
    for i, img in enumerate(_board_views(cfg, board, K, rng)):
        write_image(out / "boards" / f"board_{i:02d}.png", img)
    write_image(out / "ground.png", render_board(board, K, np.linalg.inv(T_table_cam) @ T_WORLD_BOARD, cfg.size))
    W, H = cfg.size
    camera = Camera(torch.tensor(K, dtype=torch.float32), torch.tensor(T_model_cam, dtype=torch.float32), H, W)
    truth = {"rig": {k: v for k, v in cfg.__dict__.items()}, "K": K.tolist(), "T_table_cam": T_table_cam.tolist(),
             "T_model_cam": T_model_cam.tolist(), "table_from_model": M.tolist(), "scenes": []}
    for i in range(scenes):
        spec = replace(sample_scene(np.random.default_rng([seed, i]), clevr), camera=camera)
        r = render_scene(spec, clevr)
        write_image(out / "scenes" / f"scene_{i:02d}.png", r.rgb[..., ::-1])
        write_image(out / "instance" / f"scene_{i:02d}.png", r.instance)
        objs = [{"position": list(o.position), "scale": o.scale, "yaw": o.yaw, "shape_id": o.shape_id, "color_id": o.color_id,
                 "position_table_m": (M[:3, :3] @ np.asarray(o.position) + M[:3, 3]).tolist()} for o in spec.objects]
        truth["scenes"].append({"photo": f"scenes/scene_{i:02d}.png", "seed": [seed, i], "objects": objs})
    (out / "truth.json").write_text(json.dumps(truth, indent=1))
    return truth


def position_errors(truth_scene: dict, found: list[dict], metres_per_unit: float) -> list[float]:
    """Errors (model units) of the true objects' table positions against the nearest found objects,
    matched one to one (Hungarian on the 3-D table distance); a true object with no match counts as missing
    and is left out (the caller reports the count)."""
    from scipy.optimize import linear_sum_assignment

    if not found:
        return []
    t = np.asarray([o["position_table_m"] for o in truth_scene["objects"]])
    p = np.asarray([o["position_table_m"] for o in found])
    d = np.linalg.norm(t[:, None] - p[None], axis=-1)
    rows, cols = linear_sum_assignment(d)
    return [float(d[r, c] / metres_per_unit) for r, c in zip(rows, cols)]


def _write_scene(root: Path, name: str, rgb: np.ndarray, instance: np.ndarray, objects: list[dict], camera: dict) -> None:
    from prismonet.files import write_image

    for sub in ("rgb", "instance", "annotations"):
        (root / sub).mkdir(parents=True, exist_ok=True)
    write_image(root / "rgb" / f"{name}.png", rgb[..., ::-1])
    write_image(root / "instance" / f"{name}.png", instance.astype(np.uint8))
    (root / "annotations" / f"{name}.json").write_text(json.dumps({"objects": objects, "camera": camera}))


def write_rig_datasets(rig: str | Path, recon: str | Path, out: str | Path, model: str = "shipped") -> tuple[Path, Path]:
    """Folder datasets that ``prismonet evaluate`` scores, so the calibrated path and the model's own
    view are measured by the same code: ``out/rectified`` (the prepared photos of ``real reconstruct
    --camera`` with the true instances warped like the photo and the true objects mapped into the
    model's world by the *recovered* world map) and ``out/direct`` (the same layouts rendered by the
    model's training camera, with depth)."""
    import cv2

    from calibration.storage import load_calibration
    from prismonet.data.clevr import ClevrConfig, sample_scene
    from prismonet.data.raycast_gt import render_scene
    from prismonet.files import read_image
    from prismonet.model.io import load_model, training_camera
    from realdata.rectify import rectify_labels
    from realdata.world import WorldMapping

    rig, recon, out = Path(rig), Path(recon), Path(out)
    truth = json.loads((rig / "truth.json").read_text())
    summary = {Path(r["photo"]).name: r for r in json.loads((recon / "summary.json").read_text())}
    net, info = load_model(model)
    cam, ground_z = training_camera(net, info)
    cam_d = {"K": cam.K.tolist(), "T_world_cam": cam.T_world_cam.tolist(), "height": cam.height, "width": cam.width}
    clevr = ClevrConfig(num_objects=len(truth["scenes"][0]["objects"]))
    mpu_true = truth["rig"]["metres_per_unit"]
    table_yaw = math.radians(truth["rig"]["table_yaw"])
    for sc in truth["scenes"]:
        name = Path(sc["photo"]).stem
        rec = summary[Path(sc["photo"]).name]
        world = WorldMapping.from_dict(rec["prepare"]["world"])
        M = world.matrix()
        cal, T_table_cam = load_calibration(rec["prepare"]["calibration"])
        T_photo = world.camera_in_model(T_table_cam)
        inst = rectify_labels(read_image(rig / "instance" / f"{name}.png", cv2.IMREAD_UNCHANGED), cal.K, T_photo,
                              cam.K.double().numpy(), cam.T_world_cam.double().numpy(), ground_z, cam.height)
        rgb = read_image(recon / "prepared" / "rgb" / f"{name}.png", cv2.IMREAD_COLOR)[..., ::-1]
        objs = [{"shape_id": o["shape_id"], "color": o["color_id"], "yaw": o["yaw"] - table_yaw + world.yaw,
                 "scale": o["scale"] * mpu_true * world.units_per_metre,
                 "position": (M[:3, :3] @ np.asarray(o["position_table_m"]) + M[:3, 3]).tolist()} for o in sc["objects"]]
        _write_scene(out / "rectified", name, rgb, inst, objs, cam_d)
        spec = sample_scene(np.random.default_rng(sc["seed"]), clevr)
        r = render_scene(spec, clevr)
        objs = [{"shape_id": o.shape_id, "color": o.color_id, "yaw": o.yaw, "scale": o.scale, "position": list(o.position)}
                for o in spec.objects]
        _write_scene(out / "direct", name, r.rgb, r.instance, objs, cam_d)
    for sub in ("rectified", "direct"):
        (out / sub / "dataset.json").write_text(json.dumps({"format": "prismonet-folder", "version": 1, "camera": cam_d, "ground_z": ground_z}))
    return out / "rectified", out / "direct"
