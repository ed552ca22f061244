"""More training shapes for a prior from the ones a setting has: each seen mesh stretched along its axes.

    python3 scripts/stretch_shapes.py data/furniture/tabletop data/furniture/tabletop_stretch --stretch z=0.7 z=1.4

OUT is a copy of an imported folder (``prismonet shapes import-furniture``: ``models.json`` + PLYs) in which every seen
model also appears once per ``--stretch`` (``AXIS=FACTOR[,AXIS=FACTOR]``: its vertices scaled along those object axes,
then normalised again to the largest half-extent 1), as a seen model named ``NAME-z0.7`` with the original's category,
colour, source and licence and ``stretched_from``. Unseen models are copied unchanged, so a prior trained on OUT's seen
models is scored on the same unseen meshes (``scripts/prior_unseen.py``). The meshes' licences (CC0, CC-BY) allow the
derived shapes; their attributions stay with them.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

AXES = {"x": 0, "y": 1, "z": 2}


def parse_stretch(text: str) -> dict[int, float]:
    """``"z=0.7"`` or ``"x=1.2,y=0.8"`` -> ``{axis: factor}``."""
    out = {}
    for part in text.split(","):
        k, _, v = part.partition("=")
        if k.strip() not in AXES or not v:
            raise ValueError(f"--stretch {text!r}: expected AXIS=FACTOR[,AXIS=FACTOR] with AXIS in x, y, z")
        f = float(v)
        if not f > 0:
            raise ValueError(f"--stretch {text!r}: factors must be positive")
        out[AXES[k.strip()]] = f
    return out


def stretched(vertices: np.ndarray, faces: np.ndarray, factors: dict[int, float]) -> np.ndarray:
    """The vertices scaled along ``factors``' axes, then centred and normalised (largest half-extent 1)."""
    from prismonet.shapes.normalize import normalize_mesh

    v = np.asarray(vertices, dtype=np.float64).copy()
    for axis, f in factors.items():
        v[:, axis] *= f
    return normalize_mesh(v, faces)[0]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("src")
    ap.add_argument("out")
    ap.add_argument("--stretch", nargs="+", required=True, help="AXIS=FACTOR[,AXIS=FACTOR] per variant, e.g. z=0.7 z=1.4")
    a = ap.parse_args(argv)
    try:
        variants = [(s.replace("=", "").replace(",", "-"), parse_stretch(s)) for s in a.stretch]
    except ValueError as e:
        print(f"stretch_shapes: error: {e}", file=sys.stderr)
        return 2
    from prismonet.shapes.library import copy_library, write_library_record

    src, out = Path(a.src), Path(a.out)
    try:
        record = copy_library(src, out)
    except ValueError as e:
        print(f"stretch_shapes: error: {e}", file=sys.stderr)
        return 2
    import trimesh

    models = []
    for m in record["models"]:
        models.append(m)
        if m["split"] != "seen":
            continue
        mesh = trimesh.load(src / m["file"], process=False)
        faces = np.asarray(mesh.faces)
        for tag, factors in variants:
            v = stretched(np.asarray(mesh.vertices), faces, factors)
            name = f"{m['name']}-{tag}"
            trimesh.Trimesh(v, faces, process=False).export(out / f"{name}.ply")
            half = ((v.max(0) - v.min(0)) / 2).round(6).tolist()
            models.append({**m, "name": name, "file": f"{name}.ply", "half_extents": half, "stretched_from": m["name"]})
    counts = write_library_record(out, record, models, stretched={"from": str(src), "variants": a.stretch})
    print(f"{out}: {counts['seen']} seen models ({len(variants)} stretched copies of each of {counts['seen'] // (len(variants) + 1)}), "
          f"{counts['unseen']} unseen")
    return 0


if __name__ == "__main__":
    sys.exit(main())
