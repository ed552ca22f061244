"""Mesh normalisation into the shape prior's box, and mesh validation.

Every mesh is centred on its bounding-box centre and scaled uniformly so that its largest
half-extent is ``SHAPE_HALF_EXTENT`` (= 1). The SDF is learned in the padded cube
``[-BOX_HALF, BOX_HALF]^3``, which is also the box that the renderer casts rays through: the
renderer knows every shape's bounds without looking at it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from prismonet.shapes.clevr_set import SHAPE_HALF_EXTENT

PADDING = 0.1
"""Margin around the normalised shape in which the SDF is still learned, so that the zero level
set is never at the edge of the sampled region."""
BOX_HALF = SHAPE_HALF_EXTENT + PADDING
"""Half-side of the object-frame cube that holds every normalised shape (and its SDF domain)."""
PADDED_CUBE = ((-BOX_HALF,) * 3, (BOX_HALF,) * 3)
"""The object-frame box ``(lo, hi)`` that holds every normalised shape with its padding."""

FLAT_RELATIVE_EXTENT = 1e-6
"""A mesh whose smallest bounding-box extent is below this fraction of its largest is flat."""


class MeshError(ValueError):
    """A mesh that cannot be turned into SDF samples (empty, NaN, flat)."""


@dataclass(frozen=True)
class Normalization:
    """``x_normalised = (x - center) * scale``."""

    center: tuple[float, float, float]
    scale: float


def validate_mesh(vertices: np.ndarray, faces: np.ndarray, name: str = "mesh") -> None:
    """Raise ``MeshError`` for an empty, non-finite or flat mesh, or out-of-range faces."""
    v = np.asarray(vertices)
    f = np.asarray(faces)
    if v.ndim != 2 or v.shape[1] != 3:
        raise MeshError(f"{name}: vertices must have shape (V, 3), got {v.shape}")
    if f.ndim != 2 or f.shape[1] != 3:
        raise MeshError(f"{name}: faces must have shape (F, 3), got {f.shape}")
    if len(v) == 0 or len(f) == 0:
        raise MeshError(f"{name}: empty mesh ({len(v)} vertices, {len(f)} faces)")
    if not np.isfinite(v).all():
        raise MeshError(f"{name}: {int((~np.isfinite(v)).any(1).sum())} vertices are NaN or infinite")
    if f.min() < 0 or f.max() >= len(v):
        raise MeshError(f"{name}: face indices out of range [0, {len(v) - 1}]")
    used = v[np.unique(f)]
    extent = used.max(0) - used.min(0)
    if extent.max() <= 0 or extent.min() < FLAT_RELATIVE_EXTENT * extent.max():
        axis = "xyz"[int(extent.argmin())]
        raise MeshError(f"{name}: degenerate (flat) mesh: its extent along {axis} is {extent.min():.3g}")


def normalize_mesh(vertices: np.ndarray, faces: np.ndarray, name: str = "mesh") -> tuple[np.ndarray, Normalization]:
    """Validate, centre and scale a mesh so that its largest half-extent is 1. Returns new vertices."""
    validate_mesh(vertices, faces, name)
    v = np.asarray(vertices, dtype=np.float64)
    used = v[np.unique(faces)]
    lo, hi = used.min(0), used.max(0)
    center = (lo + hi) / 2
    scale = SHAPE_HALF_EXTENT / float((hi - lo).max() / 2)
    return (v - center) * scale, Normalization(tuple(center.tolist()), scale)


def shape_bounds(meshes) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
    """The object-frame box ``(lo, hi)`` that holds every normalised mesh of a set with ``PADDING`` to
    spare, within the padded cube: a prior's ``bounds``, through which the renderer casts rays."""
    vs = np.concatenate([normalize_mesh(v, f)[0] for v, f in meshes])
    lo = np.maximum(vs.min(0) - PADDING, -BOX_HALF)
    hi = np.minimum(vs.max(0) + PADDING, BOX_HALF)
    return tuple(float(x) for x in lo), tuple(float(x) for x in hi)
