"""SDF samples from meshes: points in the padded cube and near the surface, with signed distances.

Distances are exact (open3d's closest-point query). Signs come from open3d's ray-parity test for
watertight meshes. For the others (imported furniture) a visibility vote decides: a point is inside
when fewer than ``ESCAPE_INSIDE`` of ``VISIBILITY_RAYS`` rays from it, spread evenly over the upper
hemisphere, leave the mesh without hitting a face (and below its lowest point, under the ground it stands
on, everything is outside). Upper, because objects stand on the ground and every camera sees them from above: a car without a floor panel is solid from there, while a cup's opening
leaks enough rays that its inside is empty, as the renders show it; gaps between parts leak too few to
matter. The vote needs no face orientation, which imported models rarely have consistent (a car's roof
facing inwards makes the generalized winding number negative there, and the prior learnt hollow shells).
The generalized winding number (Jacobson et al. 2013, ``inside="winding"``) stays for consistently
oriented meshes with holes.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from prismonet.shapes.normalize import BOX_HALF, normalize_mesh

WINDING_CHUNK = 256
"""Query points per block in the winding-number sum (bounds the (Q, F) temporaries, which stay in cache)."""
PARITY_RAYS = 3
"""Rays per point in open3d's parity test; odd, so that a ray through an edge is outvoted."""
VISIBILITY_RAYS = 64
"""Rays per point in the visibility vote: the upper half of a 128-point Fibonacci sphere (aligned with no axis)."""
ESCAPE_INSIDE = 0.1
"""A point is inside when fewer than this share of its upward rays escape. In a cube without its top,
1/3 of them escape from the middle and 14 % from a twentieth of the way above the bottom: it is empty."""
INSIDE_TESTS = ("visibility", "winding")


@dataclass(frozen=True)
class SamplingConfig:
    """How SDF training samples are drawn for one shape."""

    num_points: int = 16384
    """Samples per shape (DeepSDF: 16384 per shape per step)."""
    uniform_ratio: float = 0.3
    """Share of points uniform in the padded cube. DeepSDF uses 3/50; the paper uses more."""
    surface_sigmas: tuple[float, float] = (0.0707, 0.0224)
    """Std of the Gaussian offsets of near-surface points (DeepSDF's variances 0.005, 0.0005)."""
    inside: str = "visibility"
    """Inside test for meshes that are not watertight: ``visibility`` (a vote of escaping rays) or
    ``winding`` (the generalized winding number, which needs consistently oriented faces)."""

    def __post_init__(self) -> None:
        if self.inside not in INSIDE_TESTS:
            raise ValueError(f"sampling.inside: expected one of {INSIDE_TESTS}, got {self.inside!r}")

    def key(self) -> str:
        return f"n{self.num_points}-u{self.uniform_ratio}-s{self.surface_sigmas[0]}-{self.surface_sigmas[1]}-{self.inside}"


def winding_number(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Generalized winding number of a triangle mesh at ``points`` ``(Q, 3)``: ~1 inside, ~0 outside.

    Sum over faces of the signed solid angle (Van Oosterom & Strackee) divided by 4 pi. With
    ``a = A - p`` (and ``b``, ``c`` for the triangle's other corners), every term is a matrix product
    of the points with per-face constants: ``det(a, b, c) = det(A, B, C) - p . (B x C + C x A + A x B)``,
    ``a . b = A . B - p . (A + B) + |p|^2`` and ``|a|^2 = |A|^2 - 2 A . p + |p|^2``, so a block of points
    costs a few ``(Q, 3) @ (3, F)`` products and element-wise work, in float64.
    """
    tri = torch.from_numpy(np.asarray(vertices, dtype=np.float64)[np.asarray(faces)])  # (F, 3, 3)
    A, B, C = tri[:, 0], tri[:, 1], tri[:, 2]
    n = torch.linalg.cross(B, C) + torch.linalg.cross(C, A) + torch.linalg.cross(A, B)  # (F, 3)
    d0 = (A * torch.linalg.cross(B, C)).sum(-1)
    corners = torch.stack([A, B, C, n, A + B, B + C, C + A], 1).reshape(-1, 3).T.contiguous()  # (3, 7F)
    sq = torch.stack([(A * A).sum(-1), (B * B).sum(-1), (C * C).sum(-1), (A * B).sum(-1), (B * C).sum(-1), (C * A).sum(-1)])
    out = np.empty(len(points))
    for s in range(0, len(points), WINDING_CHUNK):
        p = torch.from_numpy(np.asarray(points[s : s + WINDING_CHUNK], dtype=np.float64))
        pp = (p * p).sum(-1, keepdim=True)  # (Q, 1)
        dots = (p @ corners).reshape(len(p), -1, 7)  # (Q, F, 7): p.A, p.B, p.C, p.n, p.(A+B), p.(B+C), p.(C+A)
        la = (sq[0] - 2 * dots[..., 0] + pp).clamp_min(0).sqrt()
        lb = (sq[1] - 2 * dots[..., 1] + pp).clamp_min(0).sqrt()
        lc = (sq[2] - 2 * dots[..., 2] + pp).clamp_min(0).sqrt()
        det = d0 - dots[..., 3]
        den = la * lb * lc + (sq[3] - dots[..., 4] + pp) * lc + (sq[4] - dots[..., 5] + pp) * la + (sq[5] - dots[..., 6] + pp) * lb
        out[s : s + len(p)] = (2.0 * torch.atan2(det, den)).sum(-1).numpy() / (4.0 * np.pi)
    return out


def winding_number_direct(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray, chunk: int = 2048) -> np.ndarray:
    """``winding_number`` computed term by term from ``a = A - p``, ``b``, ``c`` (the formula as written,
    3-4x slower): the reference the fast form is tested and benchmarked against."""
    tri = torch.from_numpy(np.asarray(vertices, dtype=np.float64)[np.asarray(faces)])  # (F, 3, 3)
    out = np.empty(len(points))
    for s in range(0, len(points), chunk):
        p = torch.from_numpy(np.asarray(points[s : s + chunk], dtype=np.float64))
        a, b, c = (tri[None, :, i, :] - p[:, None, :] for i in range(3))  # (Q, F, 3)
        la, lb, lc = a.norm(dim=-1), b.norm(dim=-1), c.norm(dim=-1)
        det = (a * torch.linalg.cross(b, c, dim=-1)).sum(-1)
        den = la * lb * lc + (a * b).sum(-1) * lc + (b * c).sum(-1) * la + (c * a).sum(-1) * lb
        out[s : s + len(p)] = (2.0 * torch.atan2(det, den)).sum(-1).numpy() / (4.0 * np.pi)
    return out


def is_watertight(vertices: np.ndarray, faces: np.ndarray) -> bool:
    import trimesh

    return bool(trimesh.Trimesh(vertices, faces, process=True).is_watertight)


def fibonacci_sphere(n: int) -> np.ndarray:
    """``(n, 3)`` unit vectors spread evenly over the sphere (the golden-angle spiral)."""
    i = np.arange(n) + 0.5
    polar = np.arccos(1.0 - 2.0 * i / n)
    azimuth = np.pi * (1.0 + 5.0**0.5) * i
    return np.stack([np.cos(azimuth) * np.sin(polar), np.sin(azimuth) * np.sin(polar), np.cos(polar)], 1)


def escape_fraction(scene, points: np.ndarray, rays: int = VISIBILITY_RAYS, chunk: int = 16384) -> np.ndarray:
    """``(Q,)`` share of ``rays`` upward directions (z > 0) from each point that hit no face of the open3d ``scene``."""
    import open3d as o3d

    d = fibonacci_sphere(2 * rays)
    d = d[d[:, 2] > 0].astype(np.float32)
    rays = len(d)
    out = np.empty(len(points))
    for s in range(0, len(points), chunk):
        p = np.asarray(points[s : s + chunk], np.float32)
        r = np.concatenate([np.repeat(p, rays, 0), np.tile(d, (len(p), 1))], 1)
        t = scene.cast_rays(o3d.core.Tensor(r))["t_hit"].numpy().reshape(len(p), rays)
        out[s : s + len(p)] = np.isinf(t).mean(1)
    return out


def _scene(vertices: np.ndarray, faces: np.ndarray):
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.asarray(vertices, np.float32)), o3d.core.Tensor(np.asarray(faces, np.uint32)))
    return scene


def signed_distance(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray, watertight: bool | None = None,
                    inside: str = "visibility") -> np.ndarray:
    """Signed distance ``(Q,)`` from ``points`` to a mesh; negative inside (``inside_mesh``)."""
    import open3d as o3d

    scene = _scene(vertices, faces)
    q = o3d.core.Tensor(np.asarray(points, np.float32))
    dist = scene.compute_distance(q).numpy().astype(np.float64)
    return np.where(inside_mesh(vertices, faces, points, watertight, scene, inside), -dist, dist)


def inside_mesh(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray, watertight: bool | None = None, scene=None,
                inside: str = "visibility") -> np.ndarray:
    """``(Q,)`` bool: inside the mesh, by open3d's ray parity for a watertight mesh; otherwise by the
    visibility vote (fewer than ``ESCAPE_INSIDE`` of the rays escape) or, with ``inside="winding"``,
    the generalized winding number (> 0.5)."""
    import open3d as o3d

    if inside not in INSIDE_TESTS:
        raise ValueError(f"inside: expected one of {INSIDE_TESTS}, got {inside!r}")
    if watertight is None:
        watertight = is_watertight(vertices, faces)
    if not watertight and inside == "winding":
        return winding_number(vertices, faces, points) > 0.5
    if scene is None:
        scene = _scene(vertices, faces)
    if not watertight:  # below the mesh's lowest point is under the ground it stands on: outside
        return (escape_fraction(scene, points) < ESCAPE_INSIDE) & (np.asarray(points)[:, 2] >= np.asarray(vertices)[:, 2].min())
    return scene.compute_signed_distance(o3d.core.Tensor(np.asarray(points, np.float32)), nsamples=PARITY_RAYS).numpy() < 0


def sample_sdf(
    vertices: np.ndarray, faces: np.ndarray, cfg: SamplingConfig, rng: np.random.Generator, name: str = "mesh"
) -> tuple[np.ndarray, np.ndarray]:
    """Normalise a mesh and draw SDF samples. Returns ``points (N, 3)`` float32 and ``sdf (N,)`` float32."""
    import trimesh

    v, _ = normalize_mesh(vertices, faces, name)
    n_uniform = int(round(cfg.num_points * cfg.uniform_ratio))
    n_surface = cfg.num_points - n_uniform
    mesh = trimesh.Trimesh(v, faces, process=False)
    surf, _ = trimesh.sample.sample_surface(mesh, n_surface, seed=int(rng.integers(2**31)))
    sigma = np.where(np.arange(n_surface) % 2 == 0, cfg.surface_sigmas[0], cfg.surface_sigmas[1])
    near = surf + rng.normal(size=surf.shape) * sigma[:, None]
    near = np.clip(near, -BOX_HALF, BOX_HALF)
    uniform = rng.uniform(-BOX_HALF, BOX_HALF, size=(n_uniform, 3))
    points = np.concatenate([near, uniform])
    sdf = signed_distance(v, faces, points, inside=cfg.inside)
    return points.astype(np.float32), sdf.astype(np.float32)


def cached_sdf_samples(
    vertices: np.ndarray, faces: np.ndarray, cfg: SamplingConfig, seed: int, cache_dir: Path | None, name: str = "mesh"
) -> tuple[np.ndarray, np.ndarray]:
    """``sample_sdf`` with an on-disk cache keyed by the mesh's bytes, the settings and the seed."""
    if cache_dir is None:
        return sample_sdf(vertices, faces, cfg, np.random.default_rng(seed), name)
    h = hashlib.sha256(np.ascontiguousarray(vertices, np.float64).tobytes() + np.ascontiguousarray(faces, np.int64).tobytes())
    path = Path(cache_dir) / f"{h.hexdigest()[:16]}-{cfg.key()}-seed{seed}.npz"
    if path.is_file():
        try:
            with np.load(path, allow_pickle=False) as z:
                return z["points"], z["sdf"]
        except (OSError, ValueError, KeyError):
            path.unlink(missing_ok=True)  # a damaged cache entry is recomputed
    points, sdf = sample_sdf(vertices, faces, cfg, np.random.default_rng(seed), name)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp.npz")
    np.savez(tmp, points=points, sdf=sdf)
    tmp.replace(path)
    return points, sdf
