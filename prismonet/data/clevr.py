"""CLEVR-style scenes as in the paper's modified Clevr: sampling of the scene layout.

Spheres, cylinders and cubes from the 27-shape Clevr set, in the eight CLEVR colours, rest on a
flat-coloured ground plane at random yaw. Centres lie in ``[-area_half, area_half]^2`` and no two
objects intersect (their bounding discs, or balls, keep ``min_gap`` apart). Another object may hide
one completely. Rendering is in ``prismonet.data.raycast_gt``; this module only samples.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

import numpy as np
import torch

from prismonet.data.errors import PlacementError
from prismonet.geometry.camera import Camera, intrinsics_matrix, look_at
from prismonet.geometry.pose import random_rotation_axis_angle, rotation_from_axis_cos_sin
from prismonet.shapes.clevr_set import clevr_shapes
from prismonet.shapes.library import CLEVR, shape_library

GENERATOR_VERSION = "clevr-1"

COLOR_NAMES: tuple[str, ...] = ("gray", "red", "blue", "green", "brown", "purple", "cyan", "yellow", "white", "silver", "black")
COLOR_RGB: tuple[tuple[int, int, int], ...] = (
    (87, 87, 87),
    (173, 35, 35),
    (42, 75, 215),
    (29, 105, 20),
    (129, 74, 25),
    (129, 38, 192),
    (41, 208, 208),
    (255, 238, 51),
    (240, 240, 240),
    (185, 185, 190),
    (25, 25, 25),
)
"""CLEVR's eight colours (ids 0-7, the paper's), then three that real tables hold and CLEVR lacks (ids 8-10: white,
silver, black; only with ``ClevrConfig.colors``)."""
CLEVR_COLORS: tuple[int, ...] = tuple(range(8))
"""The colour ids CLEVR draws from (the default palette)."""

CLEVR_CAMERA_EYE = (7.4811, -6.5076, 5.3437)
"""CLEVR's camera position (from its base scene), looking at the world origin."""

DISC_PACKING_DENSITY = math.pi / (2.0 * math.sqrt(3.0))
"""Densest packing of equal discs in the plane (hexagonal, ~0.9069): the upfront feasibility bound."""

MAX_SCENE_ATTEMPTS = 200
MAX_OBJECT_TRIES = 100


@dataclass(frozen=True)
class TowerConfig:
    """Block towers instead of scattered objects (``prismonet.data.towers``): Lerer et al.'s style."""

    max_towers: int = 1
    """Towers per scene: uniform in ``1 .. max_towers`` (and at most the scene's cube count)."""
    offset: float = 0.4
    """Largest shift of a cube's centre over the one below, per axis, in the cube's half-extents."""
    yaw_jitter_deg: float = 10.0
    """Largest turn of a cube against the one below."""
    margin: float = 0.1
    """Stability margin: the centre of mass stays this many half-extents inside the contact face."""
    colors: tuple[int, ...] = (1, 2, 3, 7)
    """CLEVR colour ids the cubes take (default: red, blue, green, yellow: saturated, as Lerer's)."""
    shape_id: int = 18
    """The Clevr shape of every block (18: the cube with equal sides)."""
    platform_share: float = 0.0
    """Stacked blocks of a block set only (``prismonet.data.stacks``): the share of scenes (of two blocks or more) built
    around a platform, a wide flat block at ``platform_scale`` carrying one or two short stacks, as the slab of a
    real block photo carries a board, a bar and a cube."""
    platform_scale: tuple[float, float] = (0.9, 1.2)
    """A platform's scale, uniform in this range (the other blocks keep ``ClevrConfig.scale_range``)."""

    def __post_init__(self) -> None:
        object.__setattr__(self, "colors", tuple(int(c) for c in self.colors))
        object.__setattr__(self, "platform_scale", tuple(float(x) for x in self.platform_scale))
        lo, hi = self.platform_scale
        if not (0.0 <= self.platform_share <= 1.0 and 0.0 < lo <= hi):
            raise ValueError(f"towers: platform_share must be in [0, 1] and platform_scale 0 < LO <= HI, "
                             f"got {self.platform_share}, {self.platform_scale}")
        if self.max_towers < 1:
            raise ValueError(f"towers.max_towers must be >= 1, got {self.max_towers}")
        if not (0 <= self.offset < 1 and 0 <= self.margin < 1 and self.yaw_jitter_deg >= 0):
            raise ValueError(f"towers: offset and margin must be in [0, 1) and yaw_jitter_deg >= 0, "
                             f"got {self.offset}, {self.margin}, {self.yaw_jitter_deg}")
        if not self.colors or any(not 0 <= c < len(COLOR_RGB) for c in self.colors):
            raise ValueError(f"towers.colors: expected CLEVR colour ids in 0..{len(COLOR_RGB) - 1}, got {self.colors}")
        shapes = clevr_shapes()
        if not 0 <= self.shape_id < len(shapes) or shapes[self.shape_id].category != "cube":
            raise ValueError(f"towers.shape_id: expected the id of a Clevr cube, got {self.shape_id}")


@dataclass(frozen=True)
class RandomizeConfig:
    """Per-scene draws of what real photos change (the many-objects issue, item 3): ground colour, light
    and camera. Every range is sampled uniformly; the layout is sampled as without it, in the world."""

    ground_gray: tuple[float, float] = (70.0, 210.0)
    """Grey level of the ground (0-255)."""
    ground_tint: float = 25.0
    """Warm (red up, blue down) or cool tint of the ground, uniform in +-this."""
    light_azimuth_deg: tuple[float, float] = (-180.0, 180.0)
    light_elevation_deg: tuple[float, float] = (25.0, 85.0)
    ambient: tuple[float, float] = (0.2, 0.6)
    """Ambient share of the light; the sun's is ``brightness - ambient``."""
    brightness: tuple[float, float] = (0.8, 1.2)
    """Ambient + diffuse: the light on a surface facing the sun."""
    camera_distance: tuple[float, float] = (0.75, 1.0)
    """Distance from the look-at point, times ``camera_eye``'s (11.3): farther, the objects would pass the
    depth clip at 12."""
    camera_elevation_deg: tuple[float, float] = (18.0, 50.0)
    camera_azimuth_deg: tuple[float, float] = (-45.0, 45.0)
    """Turn about the world z axis, from ``camera_eye``'s heading."""
    look_at_jitter: float = 0.3
    """The camera looks at a point uniform in +-this per ground axis."""
    focal_scale: tuple[float, float] = (0.8, 1.0)
    """Times the focal length that fits the placement area (< 1 shows more than the area)."""

    def __post_init__(self) -> None:
        for name in ("ground_gray", "light_azimuth_deg", "light_elevation_deg", "ambient", "brightness", "camera_distance",
                     "camera_elevation_deg", "camera_azimuth_deg", "focal_scale"):
            lo, hi = getattr(self, name)
            object.__setattr__(self, name, (float(lo), float(hi)))
            if not lo <= hi:
                raise ValueError(f"randomize.{name}: expected (low, high) with low <= high, got {(lo, hi)}")
        if not (0 < self.camera_elevation_deg[0] and self.camera_elevation_deg[1] < 90 and self.camera_distance[0] > 0
                and self.focal_scale[0] > 0 and self.ambient[0] >= 0 and self.brightness[0] > self.ambient[1] - 1e-9):
            raise ValueError(f"randomize: elevations in (0, 90) deg, positive distances and focal scales, and brightness "
                             f">= ambient are required, got {self}")


@dataclass(frozen=True)
class ClevrConfig:
    """Settings of the CLEVR-style generator. Defaults follow the paper's modified Clevr."""

    num_objects: int = 3
    """Objects per scene (the paper's datasets use 2 to 5); with ``min_objects``, the most per scene."""
    min_objects: int | None = None
    """Scenes with a varying count: each draws its count uniformly from ``min_objects .. num_objects``
    (None: always ``num_objects``, and the random stream is the fixed-count generator's)."""
    image_size: int = 64
    """Square image side in pixels."""
    area_half: float = 1.5
    """Object centres lie in ``[-area_half, area_half]^2`` on the ground."""
    scale_range: tuple[float, float] = (0.35, 0.7)
    """World half-extent of an object's longest axis; CLEVR's small and large sizes are 0.35 and 0.7."""
    min_gap: float = 0.05
    """Minimum distance between the bounding discs (or balls) of two objects."""
    ground_color: tuple[int, int, int] = (150, 150, 150)
    """Flat RGB colour of the ground plane (not shaded)."""
    light_dir: tuple[float, float, float] = (0.35, -0.55, 1.0)
    """Direction towards the directional light, world frame (normalised when used)."""
    ambient: float = 0.4
    """Lambertian shading: colour * (ambient + diffuse * max(0, n . l))."""
    diffuse: float = 0.6
    far_depth: float = 12.0
    """Depth is clipped at this camera z (the paper clips at 12); misses get it too."""
    depth_noise_eta: float = 0.0
    """Noisy-depth variant: Gaussian noise with sigma = eta * d^2 (the paper: eta = 0.001)."""
    random_height: bool = False
    """Variant: object centres at a random height in ``height_range``, over a lowered ground."""
    height_range: tuple[float, float] = (-1.5, 1.5)
    full_rotation: bool = False
    """Variant: uniformly random 3-D rotation instead of yaw only."""
    camera_jitter: float = 0.0
    """Per-axis uniform jitter of the camera position, U(-j, j) (CLEVR uses 0.5)."""
    camera_eye: tuple[float, float, float] = CLEVR_CAMERA_EYE
    cast_shadows: bool = False
    """Beyond the paper (real photos have them): objects cast soft shadows from the directional light, on the ground
    and on each other (``prismonet.data.raycast_gt``). The scenes drawn are the same with or without."""
    towers: TowerConfig | None = None
    """Block towers instead of scattered objects (``prismonet.data.towers``); see ``BLOCK_TOWERS``."""
    randomize: RandomizeConfig | None = None
    """Per-scene ground colour, light and camera (``RandomizeConfig``); None: fixed, as the paper."""
    colors: tuple[int, ...] = CLEVR_COLORS
    """Colour ids (into ``COLOR_RGB``) the objects draw from, uniformly; the default, CLEVR's eight, gives the scenes it
    always gave. Ids 8-10 (white, silver, black) are for models meant for real tables, where such objects occur."""
    shapes: str = CLEVR
    """Shape library (``prismonet.shapes.library``): ``"clevr"``, or a folder of imported meshes, whose
    objects keep their own colours."""
    shape_split: str = "seen"
    """Which models of an imported library: ``seen`` (the prior's), or ``unseen`` (novel shapes)."""

    def __post_init__(self) -> None:
        if isinstance(self.towers, dict):  # read back from a dataset's meta
            object.__setattr__(self, "towers", TowerConfig(**self.towers))
        if isinstance(self.randomize, dict):
            object.__setattr__(self, "randomize", RandomizeConfig(**self.randomize))
        if self.num_objects <= 0:
            raise ValueError(f"num_objects must be positive, got {self.num_objects}")
        if self.min_objects is not None and not 0 <= self.min_objects <= self.num_objects:
            raise ValueError(f"min_objects must be in 0..num_objects ({self.num_objects}), got {self.min_objects}")
        if self.image_size <= 0:
            raise ValueError(f"image_size must be positive, got {self.image_size}")
        lo, hi = self.scale_range
        if not 0 < lo <= hi:
            raise ValueError(f"scale_range must satisfy 0 < min <= max, got {self.scale_range}")
        if self.area_half <= 0:
            raise ValueError(f"area_half must be positive, got {self.area_half}")
        if not (math.isfinite(self.camera_jitter) and self.camera_jitter >= 0):
            raise ValueError(f"camera_jitter must be a finite number >= 0, got {self.camera_jitter}")
        object.__setattr__(self, "colors", tuple(self.colors))  # a list when read back from a dataset's meta
        if not self.colors or any(not 0 <= c < len(COLOR_RGB) for c in self.colors):
            raise ValueError(f"colors: expected colour ids in 0..{len(COLOR_RGB) - 1} ({', '.join(COLOR_NAMES)}), got {self.colors}")

    @property
    def ground_z(self) -> float:
        """Height of the ground plane: 0, or below the lowest possible object when heights vary."""
        if not self.random_height:
            return 0.0
        max_radius = self.scale_range[1] * max(s.bounding_radius() for s in shape_library(self.shapes, self.shape_split).specs)
        return float(self.height_range[0] - max_radius)

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class ObjectSpec:
    """Ground truth of one object. ``R`` rotates by ``yaw`` about ``axis`` (world z unless 6-DoF)."""

    shape_id: int
    category_id: int
    color_id: int
    scale: float
    position: tuple[float, float, float]
    yaw: float
    axis: tuple[float, float, float] = (0.0, 0.0, 1.0)
    shapes: str = CLEVR
    """The shape library ``shape_id`` indexes (with ``shape_split``; see ``prismonet.shapes.library``)."""
    shape_split: str = "seen"

    def rotation(self) -> np.ndarray:
        cs = torch.tensor([math.cos(self.yaw), math.sin(self.yaw)], dtype=torch.float64)
        return rotation_from_axis_cos_sin(cs, torch.tensor(self.axis, dtype=torch.float64)).numpy()

    def world_mesh(self) -> tuple[np.ndarray, np.ndarray]:
        """The object's mesh in the world frame: ``x_world = s R x_obj + p``."""
        v, f = shape_library(self.shapes, self.shape_split).mesh(self.shape_id)
        return (self.scale * v) @ self.rotation().T + np.asarray(self.position), f


@dataclass(frozen=True)
class SceneSpec:
    objects: tuple[ObjectSpec, ...]
    camera: Camera
    ground_z: float
    ground_color: tuple[int, int, int]
    seed: tuple[int, ...] = field(default=())
    light: tuple[tuple[float, float, float], float, float] | None = None
    """``(direction towards the light, ambient, diffuse)`` of this scene; None: the config's."""


BLOCK_TOWERS = ClevrConfig(num_objects=4, min_objects=2, area_half=0.3, scale_range=(0.4, 0.5),
                           camera_eye=(0.0, -10.0, 3.0), towers=TowerConfig())
"""The block-tower setting: one tower of 2 to 4 equal cubes, seen from the front and a little above."""


def clevr_camera(cfg: ClevrConfig, eye: tuple[float, float, float] | None = None,
                 target: tuple[float, float, float] = (0.0, 0.0, 0.0), focal_scale: float = 1.0) -> Camera:
    """CLEVR's camera pose, with the focal length that makes the placement area fill the image.

    The focal length is the largest for which all four corners of the area's square on the
    ground project inside the image, with the principal point at the image centre; ``focal_scale``
    multiplies it. ``eye`` and ``target``: another pose (randomised cameras).
    """
    eye_t = torch.tensor(cfg.camera_eye if eye is None else eye, dtype=torch.float64)
    T_world_cam = look_at(eye_t, torch.tensor(target, dtype=torch.float64))
    T_cam_world = torch.linalg.inv(T_world_cam)
    a = cfg.area_half
    corners = torch.tensor([[a, a, 0.0], [a, -a, 0.0], [-a, a, 0.0], [-a, -a, 0.0]], dtype=torch.float64)
    x_cam = corners @ T_cam_world[:3, :3].T + T_cam_world[:3, 3]
    half = cfg.image_size / 2.0
    ratios = (x_cam[:, :2] / x_cam[:, 2:]).abs().max()
    f = float(half / ratios) * focal_scale
    c = (cfg.image_size - 1) / 2.0
    K = intrinsics_matrix(f, f, c, c, dtype=torch.float64)
    return Camera(K.float(), T_world_cam.float(), cfg.image_size, cfg.image_size)


def sample_conditions(rng: np.random.Generator, cfg: ClevrConfig) -> tuple[Camera, tuple[int, int, int], tuple]:
    """One scene's randomised camera, ground colour and light (``cfg.randomize``)."""
    r = cfg.randomize
    eye0 = np.asarray(cfg.camera_eye, np.float64)
    dist0 = float(np.linalg.norm(eye0))
    heading0 = math.atan2(eye0[1], eye0[0])
    dist = dist0 * rng.uniform(*r.camera_distance)
    elev = math.radians(rng.uniform(*r.camera_elevation_deg))
    az = heading0 + math.radians(rng.uniform(*r.camera_azimuth_deg))
    target = np.array([*rng.uniform(-r.look_at_jitter, r.look_at_jitter, 2), 0.0])
    eye = target + dist * np.array([math.cos(elev) * math.cos(az), math.cos(elev) * math.sin(az), math.sin(elev)])
    camera = clevr_camera(cfg, tuple(eye.tolist()), tuple(target.tolist()), float(rng.uniform(*r.focal_scale)))
    g, t = rng.uniform(*r.ground_gray), rng.uniform(-r.ground_tint, r.ground_tint)
    ground = tuple(int(np.clip(round(x), 0, 255)) for x in (g + t, g, g - t))
    la, le = math.radians(rng.uniform(*r.light_azimuth_deg)), math.radians(rng.uniform(*r.light_elevation_deg))
    direction = (math.cos(le) * math.cos(la), math.cos(le) * math.sin(la), math.sin(le))
    ambient = float(rng.uniform(*r.ambient))
    diffuse = float(rng.uniform(*r.brightness)) - ambient
    return camera, ground, (direction, ambient, max(diffuse, 0.0))  # type: ignore[return-value]


def check_placement_feasible(cfg: ClevrConfig) -> None:
    """Raise ``PlacementError`` when even the smallest objects cannot fit in the area.

    Bound: discs of the smallest footprint radius ``r`` (plus half the gap) with centres in the
    square cover at most ``DISC_PACKING_DENSITY`` of the square grown by ``r``.
    """
    r = cfg.scale_range[0] * min(s.footprint_radius() for s in shape_library(cfg.shapes, cfg.shape_split).specs) + cfg.min_gap / 2
    side = 2 * cfg.area_half + 2 * r
    capacity = DISC_PACKING_DENSITY * side * side / (math.pi * r * r)
    if cfg.num_objects > capacity and not cfg.random_height and cfg.towers is None:
        raise PlacementError(
            f"impossible placement: {cfg.num_objects} objects of radius >= {r:.2f} cannot fit "
            f"without intersecting in [-{cfg.area_half}, {cfg.area_half}]^2 (at most ~{int(capacity)})"
        )


def sample_scene(rng: np.random.Generator, cfg: ClevrConfig, camera: Camera | None = None) -> SceneSpec:
    """Sample one scene layout. All randomness comes from ``rng``."""
    check_placement_feasible(cfg)
    lib = shape_library(cfg.shapes, cfg.shape_split)
    shapes = lib.specs
    light = ground = None
    if cfg.randomize is not None:
        camera, ground, light = sample_conditions(rng, cfg)
    elif camera is None or cfg.camera_jitter > 0:
        eye = np.asarray(cfg.camera_eye) + rng.uniform(-cfg.camera_jitter, cfg.camera_jitter, 3) * (cfg.camera_jitter > 0)
        camera = clevr_camera(cfg, tuple(eye.tolist()))
    three_d = cfg.random_height  # objects may then stack above each other: test balls, not discs
    count = cfg.num_objects if cfg.min_objects is None else int(rng.integers(cfg.min_objects, cfg.num_objects + 1))
    for _ in range(MAX_SCENE_ATTEMPTS):
        objects: list[ObjectSpec] = []
        centres: list[np.ndarray] = []
        radii: list[float] = []
        for _k in range(count):
            for _t in range(MAX_OBJECT_TRIES):
                spec = shapes[int(rng.integers(len(shapes)))]
                scale = float(rng.uniform(*cfg.scale_range))
                xy = rng.uniform(-cfg.area_half, cfg.area_half, 2)
                if cfg.full_rotation:
                    axis, yaw = random_rotation_axis_angle(rng)
                else:
                    axis, yaw = [0.0, 0.0, 1.0], float(rng.uniform(-math.pi, math.pi))
                if cfg.random_height:
                    z = float(rng.uniform(*cfg.height_range))
                elif cfg.full_rotation:
                    probe = ObjectSpec(spec.shape_id, spec.category_id, 0, scale, (0.0, 0.0, 0.0), yaw, tuple(axis), cfg.shapes, cfg.shape_split)
                    z = float(-probe.world_mesh()[0][:, 2].min())
                else:
                    z = scale * spec.half_extents[2]
                use_ball = three_d or cfg.full_rotation
                radius = scale * (spec.bounding_radius() if use_ball else spec.footprint_radius())
                centre = np.array([xy[0], xy[1], z]) if three_d else np.array([xy[0], xy[1], 0.0])
                if all(np.linalg.norm(centre - c) >= radius + r + cfg.min_gap for c, r in zip(centres, radii)):
                    color_id = -1 if lib.own_colors else cfg.colors[int(rng.integers(len(cfg.colors)))]
                    objects.append(ObjectSpec(spec.shape_id, spec.category_id, color_id, scale, (float(xy[0]), float(xy[1]), z), yaw,
                                              tuple(axis), cfg.shapes, cfg.shape_split))
                    centres.append(centre)
                    radii.append(radius)
                    break
            else:
                break  # this object did not fit: start the scene again
        if len(objects) == count:
            return SceneSpec(tuple(objects), camera, cfg.ground_z, cfg.ground_color if ground is None else ground, light=light)
    raise PlacementError(
        f"impossible placement: could not place {cfg.num_objects} non-intersecting objects in "
        f"[-{cfg.area_half}, {cfg.area_half}]^2 after {MAX_SCENE_ATTEMPTS} attempts"
    )
