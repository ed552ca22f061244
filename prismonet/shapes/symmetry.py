"""Symmetry about the vertical axis: the turns about z that leave a shape as it is.

A glass or a bottle looks the same at every yaw, a box turned by 180 degrees (a square one by 90) looks the same,
a mug with a handle only at 360. The image cannot tell those yaws apart, so neither can a yaw loss (L_pose): on a
round object its yaw term is noise. ``yaw_period`` finds the period from the mesh itself: surface samples, turned,
against a second set of samples (``RATIO``).
"""

from __future__ import annotations

import math

import numpy as np

ANY = 0.0
"""Period of a shape every turn leaves as it is (a surface of revolution)."""
NONE = 2 * math.pi
"""Period of a shape only a whole turn leaves as it is."""
RATIO = 1.5
"""A turn leaves the shape as it is when the 99th percentile of the distances from the turned samples to a second,
independent set of samples is at most this many times that of the unturned ones: the sampling's own spread sets the
scale, and a high percentile sees a handle that a mean would average away. On the 13 seen tableware meshes the round
ones give 0.97-1.13, a mug's handle or a spray bottle's head 2.8-10."""
QUANTILE = 0.99
ROUND_TURNS = (0.3, 0.7, 1.1, 1.9, 2.5)
"""Turns (radians), off every period of 2 pi / n for n <= 4, that a round shape must survive."""


def _turn(points: np.ndarray, angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return points @ np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])


def yaw_period(vertices: np.ndarray, faces: np.ndarray, samples: int = 8000, ratio: float = RATIO, seed: int = 0) -> float:
    """The smallest turn about the object's z axis that leaves the mesh as it is: ``ANY`` (0), ``pi / 2``, ``pi``
    or ``NONE`` (``2 pi``).

    Args:
        vertices: ``(V, 3)`` in the object frame (z up, centred as the shapes are); faces: ``(F, 3)``.
        samples: surface points per set; ratio: see ``RATIO``; seed: the sampling's.
    """
    import trimesh
    from scipy.spatial import cKDTree

    mesh = trimesh.Trimesh(np.asarray(vertices, np.float64), np.asarray(faces, np.int64), process=False)
    if len(mesh.faces) == 0 or not mesh.area > 0:
        raise ValueError("yaw_period: the mesh has no surface")
    a, _ = trimesh.sample.sample_surface(mesh, samples, seed=seed)
    b, _ = trimesh.sample.sample_surface(mesh, samples, seed=seed + 1)
    tree = cKDTree(b)
    bar = ratio * float(np.quantile(tree.query(a)[0], QUANTILE))

    def left_as_is(angle: float) -> bool:
        return float(np.quantile(tree.query(_turn(a, angle))[0], QUANTILE)) <= bar

    if all(left_as_is(t) for t in ROUND_TURNS):
        return ANY
    for period in (math.pi / 2, math.pi):
        if left_as_is(period):
            return period
    return NONE


def library_yaw_periods(name: str, split: str = "seen") -> list[float]:
    """``yaw_period`` of each shape of a shape library (``prismonet.shapes.library.shape_library``), by shape id: what
    ``LossConfig.pose_yaw_periods`` takes for scenes made from it."""
    from prismonet.shapes.library import shape_library

    lib = shape_library(name, split)
    return [yaw_period(*lib.mesh(i)) for i in range(len(lib.specs))]
