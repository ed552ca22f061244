"""Reader for the real block-tower photos of Lerer et al. (2016).

Layout: ``ROOT/recordings/img_frame1_N.png`` and ``ROOT/splits/<name>/test.txt`` with lines
``file label`` (0 = stable, 1 = unstable). The photos themselves are not shipped (not
reachable offline); the reader is tested on a fixture in the same layout.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from realdata.io import PhotoError, load_photo
from realdata.prepare import check_box


@dataclass(frozen=True)
class TowerPhoto:
    path: Path
    label: int  # 0 stable, 1 unstable


def read_split(root: str | Path, split: str, part: str = "test") -> list[TowerPhoto]:
    """The photos listed in ``splits/<split>/<part>.txt``."""
    root = Path(root)
    listing = root / "splits" / split / f"{part}.txt"
    if not listing.is_file():
        raise PhotoError(f"{listing}: no such split listing")
    out = []
    for n, line in enumerate(listing.read_text().splitlines(), 1):
        if not line.strip():
            continue
        parts = line.split()
        if len(parts) != 2 or parts[1] not in ("0", "1"):
            raise PhotoError(f"{listing}:{n}: expected 'file label' with label 0 or 1, got {line!r}")
        path = root / parts[0] if (root / parts[0]).exists() else root / "recordings" / parts[0]
        if not path.is_file():
            raise PhotoError(f"{listing}:{n}: {parts[0]} not found under {root} or {root / 'recordings'}")
        out.append(TowerPhoto(path, int(parts[1])))
    return out


def load_tower(photo: TowerPhoto, box: tuple[int, int, int, int] | None, size: int = 64) -> np.ndarray:
    """Crop (``box = (x0, y0, w, h)``, default: the centred square) and scale to ``size``."""
    import cv2

    img = load_photo(photo.path)
    H, W = img.shape[:2]
    if box is None:
        s = min(H, W)
        box = ((W - s) // 2, (H - s) // 2, s, s)
    x0, y0, w, h = check_box(box, img.shape, str(photo.path))
    return cv2.resize(img[y0 : y0 + h, x0 : x0 + w], (size, size), interpolation=cv2.INTER_AREA)
