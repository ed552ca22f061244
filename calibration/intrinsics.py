"""Intrinsics and distortion from photos of a chessboard (cv2.calibrateCamera)."""

from __future__ import annotations

import warnings

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from calibration.board import Chessboard

MIN_VIEWS = 3
"""Fewer detected boards than this cannot constrain the intrinsics."""


class BoardNotFoundWarning(UserWarning):
    """A calibration photo in which the board was not found (the photo is skipped)."""


class CalibrationError(ValueError):
    """Calibration impossible: unreadable photos, too few boards found, mixed image sizes."""


@dataclass
class Calibration:
    """Pinhole intrinsics ``K`` (3x3), distortion ``dist`` (OpenCV's k1 k2 p1 p2 k3), image size
    ``(width, height)``, RMS reprojection error in pixels, and per-photo detection results."""

    K: np.ndarray
    dist: np.ndarray
    image_size: tuple[int, int]
    rms: float
    per_image: list[dict] = field(default_factory=list)


def calibrate_images(images: list[np.ndarray], board, names: list[str] | None = None,
                     fix_aspect_ratio: bool = False) -> Calibration:
    """Calibrate from greyscale or colour images of one camera; ``board``: ``Chessboard`` or ``Charuco``."""
    import cv2

    names = names or [f"image {i}" for i in range(len(images))]
    obj, img, per_image, size = [], [], [], None
    label = f"{board.cols}x{board.rows} board" if isinstance(board, Chessboard) else f"{board.squares_x}x{board.squares_y} ChArUco board"
    for name, im in zip(names, images):
        gray = cv2.cvtColor(im, cv2.COLOR_BGR2GRAY) if im.ndim == 3 else im
        if size is None:
            size = (gray.shape[1], gray.shape[0])
        elif (gray.shape[1], gray.shape[0]) != size:
            raise CalibrationError(f"{name}: is {gray.shape[1]}x{gray.shape[0]}, other photos are {size[0]}x{size[1]}")
        found = board.detect(gray)
        per_image.append({"image": name, "found": found is not None})
        if found is None:
            warnings.warn(f"{name}: the {label} was not found; skipping this photo", BoardNotFoundWarning, stacklevel=2)
        else:
            obj.append(found[0])
            img.append(found[1])
    if len(obj) < MIN_VIEWS:
        raise CalibrationError(f"the {label} was found in {len(obj)} of {len(images)} photos; need at least {MIN_VIEWS}")
    flags = cv2.CALIB_FIX_ASPECT_RATIO if fix_aspect_ratio else 0
    K0 = np.eye(3)
    rms, K, dist, rvecs, tvecs = cv2.calibrateCamera(obj, img, size, K0, None, flags=flags)
    j = 0
    for entry in per_image:
        if entry["found"]:
            proj, _ = cv2.projectPoints(obj[j], rvecs[j], tvecs[j], K, dist)
            entry["rms_px"] = float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - img[j]) ** 2, axis=-1))))
            j += 1
    return Calibration(K, dist.reshape(-1), size, float(rms), per_image)


def calibrate_folder(paths: list[str | Path], board, fix_aspect_ratio: bool = False) -> Calibration:
    """Calibrate from photo files (any format OpenCV reads)."""
    import cv2

    if not paths:
        raise CalibrationError("no photos given")
    from prismonet.files import InputError, read_image

    images = []
    for p in paths:
        try:
            images.append(read_image(p, cv2.IMREAD_GRAYSCALE))
        except InputError as e:
            raise CalibrationError(str(e)) from None
    return calibrate_images(images, board, [str(p) for p in paths], fix_aspect_ratio)
