"""``prismonet real prepare``: photos -> a folder dataset the model reads (RGB + camera)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch

from prismonet.files import write_image
from realdata.color import (HIGHLIGHT_PERCENTILE, MAX_GAIN, MAX_TINT, ColorMapping, estimate_table_color, mapping_limited,
                            spare_highlights, table_mapping)
from realdata.gray_tint import TINTS, is_gray_view, tint_gray
from realdata.illumination import flatten_light
from realdata.io import PhotoError, load_photo
from realdata.prepare import auto_table_box, check_box, crop, resize, table_region, undistort

DEFAULT_TARGET = (150, 150, 150)
"""The synthetic ground colour (ClevrConfig.ground_color)."""


def prepare_photos(photos: list[str | Path], out: str | Path, size: int = 64, calibration: str | Path | None = None,
                   box: tuple[int, int, int, int] | None = None, normalize: str = "auto",
                   gain: tuple[float, float, float] | None = None, target=DEFAULT_TARGET,
                   view=None, metres_per_unit: float | None = None, own_camera: bool = False,
                   tiling=None, highlights: float | None = HIGHLIGHT_PERCENTILE, gray_tint: str = "off") -> list[dict]:
    """Prepare photos into ``out`` (folder format, no depth). Returns one record per prepared image: per photo,
    or with ``tiles`` > 1 per tile.

    Args:
        calibration: FileStorage YAML from ``prismonet calibrate``; undistorts, and gives K. With a
            ground pose (``calibrate ground``), each photo is rectified to ``view`` through the table
            plane (``realdata.rectify``) with the world map of ``realdata.world`` (recorded per photo),
            and takes ``view``'s camera; without one, it is cropped and resized.
        box: crop ``(x0, y0, w, h)``; default: automatic, around the table region (not with a ground pose).
        normalize: ``"auto"`` (table colour -> ``target``; where the gain would clip the photo's bright end, the
            brightness above the table's is compressed instead, ``realdata.color.spare_highlights``), ``"flat"`` (the
            table's uneven light divided out first, ``realdata.illumination``, then as ``"auto"``), ``"none"``, or
            ``"manual"`` with ``gain`` (a plain gain).
        highlights: with ``"auto"`` or ``"flat"``, the percentile of the photo's brightness that the tone curve
            lands on 1 (``realdata.color.spare_highlights``); None: the plain gain, which clips.
        view: ``(Camera, ground_z)`` to rectify to, in model units (default: the CLEVR camera at ``size``).
        metres_per_unit: the world scale; default: derived from the camera distances (``WorldMapping.derive``).
        own_camera: with a ground pose, keep the photo's own camera instead of rectifying (for camera-frame
            models, ``pose_frame = "camera"``): the photo is cropped to a square around ``view``'s footprint
            on the table and resized, and takes the calibrated camera, mapped into the model's world.
        tiling: a ``realdata.tiles.TileConfig``, uncalibrated photos only: read the table region (or ``box``)
            as overlapping square tiles, each prepared as its own image named ``STEM_tNN``, with the colour
            mapping read off the whole region or off each tile; with ``tiling.tiles`` under 1, one view that many
            times as wide instead, zoomed out (``_zoomed_out``).
        gray_tint: ``"off"``, or for a greyscale photo a hue for what is lighter than its table (``"light"``) and also
            for what is darker (``"both"``), after the colour mapping (``realdata.gray_tint``); colour photos are
            unchanged.
    """
    from prismonet.data.folder import FOLDER_FORMAT, FOLDER_VERSION

    if normalize not in ("auto", "flat", "none", "manual"):
        raise ValueError(f"normalize: expected auto, flat, none or manual, got {normalize!r}")
    if normalize == "manual" and gain is None:
        raise ValueError("normalize=manual needs a gain (r,g,b)")
    if gray_tint not in TINTS:
        raise ValueError(f"gray_tint: expected {', '.join(TINTS)}, got {gray_tint!r}")
    tiles = 1 if tiling is None else tiling.tiles
    if (tiles != 1 or (tiling is not None and (tiling.target_px or tiling.zoom_out))) and calibration is not None:
        raise ValueError("--tiles reads uncalibrated photos (each tile is seen by the training camera); a calibrated photo "
                         "is rectified to the model's view as a whole")
    stems = [Path(p).stem for p in photos]
    dup = sorted({s for s in stems if stems.count(s) > 1})
    if dup:
        raise ValueError(f"photos with the same file name would overwrite each other: {', '.join(dup)}")
    cal, T = None, None
    if calibration is not None:
        from calibration.storage import load_calibration

        cal, T = load_calibration(calibration)
    if T is not None and box is not None:
        raise ValueError("--box crops an uncalibrated photo; with a ground pose the photo is rectified to the model's view instead")
    if T is not None and view is None:
        from prismonet.data.clevr import ClevrConfig, clevr_camera

        view = (clevr_camera(ClevrConfig(image_size=size)), 0.0)
    out = Path(out)
    (out / "rgb").mkdir(parents=True, exist_ok=True)
    (out / "annotations").mkdir(exist_ok=True)
    records, first_cam = [], None
    for p in photos:
        img = raw = load_photo(p)
        flat = None
        if normalize == "flat":
            img, field = flatten_light(img)
            flat = {"field_min": float(field.min()), "field_max": float(field.max())}
        if tiles > 1:
            parts = _tiled(p, img, box, size, tiling, normalize, gain, target, highlights)
        elif tiles < 1:
            parts = _zoomed_out(p, raw, img, box, size, 1 / tiles, normalize, gain, target, highlights)
        else:
            if T is not None and own_camera:
                view_img, cam, placed = _own_camera(p, img, cal, T, view, size, metres_per_unit)
            elif T is not None:
                view_img, cam, placed = _rectified(p, img, cal, T, view, size, metres_per_unit)
            else:
                view_img, cam, placed = _cropped(p, img, cal, box, size)
            parts = [(Path(p).stem, view_img, cam, placed, _color_mapping(view_img, normalize, gain, target, highlights))]
        for name, view_img, cam, placed, (mapping, note) in parts:
            if note:
                placed["warnings"] = [*placed.get("warnings", []), note]
            view_img = mapping.apply(view_img)
            if gray_tint != "off" and is_gray_view(view_img):
                view_img, placed["gray_tint"] = tint_gray(view_img, gray_tint), gray_tint
            write_image(out / "rgb" / f"{name}.png", (np.clip(view_img, 0, 1)[..., ::-1] * 255).round().astype(np.uint8))
            if flat is not None:
                placed["light_field"] = flat
            record = {"photo": str(p), "name": name, **placed, "color_mapping": mapping.to_dict(), "camera": cam.to_dict(), "undistorted": cal is not None,
                      "calibration": None if calibration is None else str(calibration)}
            (out / "annotations" / f"{name}.json").write_text(json.dumps({"camera": cam.to_dict(), "prepare": record}, indent=1))
            records.append(record)
            first_cam = first_cam or cam
    (out / "dataset.json").write_text(json.dumps({"format": FOLDER_FORMAT, "version": FOLDER_VERSION, "camera": first_cam.to_dict(),
                                                  "source": "prismonet real prepare"}, indent=2))
    return records


def _check_size(p, cal, img) -> None:
    H, W = img.shape[:2]
    if cal is not None and (W, H) != tuple(cal.image_size):
        raise ValueError(f"{p}: is {W}x{H} but the calibration is for {cal.image_size[0]}x{cal.image_size[1]}")


def _cropped(p, img, cal, box, size):
    """Undistort (with a calibration), crop and resize: ``(image, camera, record fields)``."""
    from prismonet.geometry.camera import Camera, intrinsics_matrix

    _check_size(p, cal, img)
    H, W = img.shape[:2]
    if cal is not None:
        img = undistort(img, cal.K, cal.dist)
        K = torch.tensor(cal.K, dtype=torch.float32)
    else:
        K = intrinsics_matrix(float(W), float(W), (W - 1) / 2, (H - 1) / 2)
    b = box if box is not None else auto_table_box(img, min_side=size)
    img, cam = crop(img, Camera(K, torch.eye(4), H, W), b)
    if min(img.shape[:2]) < size:
        raise PhotoError(f"{p}: the crop is {img.shape[1]}x{img.shape[0]} px, smaller than the {size}x{size} model input; "
                         "use a larger photo or crop (upscaling would invent the detail the model reads)")
    img, cam = resize(img, cam, size)
    x0, y0, w, h = (int(v) for v in b)
    outline = [[x0 - 0.5, y0 - 0.5], [x0 + w - 0.5, y0 - 0.5], [x0 + w - 0.5, y0 + h - 0.5], [x0 - 0.5, y0 + h - 0.5]]
    return img, cam, {"crop_box": [x0, y0, w, h], "outline": outline}


def _tiled(p, img, box, size, tiling, normalize, gain, target, highlights) -> list:
    """The tiles of an uncalibrated photo: ``[(name, image, camera, record fields, (mapping, note))]``, the colour
    mapping read once off the whole region (``tiling.color`` "region") or off each tile ("tile")."""
    from realdata.tiles import inner_edges, tile_boxes

    if box is not None:
        region = tuple(int(v) for v in box)
    else:  # the table's bounding box, grown to hold the square a whole-photo reading would crop
        tx, ty, tw, th = table_region(img)
        sx, sy, side, _ = auto_table_box(img, min_side=size, region=(tx, ty, tw, th))
        rx, ry = min(tx, sx), min(ty, sy)
        region = (rx, ry, max(tx + tw, sx + side) - rx, max(ty + th, sy + side) - ry)
    x0, y0, w, h = check_box(region, img.shape, str(p))
    mapping = _color_mapping(img[y0 : y0 + h, x0 : x0 + w], normalize, gain, target, highlights)
    tiles, overlap, n = tiling.tiles, tiling.overlap, tiling.tiles
    while n > 1 and tile_boxes(region, n, overlap)[0][2] < size:
        n = max(1, n - 1)  # no tile smaller than the model's input (upscaling would invent the detail the model reads)
    note = [] if n == tiles else [f"read as {n:g} tile{'s' if n > 1 else ''} across, not {tiles:g}: the region ({w}x{h} px) "
                                  f"holds no more tiles of at least {size} px"]
    parts = []
    for t, tb in enumerate(tile_boxes(region, n, overlap)):
        view_img, cam, placed = _cropped(p, img, None, tb, size)
        placed.update(tile=t, tiles=n, warnings=note, tile_overlap=overlap, region=list(region), inner_edges=list(inner_edges(tb, region)))
        own = _color_mapping(view_img, normalize, gain, target, highlights) if tiling.color == "tile" else mapping
        parts.append((f"{Path(p).stem}_t{t:02d}", view_img, cam, placed, own))
    return parts


def _zoomed_out(p, raw, img, box, size, zoom, normalize, gain, target, highlights) -> list:
    """An uncalibrated photo's whole view zoomed out ``zoom`` times: a square ``zoom`` times as wide on the same centre
    (the whole view as ``img``, the photo as prepared so far, gives it), cut from the unprocessed photo ``raw`` with the
    part beyond it filled with the median colour of the whole view's border (in a close-up the table shows mostly
    there), then flattened (``normalize`` "flat") and colour-mapped as one photo, so that the fill and the table get one
    colour; resized to ``size``. Returns ``[(name, image, camera, record fields, (mapping, note))]`` as ``_tiled``."""
    from prismonet.geometry.camera import Camera, intrinsics_matrix

    H, W = img.shape[:2]
    x0, y0, w, h = check_box(box if box is not None else auto_table_box(img, min_side=size), img.shape, str(p))
    big = int(round(max(w, h) * zoom))
    bx, by = x0 + w // 2 - big // 2, y0 + h // 2 - big // 2
    sq = raw[y0 : y0 + h, x0 : x0 + w]
    view = np.empty((big, big, 3), raw.dtype)
    view[:] = np.median(np.concatenate([sq[0], sq[-1], sq[:, 0], sq[:, -1]]), axis=0)
    sx0, sy0, sx1, sy1 = max(bx, 0), max(by, 0), min(bx + big, W), min(by + big, H)
    view[sy0 - by : sy1 - by, sx0 - bx : sx1 - bx] = raw[sy0:sy1, sx0:sx1]
    if normalize == "flat":
        view, _ = flatten_light(view)
    K = intrinsics_matrix(float(W), float(W), (W - 1) / 2, (H - 1) / 2)
    view, cam = resize(view, Camera(K, torch.eye(4), H, W).cropped(bx, by, big, big), size)
    outline = [[bx - 0.5, by - 0.5], [bx + big - 0.5, by - 0.5], [bx + big - 0.5, by + big - 0.5], [bx - 0.5, by + big - 0.5]]
    placed = {"crop_box": [bx, by, big, big], "outline": outline, "zoom_out": zoom, "warnings": []}
    return [(Path(p).stem, view, cam, placed, _color_mapping(view, normalize, gain, target, highlights))]


def _photo_in_model(p, img, cal, T, view, size, metres_per_unit):
    """What both calibrated paths share: the undistorted photo, the world map, the photo camera in the model's
    world, the view's camera, and the view's footprint on the table in photo pixels ``(4, 2)``."""
    from realdata.rectify import rectifying_homography
    from realdata.world import WorldMapping

    _check_size(p, cal, img)
    cam, ground_z = view
    cam = cam.resized(size, size)
    K_view, T_view = cam.K.double().numpy(), cam.T_world_cam.double().numpy()
    world = WorldMapping.derive(T, T_view, ground_z, metres_per_unit)
    img = undistort(img, cal.K, cal.dist)
    T_photo = world.camera_in_model(T)
    corners = np.array([[-0.5, -0.5, 1], [size - 0.5, -0.5, 1], [size - 0.5, size - 0.5, 1], [-0.5, size - 0.5, 1]])
    q = corners @ np.linalg.inv(rectifying_homography(cal.K, T_photo, K_view, T_view, ground_z)).T
    return img, world, T_photo, cam, ground_z, q[:, :2] / q[:, 2:]


def _rectified(p, img, cal, T, view, size, metres_per_unit):
    """Undistort and rectify to ``view`` through the table: ``(image, camera, record fields)``."""
    from realdata.rectify import MIN_COVERAGE, WARN_COVERAGE, rectify
    from realdata.world import camera_warnings

    img, world, T_photo, cam, ground_z, footprint = _photo_in_model(p, img, cal, T, view, size, metres_per_unit)
    K_view, T_view = cam.K.double().numpy(), cam.T_world_cam.double().numpy()
    img, coverage = rectify(img, cal.K, T_photo, K_view, T_view, ground_z, size)
    outline = footprint.tolist()  # the view's footprint in (undistorted) photo pixels
    if coverage < MIN_COVERAGE:
        raise PhotoError(f"{p}: the photo covers {coverage:.0%} of the model's view of the table (at least {MIN_COVERAGE:.0%} needed): "
                         "aim the camera at the objects, or state a smaller --unit")
    warnings = camera_warnings(world)
    if coverage < WARN_COVERAGE:
        warnings.append(f"the photo covers {coverage:.0%} of the model's view of the table; the rest is filled with the table colour")
    return img, cam, {"rectified": True, "world": world.to_dict(), "coverage": coverage, "outline": outline, "warnings": warnings}


def _own_camera(p, img, cal, T, view, size, metres_per_unit):
    """Undistort, crop a square around ``view``'s footprint on the table and resize, keeping the photo's
    calibrated camera (in the model's world): ``(image, camera, record fields)``."""
    from prismonet.geometry.camera import Camera
    from realdata.world import camera_warnings

    img, world, T_photo, _, _, q = _photo_in_model(p, img, cal, T, view, size, metres_per_unit)
    H, W = img.shape[:2]
    side = int(min(max(np.ptp(q[:, 0]), np.ptp(q[:, 1])), W, H))
    cx, cy = q.mean(0)
    x0 = int(np.clip(round(cx - side / 2), 0, W - side))
    y0 = int(np.clip(round(cy - side / 2), 0, H - side))
    cam = Camera(torch.tensor(cal.K, dtype=torch.float32), torch.tensor(T_photo, dtype=torch.float32), H, W)
    img, cam = crop(img, cam, (x0, y0, side, side))
    if side < size:
        raise PhotoError(f"{p}: the crop is {side}x{side} px, smaller than the {size}x{size} model input; "
                         "use a larger photo (upscaling would invent the detail the model reads)")
    img, cam = resize(img, cam, size)
    outline = [[x0 - 0.5, y0 - 0.5], [x0 + side - 0.5, y0 - 0.5], [x0 + side - 0.5, y0 + side - 0.5], [x0 - 0.5, y0 + side - 0.5]]
    return img, cam, {"own_camera": True, "world": world.to_dict(), "crop_box": [x0, y0, side, side], "outline": outline,
                      "warnings": camera_warnings(world)}


def _color_mapping(img, normalize, gain, target, highlights=HIGHLIGHT_PERCENTILE) -> tuple[ColorMapping, str | None]:
    """The mapping, and a warning when the automatic one could not reach the target within its limits."""
    if normalize in ("auto", "flat"):
        table, goal = estimate_table_color(img), np.asarray(target) / 255.0
        m = table_mapping(table, goal)
        limited = mapping_limited(table, goal, m)
        m = spare_highlights(m, table, img, highlights)
        if limited:
            return m, (f"the table colour read off the photo, RGB ({', '.join(f'{255 * v:.0f}' for v in table)}), is too far from "
                       f"the training ground's to map onto it (gain limited to {MAX_GAIN:g}x, tint to {MAX_TINT:g}x); "
                       "check --box, or pass --normalize manual --gain r,g,b")
        return m, None
    if normalize == "manual":
        return ColorMapping(tuple(gain), (0.0, 0.0, 0.0)), None
    return ColorMapping((1.0, 1.0, 1.0), (0.0, 0.0, 0.0)), None
