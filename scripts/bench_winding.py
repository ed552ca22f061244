"""Winding-number inside test: the matrix-product form against the direct formula, on imported meshes.

    python3 scripts/bench_winding.py data/furniture/cars/*.ply --points 2048
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np


def main() -> None:
    import trimesh

    from prismonet.shapes.sdf_samples import winding_number, winding_number_direct

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("meshes", nargs="+")
    ap.add_argument("--points", type=int, default=2048)
    args = ap.parse_args()
    pts = np.random.default_rng(0).uniform(-1.1, 1.1, (args.points, 3))
    ratios, diffs = [], []
    for path in args.meshes:
        m = trimesh.load(path, process=False)
        v, f = np.asarray(m.vertices), np.asarray(m.faces)
        t0 = time.perf_counter()
        ref = winding_number_direct(v, f, pts)
        t1 = time.perf_counter()
        fast = winding_number(v, f, pts)
        t2 = time.perf_counter()
        ratios.append((t1 - t0) / (t2 - t1))
        diffs.append(float(np.abs(ref - fast).max()))
        print(f"{path}: {len(f)} faces, direct {t1 - t0:.2f} s, fast {t2 - t1:.2f} s ({ratios[-1]:.2f}x), max difference {diffs[-1]:.1e}")
    print(f"median speed-up {statistics.median(ratios):.2f}x over {len(ratios)} meshes; largest difference {max(diffs):.1e}")


if __name__ == "__main__":
    main()
