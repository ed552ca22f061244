"""The Clevr shape set: 3 categories x 9 scalings along the principal axes = 27 shapes.

Every shape is centred at the origin of its object frame and normalised so that its largest
half-extent is exactly 1 (``SHAPE_HALF_EXTENT``); a shape posed with scale ``s`` therefore has
world half-extent ``s`` along its longest axis. The same 27 shapes are used to generate scenes
and to pre-train the shape prior, as in the paper ("nine shapes per category with different
scaling along the axes").

The nine scalings of a category are the half-extents ``(1, b, a)`` with ``a`` (vertical) and
``b`` (second horizontal axis) each in ``ASPECTS``.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

CATEGORIES: tuple[str, ...] = ("sphere", "cylinder", "cube")
ASPECTS: tuple[float, ...] = (1.0, 0.75, 0.5)
SHAPE_HALF_EXTENT = 1.0
"""Largest half-extent of every normalised shape in its object frame."""

SPHERE_SUBDIVISIONS = 4
"""Icosphere subdivisions: 5120 faces, so the facets are far below a pixel at 64x64."""
CYLINDER_SECTIONS = 96


class UnknownCategoryError(ValueError):
    """A shape category that the Clevr set does not have."""


@dataclass(frozen=True)
class ShapeSpec:
    """One shape of the set.

    Attributes:
        shape_id: index in ``0..26``.
        category: ``"sphere"``, ``"cylinder"`` or ``"cube"``.
        category_id: index of ``category`` in ``CATEGORIES``.
        instance_id: index ``0..8`` within the category.
        half_extents: ``(x, y, z)`` half-extents in the object frame; the largest is 1.
    """

    shape_id: int
    category: str
    category_id: int
    instance_id: int
    half_extents: tuple[float, float, float]

    def footprint_radius(self) -> float:
        """Radius of the smallest disc around the origin that covers the xy footprint (scale 1)."""
        hx, hy, _ = self.half_extents
        return max(hx, hy) if self.category in ("sphere", "cylinder") else float(np.hypot(hx, hy))  # else its box

    def bounding_radius(self) -> float:
        """Radius of the smallest ball around the origin that covers the shape (scale 1)."""
        hx, hy, hz = self.half_extents
        if self.category == "sphere":
            return max(hx, hy, hz)
        if self.category == "cylinder":
            return float(np.hypot(max(hx, hy), hz))
        return float(np.linalg.norm([hx, hy, hz]))  # a cube, or any other shape: its box


def category_id(name: str) -> int:
    try:
        return CATEGORIES.index(name)
    except ValueError:
        raise UnknownCategoryError(f"unknown shape category {name!r}; expected one of {CATEGORIES}") from None


def clevr_shapes() -> list[ShapeSpec]:
    """All 27 shapes, ordered by category then instance."""
    specs = []
    for c, name in enumerate(CATEGORIES):
        for i, (a, b) in enumerate((a, b) for a in ASPECTS for b in ASPECTS):
            specs.append(ShapeSpec(len(specs), name, c, i, (SHAPE_HALF_EXTENT, b, a)))
    return specs


@lru_cache(maxsize=None)
def shape_mesh(shape_id: int) -> tuple[np.ndarray, np.ndarray]:
    """Watertight triangle mesh of a shape in its object frame: ``(V, 3)`` float64, ``(F, 3)`` int32."""
    import trimesh

    specs = clevr_shapes()
    if not 0 <= shape_id < len(specs):
        raise ValueError(f"shape_id: expected 0..{len(specs) - 1}, got {shape_id}")
    spec = specs[shape_id]
    if spec.category == "sphere":
        mesh = trimesh.creation.icosphere(subdivisions=SPHERE_SUBDIVISIONS, radius=1.0)
    elif spec.category == "cylinder":
        mesh = trimesh.creation.cylinder(radius=1.0, height=2.0, sections=CYLINDER_SECTIONS)
    else:
        mesh = trimesh.creation.box(extents=(2.0, 2.0, 2.0))
    vertices = np.asarray(mesh.vertices, dtype=np.float64) * np.asarray(spec.half_extents)
    return vertices, np.asarray(mesh.faces, dtype=np.int32)
