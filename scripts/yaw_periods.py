"""Each shape's period of symmetry about z in an imported shape folder, as ``LossConfig.pose_yaw_periods`` takes it.

    python3 scripts/yaw_periods.py data/furniture/tabletop [--split seen]

Prints a JSON list by shape id (0: round, pi / 2, pi, 2 pi: none; ``prismonet.shapes.symmetry.yaw_period``).
"""

from __future__ import annotations

import argparse
import json
import math
import sys


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("shapes", help="a folder made by 'prismonet shapes import-furniture', or 'clevr'")
    ap.add_argument("--split", default="seen", choices=("seen", "unseen"))
    args = ap.parse_args(argv)
    from prismonet.threads import use_free_cores

    if argv is None:  # the command line; a caller passing argv (a test) keeps its own threads
        use_free_cores(exit_on_error=True)  # the cores others leave free; PRISMONET_THREADS=N to choose
    from prismonet.shapes.symmetry import library_yaw_periods

    periods = library_yaw_periods(args.shapes, args.split)
    print(json.dumps([round(p, 6) for p in periods]))
    names = {0.0: "round", round(math.pi / 2, 6): "pi/2", round(math.pi, 6): "pi", round(2 * math.pi, 6): "none"}
    print(f"{sum(p == 0 for p in periods)} of {len(periods)} round; " + ", ".join(f"{i}: {names[round(p, 6)]}" for i, p in enumerate(periods)),
          file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
