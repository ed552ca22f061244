"""Shape quality: Chamfer-L1 between surfaces and volumetric IoU, in the normalised object frame."""

from __future__ import annotations

import numpy as np
import torch

from prismonet.shapes.normalize import BOX_HALF

CHAMFER_POINTS = 30000
"""Surface samples per mesh for Chamfer-L1 (as in DeepSDF / Occupancy Networks evaluations)."""
IOU_RESOLUTION = 64
"""Grid points per axis over the padded box for volumetric IoU."""


def chamfer_l1(a: np.ndarray, b: np.ndarray) -> float:
    """Symmetric Chamfer-L1 between point sets ``(N, 3)`` and ``(M, 3)``:
    ``0.5 * (mean_a min_b |a - b| + mean_b min_a |a - b|)`` with Euclidean distances."""
    from scipy.spatial import cKDTree

    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    if len(a) == 0 or len(b) == 0:
        raise ValueError(f"chamfer_l1: empty point set ({len(a)} and {len(b)} points)")
    d_ab, _ = cKDTree(b).query(a)
    d_ba, _ = cKDTree(a).query(b)
    return 0.5 * (float(d_ab.mean()) + float(d_ba.mean()))


def mesh_chamfer_l1(mesh_a, mesh_b, n: int = CHAMFER_POINTS, seed: int = 0) -> float:
    """Chamfer-L1 between two ``trimesh.Trimesh`` surfaces, from ``n`` area-uniform samples each."""
    import trimesh

    pa, _ = trimesh.sample.sample_surface(mesh_a, n, seed=seed)
    pb, _ = trimesh.sample.sample_surface(mesh_b, n, seed=seed + 1)
    return chamfer_l1(pa, pb)


def grid_points(resolution: int = IOU_RESOLUTION) -> np.ndarray:
    """Cell centres of a ``resolution^3`` grid over the padded box, ``(resolution^3, 3)``."""
    step = 2 * BOX_HALF / resolution
    axis = -BOX_HALF + step * (np.arange(resolution) + 0.5)
    return np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3)


def volumetric_iou(occ_a: np.ndarray, occ_b: np.ndarray) -> float:
    """IoU of two boolean occupancy arrays of the same shape."""
    occ_a, occ_b = np.asarray(occ_a, bool), np.asarray(occ_b, bool)
    if occ_a.shape != occ_b.shape:
        raise ValueError(f"volumetric_iou: shapes differ: {occ_a.shape} vs {occ_b.shape}")
    union = np.logical_or(occ_a, occ_b).sum()
    return 1.0 if union == 0 else float(np.logical_and(occ_a, occ_b).sum() / union)


def mesh_occupancy(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray, inside: str = "visibility") -> np.ndarray:
    """Inside test, the same as the SDF samples' signs (``prismonet.shapes.sdf_samples.inside_mesh``): ray
    parity for a watertight mesh, the visibility vote (or the winding number) for one with holes."""
    from prismonet.shapes.sdf_samples import inside_mesh

    return inside_mesh(vertices, faces, points, inside=inside)


@torch.no_grad()
def decoder_occupancy(decoder, latent: torch.Tensor, points: np.ndarray, chunk: int = 65536) -> np.ndarray:
    z = latent.reshape(1, -1).float()
    pts = torch.from_numpy(np.asarray(points, np.float32))
    return torch.cat([decoder(z, pts[s : s + chunk]) < 0 for s in range(0, len(pts), chunk)]).numpy()
