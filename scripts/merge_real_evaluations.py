"""One evaluation of labelled photos from several readings of them (``realdata.evaluate.merge_evaluations``): e.g. the
greyscale photos read with ``--gray-tint both`` and the colour ones with the test-time steps, pooled as one.

    python3 scripts/merge_real_evaluations.py --out OUT RUN_GREY:blox,coins RUN_COLOUR

Each ``RUN[:STEM,...]`` is a ``real evaluate`` output folder and the photo stems to take from it (none: every photo no
earlier folder gave). Writes ``OUT/real_evaluation.json`` and prints the table ``real evaluate`` prints.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main() -> None:
    from prismonet.files import write_atomic
    from realdata.evaluate import format_real_table, merge_evaluations

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", nargs="+", metavar="RUN[:STEM,...]")
    ap.add_argument("--out", required=True)
    args = ap.parse_args()
    parts = []
    for item in args.runs:
        run, _, stems = item.partition(":")
        path = Path(run) / "real_evaluation.json"
        if not path.is_file():
            ap.error(f"{run}: no real_evaluation.json (a `prismonet real evaluate` output folder)")
        parts.append((json.loads(path.read_text()), {s for s in stems.split(",") if s} or None))
    try:
        merged = merge_evaluations(parts)
    except ValueError as e:
        ap.error(str(e))
    Path(args.out).mkdir(parents=True, exist_ok=True)
    write_atomic(Path(args.out) / "real_evaluation.json", json.dumps(merged, indent=1))
    print(format_real_table(merged))
    print(f"merged from {', '.join(args.runs)} into {args.out}/real_evaluation.json")


if __name__ == "__main__":
    main()
