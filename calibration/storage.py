"""Calibrations in OpenCV's FileStorage YAML (readable by OpenCV's own tools), and conversion to
the project's kornia-backed ``prismonet.geometry.Camera``."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from calibration.intrinsics import Calibration, CalibrationError


def save_calibration(cal: Calibration, path: str | Path, T_world_cam: np.ndarray | None = None) -> Path:
    """Write ``camera_matrix``, ``distortion_coefficients``, ``image_width/height``,
    ``avg_reprojection_error`` (OpenCV's sample names), and optionally ``T_world_cam``."""
    import cv2

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.tmp{path.suffix}")
    fs = cv2.FileStorage(str(tmp), cv2.FILE_STORAGE_WRITE)
    fs.write("image_width", int(cal.image_size[0]))
    fs.write("image_height", int(cal.image_size[1]))
    fs.write("camera_matrix", np.asarray(cal.K, np.float64))
    fs.write("distortion_coefficients", np.asarray(cal.dist, np.float64).reshape(-1, 1))
    fs.write("avg_reprojection_error", float(cal.rms))
    if T_world_cam is not None:
        fs.write("T_world_cam", np.asarray(T_world_cam, np.float64))
    fs.release()
    tmp.replace(path)
    return path


def load_calibration(path: str | Path) -> tuple[Calibration, np.ndarray | None]:
    """Read a FileStorage YAML (ours or OpenCV's sample format): ``(calibration, T_world_cam or None)``."""
    import cv2

    path = Path(path)
    if not path.is_file():
        raise CalibrationError(f"{path}: no such calibration file")
    try:  # OpenCV's parser raises cv2.error or SystemError on truncated or garbage files
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
        if not fs.isOpened():
            raise CalibrationError(f"{path}: not a readable OpenCV FileStorage file")
        K = fs.getNode("camera_matrix").mat()
        dist = fs.getNode("distortion_coefficients").mat()
        w, h = int(fs.getNode("image_width").real()), int(fs.getNode("image_height").real())
        rms = fs.getNode("avg_reprojection_error").real()
        T = fs.getNode("T_world_cam").mat()
        fs.release()
    except (cv2.error, SystemError):
        raise CalibrationError(f"{path}: not a readable OpenCV FileStorage file (truncated, or not OpenCV YAML/XML)") from None
    if K is None or K.shape != (3, 3) or not np.isfinite(K).all() or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise CalibrationError(f"{path}: missing or malformed camera_matrix")
    if w <= 0 or h <= 0:
        raise CalibrationError(f"{path}: missing or non-positive image_width / image_height")
    if T is not None and (T.shape != (4, 4) or not np.isfinite(T).all() or abs(np.linalg.det(T[:3, :3]) - 1) > 1e-3):
        raise CalibrationError(f"{path}: T_world_cam must be a finite 4x4 rigid transform")
    dist = np.zeros(5) if dist is None else dist.reshape(-1)
    return Calibration(K, dist, (w, h), float(rms)), T


def to_camera(cal: Calibration, T_world_cam: np.ndarray | None = None):
    """The calibration as a ``prismonet.geometry.Camera`` (distortion must be removed first:
    undistort the images, see ``realdata``)."""
    import torch

    from prismonet.geometry.camera import Camera

    T = np.eye(4) if T_world_cam is None else np.asarray(T_world_cam)
    return Camera(torch.tensor(cal.K, dtype=torch.float32), torch.tensor(T, dtype=torch.float32), cal.image_size[1], cal.image_size[0])
