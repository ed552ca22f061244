"""Wooden toy blocks as a shape set: boxes of many proportions (cubes, bars, boards, slabs), hexagonal
prisms and triangular wedges, made here from their geometry (no download, no licence of others).

They are what a real block photo holds (the shipped ``blox.jpg``: a hexagonal slab carrying a board, a
bar and a cube, with blocks and a wedge in front), which the Clevr set's single cube cannot draw. The set
is written as a folder in the import format (``models.json`` + one PLY per shape,
``prismonet.shapes.library``), so that the prior's pre-training, the scene generators and the renderer
take it like any imported set; ``models.json`` says ``"own_colors": false``: the generators give every
block one of the CLEVR colours, as they do Clevr shapes.

Every shape is centred, its largest half-extent is 1 and its base lies at ``z = -h_z`` (Clevr's rules).
Boxes and hexagonal prisms have a flat top that other blocks may rest on (``top_face``); a wedge's top
is a ridge.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from prismonet.files import write_atomic

SETTING = "blocks"
BOX_WIDTHS = (1.0, 0.6, 0.35)
"""Half-extents along y of the boxes (x is 1)."""
BOX_HEIGHTS = (1.0, 0.5, 0.25, 0.15)
"""Half-extents along z of the boxes: cube-like, bars, boards, thin boards."""
HEX_HEIGHTS = (0.8, 0.4, 0.2)
"""Half-heights of the hexagonal prisms (circumradius 1: a corner on +x)."""
WEDGE_SIZES = ((1.0, 0.8), (0.5, 0.8), (1.0, 0.45), (0.5, 0.45))
"""``(h_y, h_z)`` of the wedges: a triangle in the xz plane (base 2 along x), extruded along y."""
HEX_HALF_WIDTH = math.cos(math.pi / 6)
"""Half-extent along y of a hexagon of circumradius 1 with a corner on +x (flat to flat / 2)."""


def block_specs() -> list[dict]:
    """Every block: ``name``, ``category`` (``box``, ``hexprism``, ``wedge``) and ``half_extents``."""
    out = []
    for hy in BOX_WIDTHS:
        for hz in BOX_HEIGHTS:
            out.append({"name": f"box_{hy:g}_{hz:g}", "category": "box", "half_extents": [1.0, hy, hz]})
    for hz in HEX_HEIGHTS:
        out.append({"name": f"hexprism_{hz:g}", "category": "hexprism", "half_extents": [1.0, HEX_HALF_WIDTH, hz]})
    for hy, hz in WEDGE_SIZES:
        out.append({"name": f"wedge_{hy:g}_{hz:g}", "category": "wedge", "half_extents": [1.0, hy, hz]})
    return out


def _prism(outline: np.ndarray, axis: int, half: float):
    """A closed prism: the convex polygon ``outline (n, 2)`` extruded by ``+-half`` along ``axis``
    (outline coordinates are the other two axes, in order)."""
    import trimesh

    other = [a for a in range(3) if a != axis]
    n = len(outline)
    v = np.zeros((2 * n, 3))
    for side, h in enumerate((-half, half)):
        v[side * n:(side + 1) * n, other[0]] = outline[:, 0]
        v[side * n:(side + 1) * n, other[1]] = outline[:, 1]
        v[side * n:(side + 1) * n, axis] = h
    mesh = trimesh.convex.convex_hull(v)
    return np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int32)


def block_mesh(category: str, half_extents) -> tuple[np.ndarray, np.ndarray]:
    """Watertight mesh ``(vertices (V, 3), faces (F, 3))`` of a block, centred, in its object frame: a box or a
    hexagonal prism is its top face extruded down to ``-h_z``; a wedge, its triangle in the xz plane along y."""
    hx, hy, hz = (float(h) for h in half_extents)
    if category == "wedge":
        outline = np.array([[-hx, -hz], [hx, -hz], [0.0, hz]])  # (x, z): base on the ground, ridge on top
        return _prism(outline, 1, hy)
    return _prism(top_face(category, half_extents), 2, hz)


def top_face(category: str, half_extents) -> np.ndarray | None:
    """The flat top ``(n, 2)`` (object-frame xy, counter-clockwise) that another block may rest on, at
    ``z = h_z``; ``None`` for a wedge (its top is a ridge)."""
    hx, hy, _ = (float(h) for h in half_extents)
    if category == "box":
        return np.array([[-hx, -hy], [hx, -hy], [hx, hy], [-hx, hy]])
    if category == "hexprism":
        a = np.arange(6) * math.pi / 3
        return np.stack([hx * np.cos(a), hx * np.sin(a)], 1)
    if category == "wedge":
        return None
    raise ValueError(f"unknown block category {category!r}; expected box, hexprism or wedge")


def volume(category: str, half_extents) -> float:
    """Volume at scale 1 (the blocks' masses, for the stacks' balance)."""
    hx, hy, hz = (float(h) for h in half_extents)
    if category == "box":
        return 8.0 * hx * hy * hz
    if category == "hexprism":
        return 1.5 * math.sqrt(3.0) * hx * hx * 2.0 * hz
    if category == "wedge":
        return 0.5 * (2.0 * hx) * (2.0 * hz) * (2.0 * hy)
    raise ValueError(f"unknown block category {category!r}; expected box, hexprism or wedge")


def write_blocks(out: str | Path) -> dict:
    """Write the block set to the new folder ``out`` (PLYs and ``models.json``); returns the record."""
    import trimesh

    out = Path(out)
    if out.exists() and any(out.iterdir()):
        raise ValueError(f"{out} exists and is not empty; choose a new folder")
    out.mkdir(parents=True, exist_ok=True)
    models = []
    for spec in block_specs():
        v, f = block_mesh(spec["category"], spec["half_extents"])
        mesh = trimesh.Trimesh(v, f, vertex_colors=np.full((len(v), 4), (160, 160, 160, 255), np.uint8), process=False)
        if not mesh.is_watertight:
            raise RuntimeError(f"block {spec['name']}: mesh is not watertight")
        write_atomic(out / f"{spec['name']}.ply", mesh.export(file_type="ply"))
        models.append({**spec, "file": f"{spec['name']}.ply", "faces": int(len(f)), "watertight": True, "split": "seen",
                       "source": "made by prismonet.shapes.blocks", "licence": "the project's"})
    record = {"setting": SETTING, "own_colors": False, "models": models,
              "counts": {"seen": len(models), "unseen": 0}}
    write_atomic(out / "models.json", json.dumps(record, indent=1).encode())
    return record
