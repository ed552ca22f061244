"""The shapes scenes are made of: the 27 Clevr shapes, or a folder of imported meshes
(``prismonet.shapes.furniture``), behind one interface for the scene generator and its renderer.

A library lists ``ShapeSpec`` entries (id, category, half-extents: what placement needs) and gives each
shape's mesh in its object frame (centred, largest half-extent 1) and, for imported meshes, the colour of
each face (Clevr shapes take one of the eight CLEVR colours per object instead).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

from prismonet.shapes.clevr_set import ShapeSpec, clevr_shapes, shape_mesh

CLEVR = "clevr"


@dataclass(frozen=True)
class ShapeLibrary:
    name: str
    """``"clevr"`` or the folder of an import."""
    split: str
    """Which models of an import (``seen`` or ``unseen``); ``"all"`` for Clevr."""
    specs: tuple[ShapeSpec, ...]
    categories: tuple[str, ...]
    files: tuple[str, ...] = ()
    """The PLY of each shape (imports only)."""
    recolor: bool = False
    """An import whose objects take a CLEVR colour each, as Clevr shapes do (``models.json``'s
    ``"own_colors": false``, e.g. ``prismonet.shapes.blocks``)."""

    @property
    def own_colors(self) -> bool:
        """Whether the shapes carry their own colours (imports) rather than taking a CLEVR colour."""
        return self.name != CLEVR and not self.recolor

    def mesh(self, shape_id: int) -> tuple[np.ndarray, np.ndarray]:
        """``(vertices (V, 3) float64, faces (F, 3) int32)`` in the object frame."""
        if self.name == CLEVR:
            return shape_mesh(shape_id)
        return _ply(self.files[shape_id])[:2]

    def face_colors(self, shape_id: int) -> np.ndarray | None:
        """``(F, 3)`` uint8 colour of each face (the mean of its vertices'), or ``None`` for Clevr shapes."""
        return None if self.name == CLEVR else _ply(self.files[shape_id])[2]


@lru_cache(maxsize=None)
def _ply(path: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    import trimesh

    mesh = trimesh.load(path, process=False)
    v, f = np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int32)
    vc = np.asarray(mesh.visual.vertex_colors, np.float64)[:, :3]
    return v, f, np.rint(vc[f].mean(1)).astype(np.uint8)


@lru_cache(maxsize=None)
def shape_library(name: str = CLEVR, split: str = "seen") -> ShapeLibrary:
    """The library called ``name``: ``"clevr"``, or a folder made by ``shapes import-furniture``
    (its ``split`` models, ordered by name, ids ``0..n-1`` in that order)."""
    if name == CLEVR:
        specs = tuple(clevr_shapes())
        return ShapeLibrary(CLEVR, "all", specs, tuple(dict.fromkeys(s.category for s in specs)))
    folder = Path(name)
    if not (folder / "models.json").is_file():
        raise ValueError(f"unknown shape library {name!r}: expected 'clevr' or a folder made by 'shapes import-furniture'")
    record = json.loads((folder / "models.json").read_text())
    models = sorted((m for m in record["models"] if m["split"] == split), key=lambda m: m["name"])
    if not models:
        raise ValueError(f"{folder}: no {split!r} models")
    cats = tuple(sorted({m.get("category", record["setting"]) for m in models}))
    specs, count = [], {c: 0 for c in cats}
    for i, m in enumerate(models):
        c = m.get("category", record["setting"])
        specs.append(ShapeSpec(i, c, cats.index(c), count[c], tuple(float(h) for h in m["half_extents"])))
        count[c] += 1
    return ShapeLibrary(str(folder), split, tuple(specs), cats, tuple(str(folder / m["file"]) for m in models),
                        recolor=not record.get("own_colors", True))


def copy_library(src: str | Path, out: str | Path) -> dict:
    """Copy an imported folder (``models.json`` and its meshes) into the new folder ``out``, to add models to; returns
    the ``models.json`` record. ``ValueError`` when ``src`` is not an import or ``out`` exists."""
    import shutil

    src, out = Path(src), Path(out)
    if not (src / "models.json").is_file():
        raise ValueError(f"{src} has no models.json (a folder made by `prismonet shapes import-furniture`)")
    if out.exists():
        raise ValueError(f"{out} exists; choose a new folder")
    record = json.loads((src / "models.json").read_text())
    out.mkdir(parents=True)
    for m in record["models"]:
        shutil.copy2(src / m["file"], out / m["file"])
    return record


def write_library_record(out: str | Path, record: dict, models: list[dict], **extra) -> dict[str, int]:
    """Write ``out/models.json``: ``record`` with ``models``, their counts per split and ``extra`` fields; returns the counts."""
    counts = {s: sum(1 for m in models if m["split"] == s) for s in ("seen", "unseen")}
    (Path(out) / "models.json").write_text(json.dumps({**record, "models": models, "counts": counts, **extra}, indent=1))
    return counts
