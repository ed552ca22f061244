"""Meshes from the SDF by marching cubes (scikit-image), in the object or the world frame."""

from __future__ import annotations

import numpy as np
import torch

from prismonet.shapes.normalize import BOX_HALF

GRID_CHUNK = 65536
"""Grid points per decoder call, to bound memory at high resolutions."""


class EmptyMeshError(ValueError):
    """The SDF has no zero crossing in the box: there is no surface to extract."""


@torch.no_grad()
def sdf_grid(decoder, latent: torch.Tensor, resolution: int) -> np.ndarray:
    """Phi on a ``resolution^3`` grid spanning ``[-BOX_HALF, BOX_HALF]^3``, indexed ``[x, y, z]``."""
    decoder.check_latent(latent)
    if resolution < 2:
        raise ValueError(f"resolution must be at least 2, got {resolution}")
    axis = torch.linspace(-BOX_HALF, BOX_HALF, resolution)
    pts = torch.stack(torch.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3)
    z = latent.reshape(1, -1).float()
    out = torch.cat([decoder(z, pts[s : s + GRID_CHUNK]) for s in range(0, len(pts), GRID_CHUNK)])
    return out.reshape(resolution, resolution, resolution).numpy()


def extract_mesh(decoder, latent: torch.Tensor, resolution: int = 64, T_world_obj: torch.Tensor | None = None):
    """Marching cubes on Phi(latent, .) at level 0. Returns a ``trimesh.Trimesh``.

    Args:
        decoder: an ``SDFDecoder``.
        latent: ``(D,)`` shape code.
        resolution: grid points per axis over the padded box.
        T_world_obj: optional ``(4, 4)`` pose; the mesh is then in the world frame.
    """
    import trimesh
    from skimage.measure import marching_cubes

    grid = sdf_grid(decoder, latent, resolution)
    if not (grid.min() < 0 < grid.max()):
        raise EmptyMeshError(f"no surface: the SDF lies in [{grid.min():.3f}, {grid.max():.3f}] over the whole box")
    spacing = 2 * BOX_HALF / (resolution - 1)
    verts, faces, _, _ = marching_cubes(grid, level=0.0, spacing=(spacing,) * 3)
    verts = verts - BOX_HALF
    # With gradient_direction="descent" (the default), faces wind outward for an SDF, which
    # grows outward; the grid is indexed [x, y, z], our object frame, so the winding stands.
    if T_world_obj is not None:
        T = T_world_obj.detach().double().numpy()
        verts = verts @ T[:3, :3].T + T[:3, 3]
    return trimesh.Trimesh(verts, faces, process=False)


def to_open3d(mesh):
    """A ``trimesh.Trimesh`` as an ``open3d.geometry.TriangleMesh`` (with vertex normals)."""
    import open3d as o3d

    m = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(np.asarray(mesh.vertices)), o3d.utility.Vector3iVector(np.asarray(mesh.faces)))
    m.compute_vertex_normals()
    return m
