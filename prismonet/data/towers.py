"""Block towers in the style of Lerer et al. (2016), as the paper trains on for its real block-tower
images: equal cubes in a few saturated colours, stacked into towers that stand, seen by a camera in
front of them and a little above.

A scene holds ``min_objects .. num_objects`` cubes (uniform), dealt into ``1 .. max_towers`` towers
(uniform, each tower at least one cube; the paper's towers have 2 to 4). All cubes of a scene have
one size, drawn from ``scale_range``. Each cube rests on the one below (its centre ``2 s`` higher,
faces in contact) or on the ground, shifted by up to ``offset`` x its half-extent and turned by up to
``yaw_jitter_deg`` against the one below. A tower is kept only when it stands: for every cube, the
centre of mass of it and the cubes above lies inside its contact face with the cube below (the
intersection of both squares, shrunk by ``margin`` x the half-extent), as for rigid blocks of equal
mass. Towers do not touch each other. Rendering, depth and instance masks are Clevr's
(``prismonet.data.raycast_gt``); the ground truth fills the same arrays.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from prismonet.data.clevr import ClevrConfig, ObjectSpec, SceneSpec
from prismonet.data.errors import PlacementError
from prismonet.geometry.camera import Camera, intrinsics_matrix, look_at
from prismonet.shapes.clevr_set import clevr_shapes

MAX_TOWER_TRIES = 200


def tower_camera(cfg: ClevrConfig, eye: tuple[float, float, float] | None = None) -> Camera:
    """A camera at ``cfg.camera_eye`` looking at the middle of the tallest tower's height, with the
    focal length that keeps every cube of every possible tower inside the image."""
    t = cfg.towers
    s = cfg.scale_range[1]
    reach = cfg.area_half + s * math.sqrt(2.0) + (cfg.num_objects - 1) * t.offset * s  # furthest cube corner
    height = 2.0 * s * cfg.num_objects
    eye_t = torch.tensor(cfg.camera_eye if eye is None else eye, dtype=torch.float64)
    T_world_cam = look_at(eye_t, torch.tensor([0.0, 0.0, height / 2.0], dtype=torch.float64))
    T_cam_world = torch.linalg.inv(T_world_cam)
    corners = torch.tensor([[x, y, z] for x in (-reach, reach) for y in (-reach, reach) for z in (0.0, height)], dtype=torch.float64)
    x_cam = corners @ T_cam_world[:3, :3].T + T_cam_world[:3, 3]
    if not bool((x_cam[:, 2] > 0).all()):
        raise PlacementError(f"tower camera at {tuple(eye_t.tolist())} is inside the space the towers may take")
    half = cfg.image_size / 2.0
    f = float(half / (x_cam[:, :2] / x_cam[:, 2:]).abs().max())
    c = (cfg.image_size - 1) / 2.0
    return Camera(intrinsics_matrix(f, f, c, c, dtype=torch.float64).float(), T_world_cam.float(), cfg.image_size, cfg.image_size)


def inside_square(p: np.ndarray, centre: np.ndarray, yaw: float, half: float) -> bool:
    """Whether the point ``p`` (xy) lies in the square of half-side ``half`` at ``centre`` turned by ``yaw``."""
    c, s = math.cos(yaw), math.sin(yaw)
    d = p - centre
    return abs(c * d[0] + s * d[1]) <= half and abs(-s * d[0] + c * d[1]) <= half


def tower_stands(xy: np.ndarray, yaw: np.ndarray, s: float, margin: float) -> bool:
    """Whether a tower of equal cubes (centres ``xy (n, 2)`` bottom to top, yaws ``(n,)``, half-extent
    ``s``) stands: for each cube above the first, the centre of mass of it and every cube above lies in
    its contact face with the cube below, shrunk by ``margin * s``."""
    for i in range(1, len(xy)):
        com = xy[i:].mean(0)
        inner = s * (1.0 - margin)
        if not (inside_square(com, xy[i], yaw[i], inner) and inside_square(com, xy[i - 1], yaw[i - 1], inner)):
            return False
    return True


def deal(rng: np.random.Generator, n: int, towers: int) -> list[int]:
    """``n`` cubes into ``towers`` non-empty towers, uniformly over the ways to cut the row of cubes."""
    cuts = np.sort(rng.choice(np.arange(1, n), size=towers - 1, replace=False)) if towers > 1 else np.array([], int)
    return np.diff(np.concatenate([[0], cuts, [n]])).astype(int).tolist()


def _one_tower(rng: np.random.Generator, cfg: ClevrConfig, height: int, s: float):
    """``(xy (h, 2), yaw (h,))`` of a standing tower of ``height`` cubes with its base in the area."""
    t = cfg.towers
    for _ in range(MAX_TOWER_TRIES):
        xy = np.zeros((height, 2))
        yaw = np.zeros(height)
        xy[0] = rng.uniform(-cfg.area_half, cfg.area_half, 2)
        yaw[0] = rng.uniform(-math.pi / 4, math.pi / 4)
        for i in range(1, height):
            xy[i] = xy[i - 1] + rng.uniform(-t.offset, t.offset, 2) * s
            yaw[i] = yaw[i - 1] + math.radians(rng.uniform(-t.yaw_jitter_deg, t.yaw_jitter_deg))
        if tower_stands(xy, yaw, s, t.margin):
            return xy, yaw
    raise PlacementError(f"could not build a standing tower of {height} cubes in {MAX_TOWER_TRIES} tries "
                         f"(offset {t.offset}, margin {t.margin}: lower the offset)")


def sample_towers(rng: np.random.Generator, cfg: ClevrConfig, camera: Camera | None = None) -> SceneSpec:
    """Sample one block-tower scene (``cfg.towers`` set). All randomness comes from ``rng``."""
    t = cfg.towers
    if t is None:
        raise ValueError("sample_towers: cfg.towers is not set")
    camera = tower_camera(cfg) if camera is None else camera
    spec = clevr_shapes()[t.shape_id]
    lo = cfg.num_objects if cfg.min_objects is None else cfg.min_objects
    n = int(rng.integers(max(lo, 1), cfg.num_objects + 1))
    s = float(rng.uniform(*cfg.scale_range))
    heights = deal(rng, n, int(rng.integers(1, min(t.max_towers, n) + 1)))
    for _ in range(MAX_TOWER_TRIES):
        towers, discs = [], []
        for h in heights:
            xy, yaw = _one_tower(rng, cfg, h, s)
            centre = xy[0]
            radius = float(np.linalg.norm(xy - centre, axis=1).max()) + s * math.sqrt(2.0)
            if any(np.linalg.norm(centre - c) < radius + r + cfg.min_gap for c, r in discs):
                break
            towers.append((xy, yaw))
            discs.append((centre, radius))
        if len(towers) == len(heights):
            break
    else:
        raise PlacementError(f"could not place {len(heights)} towers apart in [-{cfg.area_half}, {cfg.area_half}]^2")
    objects = []
    for xy, yaw in towers:
        for level in range(len(xy)):
            color = int(t.colors[int(rng.integers(len(t.colors)))])
            z = s * spec.half_extents[2] * (2 * level + 1)
            objects.append(ObjectSpec(spec.shape_id, spec.category_id, color, s, (float(xy[level, 0]), float(xy[level, 1]), z),
                                      float(yaw[level])))
    return SceneSpec(tuple(objects), camera, cfg.ground_z, cfg.ground_color)
