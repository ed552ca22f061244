"""Labelled real photos: one JSON per photo, ``{"photo": PATH (relative to the JSON), "objects":
[{"box": [x0, y0, x1, y1], "colour": WORD, "kind": WORD}, ...]}``, boxes in photo pixels (the
outermost pixels' corners), and optionally ``"elevation_deg"``: the camera's elevation above the table,
judged by eye (for uncalibrated photos and models that take the camera as an input), and ``"ignore": [[x0, y0, x1,
y1], ...]``: boxes of visible objects too small to be labelled (a detection on one counts neither for nor against the
model, as COCO's crowd regions; ``realdata.evaluate``).
``realdata/samples/labels/`` holds the shipped photos' labels."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path


class LabelError(ValueError):
    """A label file that is missing, malformed, or names a photo that is not there (one line)."""


@dataclass(frozen=True)
class LabelledPhoto:
    label_file: Path
    photo: Path
    boxes: tuple[tuple[float, float, float, float], ...]
    words: tuple[tuple[str, str], ...]
    """``(colour, kind)`` per object."""
    elevation_deg: float | None = None
    """The camera's elevation above the table by eye, in (0, 90), if the label gives one."""
    ignore: tuple[tuple[float, float, float, float], ...] = ()
    """Boxes of visible objects too small to label: detections there are neither hits nor false ones."""


def _box(value, where: str) -> tuple[float, float, float, float]:
    import math

    if not (isinstance(value, list) and len(value) == 4 and all(isinstance(v, (int, float)) and math.isfinite(v) for v in value)):
        raise LabelError(f"{where}: box must be [x0, y0, x1, y1] (four finite numbers), got {value!r}")
    x0, y0, x1, y1 = (float(v) for v in value)
    if x1 <= x0 or y1 <= y0:
        raise LabelError(f"{where}: box must have x1 > x0 and y1 > y0, got {value!r}")
    return x0, y0, x1, y1


def load_label(path: str | Path) -> LabelledPhoto:
    from prismonet.files import InputError, read_json

    path = Path(path)
    try:
        d = read_json(path, dict)
    except InputError as e:
        raise LabelError(str(e)) from None
    if not isinstance(d.get("photo"), str) or not isinstance(d.get("objects"), list):
        raise LabelError(f"{path}: expected {{\"photo\": PATH, \"objects\": [...]}}")
    photo = (path.parent / d["photo"]).resolve()
    if not photo.is_file():
        raise LabelError(f"{path}: labels a photo that is not there: {photo}")
    boxes, words = [], []
    for i, o in enumerate(d["objects"]):
        if not isinstance(o, dict):
            raise LabelError(f"{path}: object {i} is not a JSON object")
        boxes.append(_box(o.get("box"), f"{path}: object {i}"))
        words.append((str(o.get("colour", "")), str(o.get("kind", ""))))
    ignore = d.get("ignore", [])
    if not isinstance(ignore, list):
        raise LabelError(f"{path}: ignore must be a list of boxes, got {ignore!r}")
    ignore = tuple(_box(b, f"{path}: ignore box {i}") for i, b in enumerate(ignore))
    elev = d.get("elevation_deg")
    if elev is not None and not (isinstance(elev, (int, float)) and not isinstance(elev, bool) and 0 < elev < 90):
        raise LabelError(f"{path}: elevation_deg must be a number of degrees in (0, 90), got {elev!r}")
    return LabelledPhoto(path, photo, tuple(boxes), tuple(words), None if elev is None else float(elev), ignore)


def load_labels(folder: str | Path) -> list[LabelledPhoto]:
    """Every ``*.json`` label in ``folder``, sorted by name."""
    folder = Path(folder)
    if not folder.is_dir():
        raise LabelError(f"{folder}: no such folder of photo labels")
    files = sorted(folder.glob("*.json"))
    if not files:
        raise LabelError(f"{folder}: holds no photo labels (*.json)")
    labels = [load_label(f) for f in files]
    stems = [lab.photo.stem for lab in labels]
    dup = sorted({s for s in stems if stems.count(s) > 1})
    if dup:
        raise LabelError(f"{folder}: several labels for the photo(s) {', '.join(dup)}")
    return labels


def pool_labels(folders: dict[str, str | Path], out: str | Path) -> int:
    """Copy the labelled photos of several folders into one, ``out``: each ``{prefix: folder}``'s photos go to
    ``out/photos/PREFIX_NAME`` and its labels to ``out/PREFIX_LABEL.json``, pointing at them (the photos copied, not
    linked, so the pooled folder stands alone). Every label is read first (``load_labels``: a bad folder is refused
    before anything is written). Returns the number of labelled photos pooled."""
    import json

    from prismonet.files import write_atomic

    pools = {prefix: load_labels(folder) for prefix, folder in folders.items()}
    out = Path(out)
    (out / "photos").mkdir(parents=True, exist_ok=True)
    for prefix, labels in pools.items():
        for lab in labels:
            name = f"{prefix}_{lab.photo.name}"
            write_atomic(out / "photos" / name, lab.photo.read_bytes())  # an interrupted copy never stands as a photo
            d = json.loads(lab.label_file.read_text())
            d["photo"] = f"photos/{name}"
            write_atomic(out / f"{prefix}_{lab.label_file.name}", json.dumps(d, indent=1))
    return sum(len(labels) for labels in pools.values())
