"""Ground-truth rendering of Clevr scenes with open3d's ``RaycastingScene``.

This is deliberately independent of the project's differentiable SDF renderer, so that a bug in
that renderer cannot cancel out when its output is evaluated against this ground truth.
Outputs: RGB (Lambertian, flat ground; cast shadows with ``ClevrConfig.cast_shadows``), depth as camera z
clipped at ``far_depth``, and an instance-id mask (0 = ground, k = k-th object of the scene, 1-based).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from prismonet.data.clevr import COLOR_RGB, ClevrConfig, SceneSpec
from prismonet.geometry.camera import camera_rays


@dataclass
class RenderedScene:
    """One rendered scene. ``rgb``: (H, W, 3) uint8; ``depth``: (H, W) float32; ``instance``: (H, W) uint8."""

    rgb: np.ndarray
    depth: np.ndarray
    instance: np.ndarray


def world_rays(spec: SceneSpec) -> tuple[np.ndarray, np.ndarray]:
    """Ray origins and directions ``(H*W, 3)`` in the world; the camera-z of ``o + t d`` is ``t``."""
    cam = spec.camera
    d_cam = camera_rays(cam.K.double(), cam.height, cam.width).reshape(-1, 3).numpy()
    T = cam.T_world_cam.double().numpy()
    d = d_cam @ T[:3, :3].T
    o = np.broadcast_to(T[:3, 3], d.shape)
    return o, d


SHADOW_RAYS = 8
"""Shadow rays per pixel: the light's direction and seven more on a cone around it (a soft edge)."""
SHADOW_SPREAD_DEG = 4.0
"""Half-angle of that cone: the light's apparent radius."""


def shadow_directions(light: np.ndarray, rays: int = SHADOW_RAYS, spread_deg: float = SHADOW_SPREAD_DEG) -> np.ndarray:
    """``(rays, 3)`` unit directions: ``light`` (unit) itself and ``rays - 1`` more at ``spread_deg`` from it, evenly
    around it (a fixed pattern: the same scene always casts the same shadow)."""
    helper = np.array([1.0, 0.0, 0.0]) if abs(light[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = np.cross(light, helper)
    u /= np.linalg.norm(u)
    v = np.cross(light, u)
    a = np.radians(spread_deg)
    phi = 2 * np.pi * np.arange(rays - 1) / max(rays - 1, 1)
    ring = np.cos(a) * light + np.sin(a) * (np.cos(phi)[:, None] * u + np.sin(phi)[:, None] * v)
    return np.concatenate([light[None], ring], 0)


def shadow_fraction(scene, points: np.ndarray, normals: np.ndarray, light: np.ndarray, nthreads: int = 0) -> np.ndarray:
    """``(n,)`` share of the shadow rays from surface ``points (n, 3)`` (unit ``normals (n, 3)``) towards ``light``
    that an object of open3d ``scene`` blocks: 0 lit, 1 in full shadow."""
    import open3d as o3d

    dirs = shadow_directions(light)
    start = points + 1e-3 * normals  # off the surface, so that a ray does not hit where it starts
    rays = np.concatenate([np.repeat(start[None], len(dirs), 0), np.repeat(dirs[:, None], len(points), 1)], -1)
    blocked = scene.test_occlusions(o3d.core.Tensor(rays.reshape(-1, 6).astype(np.float32)), nthreads=nthreads).numpy()
    return blocked.reshape(len(dirs), len(points)).mean(0)


def _surface_colors(spec: SceneSpec, geom: np.ndarray, prim: np.ndarray) -> np.ndarray:
    """``(n, 3)`` albedo of hits on objects ``geom`` at triangles ``prim``: the object's CLEVR colour, or
    for shapes with their own colours (imported meshes) the colour of the triangle hit."""
    from prismonet.shapes.library import shape_library

    out = np.zeros((len(geom), 3))
    for k, obj in enumerate(spec.objects):
        sel = geom == k
        if not sel.any():
            continue
        if obj.color_id >= 0:
            out[sel] = COLOR_RGB[obj.color_id]
        else:
            out[sel] = shape_library(obj.shapes, obj.shape_split).face_colors(obj.shape_id)[prim[sel]]
    return out


def render_scene(
    spec: SceneSpec,
    cfg: ClevrConfig,
    rng: np.random.Generator | None = None,
    nthreads: int = 0,
    rays: tuple[np.ndarray, np.ndarray] | None = None,
) -> RenderedScene:
    """Raycast a scene layout.

    ``rng`` is needed only for the noisy-depth variant; ``rays`` (from ``world_rays``) may be
    passed to reuse them across scenes that share a camera.
    """
    import open3d as o3d

    H, W = spec.camera.height, spec.camera.width
    o, d = world_rays(spec) if rays is None else rays

    scene = o3d.t.geometry.RaycastingScene()
    for obj in spec.objects:
        v, f = obj.world_mesh()
        scene.add_triangles(o3d.core.Tensor(v.astype(np.float32)), o3d.core.Tensor(f.astype(np.uint32)))
    rays = o3d.core.Tensor(np.concatenate([o, d], axis=1).astype(np.float32))
    hit = scene.cast_rays(rays, nthreads=nthreads)
    t_obj = hit["t_hit"].numpy().astype(np.float64)
    geom = hit["geometry_ids"].numpy().astype(np.int64)
    normals = hit["primitive_normals"].numpy().astype(np.float64)
    obj_hit = np.isfinite(t_obj)

    # Ground plane z = ground_z, hit where the ray points down towards it.
    with np.errstate(divide="ignore", invalid="ignore"):
        t_ground = (spec.ground_z - o[:, 2]) / d[:, 2]
    t_ground = np.where((d[:, 2] < 0) & (t_ground > 0), t_ground, np.inf)

    fg = obj_hit & (t_obj < t_ground)
    depth = np.where(fg, t_obj, t_ground)
    depth = np.minimum(depth, cfg.far_depth)

    # (in float32, open3d's id for "no hit" is 2^32 - 1; only read ids where fg)
    instance = np.where(fg, geom + 1, 0).astype(np.uint8)

    direction, ambient, diffuse = (cfg.light_dir, cfg.ambient, cfg.diffuse) if spec.light is None else spec.light
    light = np.asarray(direction, dtype=np.float64)
    light = light / np.linalg.norm(light)
    direct = diffuse * np.clip(normals @ light, 0.0, None)
    shade = ambient + direct
    rgb = np.broadcast_to(np.asarray(spec.ground_color, dtype=np.float64), (H * W, 3)).copy()
    if cfg.cast_shadows and len(spec.objects):
        # A blocked light takes its direct share away: on an object the diffuse term; on the (unshaded) ground the
        # share that term would have if the ground were lit the same way, diffuse cos / (ambient + diffuse cos).
        ground = ~fg & np.isfinite(t_ground)
        surf = fg | ground
        up = np.broadcast_to(np.array([0.0, 0.0, 1.0]), normals.shape)
        n_surf = np.where(fg[:, None], normals, up)
        t_surf = np.where(fg, t_obj, t_ground)
        facing = surf & ((n_surf @ light) > 0)
        frac = np.zeros(H * W)
        idx = np.nonzero(facing)[0]
        if len(idx):
            frac[idx] = shadow_fraction(scene, o[idx] + t_surf[idx, None] * d[idx], n_surf[idx], light, nthreads)
        shade = shade - np.where(fg, direct * frac, 0.0)
        cos_g = max(float(light[2]), 0.0)
        share = diffuse * cos_g / max(ambient + diffuse * cos_g, 1e-9)
        rgb[ground] *= (1.0 - share * frac[ground])[:, None]
    if fg.any():
        prim = hit["primitive_ids"].numpy().astype(np.int64)
        rgb[fg] = _surface_colors(spec, geom[fg], prim[fg]) * shade[fg, None]
    rgb = np.clip(np.rint(rgb), 0, 255).astype(np.uint8)

    if cfg.depth_noise_eta > 0:
        if rng is None:
            raise ValueError("render_scene: the noisy-depth variant needs an rng")
        depth = depth + rng.normal(size=depth.shape) * cfg.depth_noise_eta * depth**2
        depth = np.clip(depth, 0.0, cfg.far_depth)

    return RenderedScene(rgb.reshape(H, W, 3), depth.reshape(H, W).astype(np.float32), instance.reshape(H, W))
