"""Pool folders of labelled photos into one (``realdata.labels.pool_labels``): the photo stand-ins' three sets (tiny,
crowded, sparse) are read as one pooled folder per split, each photo renamed ``SET_NAME``.

    python3 scripts/pool_photos.py tiny=data/standins/tiny_photos/val crowded=data/standins/crowded_photos/val \
        sparse=data/standins/sparse_photos/val --out data/standins/pooled_val
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main() -> None:
    from realdata.labels import LabelError, pool_labels

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("folders", nargs="+", metavar="PREFIX=FOLDER", help="a folder of labelled photos and its name prefix")
    ap.add_argument("--out", required=True)
    args = ap.parse_args()
    pools = {}
    for item in args.folders:
        prefix, sep, folder = item.partition("=")
        if not sep or not prefix or not folder or not prefix.replace("-", "").isalnum():
            ap.error(f"expected PREFIX=FOLDER with a plain prefix (letters, digits, -), got {item!r}")
        if prefix in pools:
            ap.error(f"the prefix {prefix!r} is given twice")
        pools[prefix] = folder
    try:
        n = pool_labels(pools, args.out)
    except LabelError as e:
        sys.exit(f"pool_photos: error: {e}")
    print(f"pooled {n} labelled photos from {len(pools)} folders into {args.out}")


if __name__ == "__main__":
    main()
