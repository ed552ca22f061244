"""SDF samples from meshes: points in the padded cube and near the surface, with signed distances.

Distances are exact (open3d's closest-point query). Signs come from open3d's ray-parity test
for watertight meshes and from the generalized winding number (Jacobson et al. 2013) otherwise,
which stays right for meshes with holes: a point is inside where the winding number exceeds 1/2.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from prismonet.shapes.normalize import BOX_HALF, normalize_mesh

WINDING_CHUNK = 2048
"""Query points per block in the winding-number sum (bounds the (Q, F) temporaries)."""
PARITY_RAYS = 3
"""Rays per point in open3d's parity test; odd, so that a ray through an edge is outvoted."""


@dataclass(frozen=True)
class SamplingConfig:
    """How SDF training samples are drawn for one shape."""

    num_points: int = 16384
    """Samples per shape (DeepSDF: 16384 per shape per step)."""
    uniform_ratio: float = 0.3
    """Share of points uniform in the padded cube. DeepSDF uses 3/50; the paper uses more."""
    surface_sigmas: tuple[float, float] = (0.0707, 0.0224)
    """Std of the Gaussian offsets of near-surface points (DeepSDF's variances 0.005, 0.0005)."""

    def key(self) -> str:
        return f"n{self.num_points}-u{self.uniform_ratio}-s{self.surface_sigmas[0]}-{self.surface_sigmas[1]}"


def winding_number(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Generalized winding number of a triangle mesh at ``points`` ``(Q, 3)``: ~1 inside, ~0 outside.

    Sum over faces of the signed solid angle (Van Oosterom & Strackee) divided by 4 pi.
    """
    tri = torch.from_numpy(np.asarray(vertices, dtype=np.float64)[np.asarray(faces)])  # (F, 3, 3)
    out = np.empty(len(points))
    for s in range(0, len(points), WINDING_CHUNK):
        p = torch.from_numpy(np.asarray(points[s : s + WINDING_CHUNK], dtype=np.float64))
        a, b, c = (tri[None, :, i, :] - p[:, None, :] for i in range(3))  # (Q, F, 3)
        la, lb, lc = a.norm(dim=-1), b.norm(dim=-1), c.norm(dim=-1)
        det = (a * torch.linalg.cross(b, c, dim=-1)).sum(-1)
        den = la * lb * lc + (a * b).sum(-1) * lc + (b * c).sum(-1) * la + (c * a).sum(-1) * lb
        out[s : s + len(p)] = (2.0 * torch.atan2(det, den)).sum(-1).numpy() / (4.0 * np.pi)
    return out


def is_watertight(vertices: np.ndarray, faces: np.ndarray) -> bool:
    import trimesh

    return bool(trimesh.Trimesh(vertices, faces, process=True).is_watertight)


def signed_distance(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray, watertight: bool | None = None) -> np.ndarray:
    """Signed distance ``(Q,)`` from ``points`` to a mesh; negative inside."""
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.asarray(vertices, np.float32)), o3d.core.Tensor(np.asarray(faces, np.uint32)))
    q = o3d.core.Tensor(np.asarray(points, np.float32))
    dist = scene.compute_distance(q).numpy().astype(np.float64)
    if watertight is None:
        watertight = is_watertight(vertices, faces)
    if watertight:
        inside = scene.compute_signed_distance(q, nsamples=PARITY_RAYS).numpy() < 0
    else:
        inside = winding_number(vertices, faces, points) > 0.5
    return np.where(inside, -dist, dist)


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
    sdf = signed_distance(v, faces, points)
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
