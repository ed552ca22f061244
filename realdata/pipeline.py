"""``prismonet real prepare``: photos -> a folder dataset the model reads (RGB + camera)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch

from prismonet.files import write_image
from realdata.color import ColorMapping, estimate_table_color, table_mapping
from realdata.io import PhotoError, load_photo
from realdata.prepare import auto_table_box, crop, resize, undistort

DEFAULT_TARGET = (150, 150, 150)
"""The synthetic ground colour (ClevrConfig.ground_color)."""


def prepare_photos(photos: list[str | Path], out: str | Path, size: int = 64, calibration: str | Path | None = None,
                   box: tuple[int, int, int, int] | None = None, normalize: str = "auto",
                   gain: tuple[float, float, float] | None = None, target=DEFAULT_TARGET) -> list[dict]:
    """Prepare photos into ``out`` (folder format, no depth). Returns one record per photo.

    Args:
        calibration: FileStorage YAML from ``prismonet calibrate``; undistorts, and gives K and,
            if it has one, ``T_world_cam``. Without it, a nominal camera (fx = image width) is used.
        box: crop ``(x0, y0, w, h)``; default: automatic, around the table region.
        normalize: ``"auto"`` (table colour -> ``target``), ``"none"``, or ``"manual"`` with ``gain``.
    """
    from prismonet.data.folder import FOLDER_FORMAT, FOLDER_VERSION
    from prismonet.geometry.camera import Camera, intrinsics_matrix

    if normalize not in ("auto", "none", "manual"):
        raise ValueError(f"normalize: expected auto, none or manual, got {normalize!r}")
    if normalize == "manual" and gain is None:
        raise ValueError("normalize=manual needs a gain (r,g,b)")
    stems = [Path(p).stem for p in photos]
    dup = sorted({s for s in stems if stems.count(s) > 1})
    if dup:
        raise ValueError(f"photos with the same file name would overwrite each other: {', '.join(dup)}")
    out = Path(out)
    (out / "rgb").mkdir(parents=True, exist_ok=True)
    (out / "annotations").mkdir(exist_ok=True)
    cal, T = None, None
    if calibration is not None:
        from calibration.storage import load_calibration

        cal, T = load_calibration(calibration)
    records, first_cam = [], None
    for p in photos:
        img = load_photo(p)
        H, W = img.shape[:2]
        if cal is not None:
            if (W, H) != tuple(cal.image_size):
                raise ValueError(f"{p}: is {W}x{H} but the calibration is for {cal.image_size[0]}x{cal.image_size[1]}")
            img = undistort(img, cal.K, cal.dist)
            K = torch.tensor(cal.K, dtype=torch.float32)
        else:
            K = intrinsics_matrix(float(W), float(W), (W - 1) / 2, (H - 1) / 2)
        T_world_cam = torch.eye(4) if T is None else torch.tensor(T, dtype=torch.float32)
        cam = Camera(K, T_world_cam, H, W)
        b = box if box is not None else auto_table_box(img)
        img, cam = crop(img, cam, b)
        if min(img.shape[:2]) < size:
            raise PhotoError(f"{p}: the crop is {img.shape[1]}x{img.shape[0]} px, smaller than the {size}x{size} model input; "
                             "use a larger photo or crop (upscaling would invent the detail the model reads)")
        img, cam = resize(img, cam, size)
        if normalize == "auto":
            mapping = table_mapping(estimate_table_color(img), np.asarray(target) / 255.0)
        elif normalize == "manual":
            mapping = ColorMapping(tuple(gain), (0.0, 0.0, 0.0))
        else:
            mapping = ColorMapping((1.0, 1.0, 1.0), (0.0, 0.0, 0.0))
        img = mapping.apply(img)
        name = Path(p).stem
        write_image(out / "rgb" / f"{name}.png", (np.clip(img, 0, 1)[..., ::-1] * 255).round().astype(np.uint8))
        record = {"photo": str(p), "crop_box": list(map(int, b)), "color_mapping": mapping.to_dict(), "camera": cam.to_dict(),
                  "undistorted": cal is not None}
        (out / "annotations" / f"{name}.json").write_text(json.dumps({"camera": cam.to_dict(), "prepare": record}, indent=1))
        records.append(record)
        first_cam = first_cam or cam
    (out / "dataset.json").write_text(json.dumps({"format": FOLDER_FORMAT, "version": FOLDER_VERSION, "camera": first_cam.to_dict(),
                                                  "source": "prismonet real prepare"}, indent=2))
    return records
