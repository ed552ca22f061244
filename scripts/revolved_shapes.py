"""More training shapes for a tableware prior: surfaces of revolution drawn at random (bottles, tumblers, cups, stemmed
glasses), added to an imported setting's seen models.

    python3 scripts/revolved_shapes.py data/furniture/tabletop data/furniture/tabletop_revolved --count 60 [--seed 0] \
        [--colors grey|random]

OUT is a copy of an imported folder (``prismonet shapes import-furniture``: ``models.json`` + PLYs) with ``--count``
generated seen models added (``generated-KIND-NNN``, licence CC0-1.0: made here). Each is a closed profile in (radius,
height) revolved about z (``trimesh.creation.revolve``): a solid bottle (body, shoulder, neck), or a hollow vessel
(straight or tapered wall, a floor, a wall thickness), with or without a stem and foot. Unseen models are copied
unchanged, so ``scripts/prior_unseen.py`` scores a prior trained on OUT on the same unseen meshes. Colours are a grey;
nothing of the scenes depends on them (the prior is shape alone). With ``--colors random`` each generated model gets one
colour of its own (``random_color``), so that scenes can show the generated shapes too without a colour that tells them
apart; the shapes are the same either way (the colours are drawn from their own stream).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

KINDS = ("bottle", "tumbler", "cup", "stemmed")


def profile(kind: str, rng: np.random.Generator) -> np.ndarray:
    """A closed (radius, height) polyline from the axis back to the axis, counter-clockwise, height about 2."""
    h = 2.0
    if kind == "bottle":
        R = rng.uniform(0.25, 0.7)
        body = rng.uniform(0.45, 0.7) * h
        shoulder = rng.uniform(0.08, 0.25) * h
        neck_r = rng.uniform(0.12, 0.4) * R
        pts = [(0, 0), (R, 0), (R, body), (neck_r, body + shoulder), (neck_r, h), (0, h)]
        return np.asarray(pts)
    R0 = rng.uniform(0.3, 0.9)  # rim radius
    taper = rng.uniform(0.6, 1.0) if kind != "cup" else rng.uniform(0.75, 1.0)
    wall = rng.uniform(0.03, 0.08)
    if kind == "stemmed":
        foot_r, foot_t = rng.uniform(0.5, 0.9) * R0, rng.uniform(0.03, 0.08)
        stem_r, stem_h = rng.uniform(0.04, 0.1), rng.uniform(0.25, 0.5) * h
        bowl_lo, floor = foot_t + stem_h, rng.uniform(0.05, 0.15)
        r_lo = rng.uniform(0.1, 0.5) * R0
        return np.asarray([(0, 0), (foot_r, 0), (foot_r, foot_t), (stem_r, foot_t), (stem_r, bowl_lo), (r_lo, bowl_lo + 0.05),
                           (R0, h), (R0 - wall, h), (max(r_lo - wall, 0.02), bowl_lo + 0.05 + floor), (0, bowl_lo + 0.05 + floor)])
    height = h * (rng.uniform(0.4, 0.8) if kind == "cup" else rng.uniform(0.6, 1.0))
    floor = rng.uniform(0.04, 0.15)
    r_base = R0 * taper
    return np.asarray([(0, 0), (r_base, 0), (R0, height), (R0 - wall, height), (r_base - wall, floor), (0, floor)])


def random_color(rng: np.random.Generator) -> np.ndarray:
    """One RGB albedo in [0, 1]: hue uniform, saturation in [0, 0.8], value in [0.08, 1] (dark bottles to white cups:
    the imported tableware's own colours span that range)."""
    import colorsys

    return np.asarray(colorsys.hsv_to_rgb(rng.uniform(0, 1), rng.uniform(0, 0.8), rng.uniform(0.08, 1.0)))


def revolved_mesh(kind: str, rng: np.random.Generator, sections: int = 48) -> tuple[np.ndarray, np.ndarray]:
    """A watertight mesh of one random shape of ``kind``, normalised (largest half-extent 1, centred)."""
    import trimesh

    from prismonet.shapes.normalize import normalize_mesh

    mesh = trimesh.creation.revolve(profile(kind, rng), sections=sections)
    v = normalize_mesh(np.asarray(mesh.vertices), np.asarray(mesh.faces))[0]
    return v, np.asarray(mesh.faces)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("src")
    ap.add_argument("out")
    ap.add_argument("--count", type=int, default=60)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--colors", choices=("grey", "random"), default="grey",
                    help="grey (0.7) for every generated model, or one random colour each (scenes that show them)")
    a = ap.parse_args(argv)
    from prismonet.shapes.library import copy_library, write_library_record

    src, out = Path(a.src), Path(a.out)
    if a.count <= 0:
        print("revolved_shapes: error: --count must be positive", file=sys.stderr)
        return 2
    try:
        record = copy_library(src, out)
    except ValueError as e:
        print(f"revolved_shapes: error: {e}", file=sys.stderr)
        return 2
    import trimesh

    models = list(record["models"])
    rng = np.random.default_rng(a.seed)
    color_rng = np.random.default_rng([a.seed, 1])  # its own stream: the shapes do not depend on --colors
    for i in range(a.count):
        kind = KINDS[i % len(KINDS)]
        v, f = revolved_mesh(kind, rng)
        name = f"generated-{kind}-{i:03d}"
        color = random_color(color_rng) if a.colors == "random" else np.full(3, 0.7)
        mesh = trimesh.Trimesh(v, f, process=False)
        mesh.visual.vertex_colors = np.append(np.rint(color * 255), 255).astype(np.uint8)
        mesh.export(out / f"{name}.ply")
        models.append({"name": name, "title": f"Generated {kind}", "category": "bottle" if kind == "bottle" else "glass",
                       "file": f"{name}.ply", "faces": int(len(f)), "half_extents": ((v.max(0) - v.min(0)) / 2).round(6).tolist(),
                       "color": color.round(4).tolist(), "watertight": bool(mesh.is_watertight), "creator": "prismonet scripts/revolved_shapes.py",
                       "licence": "CC0-1.0", "source": {"generated": kind, "seed": a.seed, "index": i}, "split": "seen"})
    counts = write_library_record(out, record, models, generated={"from": str(src), "count": a.count, "seed": a.seed})
    print(f"{out}: {counts['seen']} seen models ({a.count} generated), {counts['unseen']} unseen")
    return 0


if __name__ == "__main__":
    sys.exit(main())
