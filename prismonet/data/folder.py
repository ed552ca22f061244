"""The interchange folder format: plain PNG and JSON files that a person can write by hand.

Layout::

    DIR/
      dataset.json            {"format": "prismonet-folder", "version": 1,
                               "depth_scale": 1000.0,   # depth = png value / depth_scale
                               "camera": {"K": [[fx,0,cx],[0,fy,cy],[0,0,1]],
                                          "T_world_cam": 4x4 list, "height": H, "width": W},
                               "ground_z": 0.0}         # optional, default 0
      rgb/<name>.png          8-bit RGB (or grey) image; its file names define the scenes
      depth/<name>.png        optional folder: 16-bit depth, 0 = unknown
      instance/<name>.png     optional folder: 8-bit ids, 0 = background, k = object k
      annotations/<name>.json optional: {"objects": [{"shape_id", "category", "color",
                                          "scale", "position": [x,y,z], "yaw",
                                          "axis": [x,y,z]}], "camera": {...}}

Every object field is optional. ``category`` and ``color`` are names (``"cube"``, ``"red"``) or
ids. When ``depth/`` or ``instance/`` exists it must hold a file for every scene.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from prismonet.data.errors import DatasetError
from prismonet.data.scenes import empty_scene_arrays
from prismonet.files import write_image

FOLDER_FORMAT = "prismonet-folder"
FOLDER_VERSION = 1
DEFAULT_DEPTH_SCALE = 1000.0
"""Depth PNG units per world unit: millimetres for a metre-scale scene; 16 bits cover 65.5 units."""


def _imread(path: Path, flags: int) -> np.ndarray:
    from prismonet.files import InputError, read_image

    try:
        return read_image(path, flags)
    except InputError as e:
        raise DatasetError(str(e)) from None


def _read_json(path: Path) -> dict:
    from prismonet.files import InputError, read_json

    try:
        return read_json(path, dict)
    except InputError as e:
        raise DatasetError(f"corrupted JSON: {e}") from None


def _lookup(value, names: tuple[str, ...], what: str, path: Path) -> int:
    if isinstance(value, str):
        if value not in names:
            raise DatasetError(f"{path}: unknown {what} {value!r}; expected one of {names}")
        return names.index(value)
    return int(value)


def read_folder(root: Path) -> tuple[dict[str, np.ndarray], list[str], dict]:
    """Read a folder dataset into scene arrays. Returns ``(arrays, scene_names, dataset_json)``."""
    import cv2

    from prismonet.data.clevr import COLOR_NAMES
    from prismonet.shapes.clevr_set import CATEGORIES

    root = Path(root)
    meta_path = root / "dataset.json"
    if not meta_path.is_file():
        raise DatasetError(f"{root}: not a folder dataset (no dataset.json)")
    meta = _read_json(meta_path)
    if meta.get("format") != FOLDER_FORMAT:
        raise DatasetError(f"{meta_path}: format is {meta.get('format')!r}, expected {FOLDER_FORMAT!r}")
    if "camera" not in meta:
        raise DatasetError(f"{meta_path}: missing 'camera'")
    names = sorted(p.stem for p in (root / "rgb").glob("*.png"))
    if not names:
        raise DatasetError(f"{root}/rgb: no PNG images")
    has_depth = (root / "depth").is_dir()
    has_instance = (root / "instance").is_dir()
    if has_depth and "depth_scale" not in meta:
        raise DatasetError(f"{meta_path}: has depth/ but no 'depth_scale'")
    depth_scale = meta.get("depth_scale", DEFAULT_DEPTH_SCALE)
    if isinstance(depth_scale, bool) or not isinstance(depth_scale, (int, float)) or not math.isfinite(depth_scale) or depth_scale <= 0:
        raise DatasetError(f"{meta_path}: 'depth_scale' must be a finite positive number, got {depth_scale!r}")
    depth_scale = float(depth_scale)

    annotations = {}
    for name in names:
        path = root / "annotations" / f"{name}.json"
        annotations[name] = _read_json(path) if path.is_file() else {}
        if not isinstance(annotations[name], dict) or not isinstance(annotations[name].get("objects", []), list):
            raise DatasetError(f"{path}: expected a JSON object whose 'objects' is a list")
    max_objects = max([len(a.get("objects", [])) for a in annotations.values()] + [1])

    first = _imread(root / "rgb" / f"{names[0]}.png", cv2.IMREAD_COLOR)
    H, W = first.shape[:2]
    a = empty_scene_arrays(len(names), H, W, max_objects)
    for i, name in enumerate(names):
        rgb = _imread(root / "rgb" / f"{name}.png", cv2.IMREAD_COLOR)
        if rgb.shape[:2] != (H, W):
            raise DatasetError(f"scene {name!r}: rgb is {rgb.shape[1]}x{rgb.shape[0]}, other scenes are {W}x{H}")
        a["rgb"][i] = rgb[..., ::-1]
        for folder, key, flags in (("depth", has_depth, cv2.IMREAD_UNCHANGED), ("instance", has_instance, cv2.IMREAD_UNCHANGED)):
            if not key:
                continue
            path = root / folder / f"{name}.png"
            if not path.is_file():
                raise DatasetError(f"scene {name!r}: missing {folder}/{name}.png")
            img = _imread(path, flags)
            if img.ndim != 2:
                raise DatasetError(f"{path}: expected a single-channel image, got {img.shape[2]} channels")
            if img.shape != (H, W):
                raise DatasetError(f"scene {name!r}: {folder} is {img.shape[1]}x{img.shape[0]} but rgb is {W}x{H}")
            if folder == "depth":
                if img.dtype != np.uint16:
                    raise DatasetError(f"{path}: depth must be a 16-bit PNG, got {img.dtype}")
                a["depth"][i] = img.astype(np.float32) / depth_scale
            else:
                a["instance"][i] = img
        ann = annotations[name]
        cam = ann.get("camera", meta["camera"])
        try:
            a["K"][i] = np.asarray(cam["K"], dtype=np.float32)
            a["T_world_cam"][i] = np.asarray(cam["T_world_cam"], dtype=np.float32)
        except (KeyError, ValueError) as e:
            raise DatasetError(f"scene {name!r}: bad camera ({e!r}); need 'K' (3x3) and 'T_world_cam' (4x4)") from None
        if (int(cam.get("height", H)), int(cam.get("width", W))) != (H, W):
            raise DatasetError(f"scene {name!r}: camera is {cam.get('width')}x{cam.get('height')} but rgb is {W}x{H}")
        a["ground_z"][i] = float(ann.get("ground_z", meta.get("ground_z", 0.0)))
        a["ground_color"][i] = ann.get("ground_color", [0, 0, 0])
        objects = ann.get("objects", [])
        a["obj_count"][i] = len(objects)
        ann_path = root / "annotations" / f"{name}.json"
        for k, obj in enumerate(objects):
            a["obj_shape"][i, k] = int(obj.get("shape_id", -1))
            if "category" in obj:
                a["obj_category"][i, k] = _lookup(obj["category"], CATEGORIES, "category", ann_path)
            if "color" in obj:
                a["obj_color"][i, k] = _lookup(obj["color"], COLOR_NAMES, "color", ann_path)
            a["obj_scale"][i, k] = float(obj.get("scale", 0.0))
            a["obj_position"][i, k] = obj.get("position", [0.0, 0.0, 0.0])
            a["obj_yaw"][i, k] = float(obj.get("yaw", 0.0))
            a["obj_axis"][i, k] = obj.get("axis", [0.0, 0.0, 1.0])
    return a, names, meta


def write_folder(root: Path, arrays: dict[str, np.ndarray], depth_scale: float = DEFAULT_DEPTH_SCALE) -> None:
    """Write scene arrays (e.g. a slice of a packed split) in the folder format.

    The camera of the first scene becomes the default in ``dataset.json``; every scene's
    annotation also carries its own camera, so per-scene cameras survive the round trip.
    """
    from prismonet.data.clevr import COLOR_NAMES
    from prismonet.shapes.clevr_set import CATEGORIES

    root = Path(root)
    for sub in ("rgb", "depth", "instance", "annotations"):
        (root / sub).mkdir(parents=True, exist_ok=True)
    n, H, W = arrays["rgb"].shape[:3]
    max_depth = np.iinfo(np.uint16).max / depth_scale
    if float(np.max(arrays["depth"], initial=0.0)) > max_depth:
        raise ValueError(f"depth exceeds {max_depth:.2f}, the largest value a 16-bit PNG holds at depth_scale={depth_scale}")

    def camera(i):
        return {"K": arrays["K"][i].tolist(), "T_world_cam": arrays["T_world_cam"][i].tolist(), "height": H, "width": W}

    width = max(4, len(str(n - 1)))
    for i in range(n):
        name = f"{i:0{width}d}"
        write_image(root / "rgb" / f"{name}.png", arrays["rgb"][i][..., ::-1])
        depth = np.rint(np.asarray(arrays["depth"][i], dtype=np.float64) * depth_scale).astype(np.uint16)
        write_image(root / "depth" / f"{name}.png", depth)
        write_image(root / "instance" / f"{name}.png", arrays["instance"][i])
        objects = []
        for k in range(int(arrays["obj_count"][i])):
            cat, col = int(arrays["obj_category"][i, k]), int(arrays["obj_color"][i, k])
            obj = {
                "shape_id": int(arrays["obj_shape"][i, k]),
                "scale": float(arrays["obj_scale"][i, k]),
                "position": arrays["obj_position"][i, k].tolist(),
                "yaw": float(arrays["obj_yaw"][i, k]),
                "axis": arrays["obj_axis"][i, k].tolist(),
            }
            if cat >= 0:
                obj["category"] = CATEGORIES[cat]
            if col >= 0:
                obj["color"] = COLOR_NAMES[col]
            objects.append(obj)
        ann = {
            "objects": objects,
            "camera": camera(i),
            "ground_z": float(arrays["ground_z"][i]),
            "ground_color": arrays["ground_color"][i].tolist(),
        }
        (root / "annotations" / f"{name}.json").write_text(json.dumps(ann, indent=1))
    meta = {"format": FOLDER_FORMAT, "version": FOLDER_VERSION, "depth_scale": depth_scale, "camera": camera(0)}
    (root / "dataset.json").write_text(json.dumps(meta, indent=2))
