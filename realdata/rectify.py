"""Rectify a calibrated photo to the model's training view through the ground plane.

A point ``(X, Y)`` of the ground ``z = ground_z`` projects into a camera ``(K, T_world_cam)`` by the
homography ``G = K [R^T e1 | R^T e2 | R^T (ground_z e3 - c)]``; the photo pixel of a ground point
therefore maps to its training-view pixel by ``H = G_train G_photo^-1``. The warp is exact on the
table, and for every point when both cameras share a centre (``realdata.world``); the photo must be
undistorted first.
"""

from __future__ import annotations

import math

import numpy as np

MIN_COVERAGE = 0.5
"""Refuse a rectified view less than this fraction of which the photo covers."""
WARN_COVERAGE = 0.95
"""Warn below this coverage (the rest is filled from the nearest photo pixels)."""


def ground_homography(K: np.ndarray, T_world_cam: np.ndarray, ground_z: float) -> np.ndarray:
    """``(3, 3)`` map from ground coordinates ``(X, Y, 1)`` to pixels of the camera."""
    T = np.asarray(T_world_cam, np.float64)
    Rt = T[:3, :3].T
    c = T[:3, 3]
    return np.asarray(K, np.float64) @ np.column_stack([Rt[:, 0], Rt[:, 1], Rt @ (np.array([0.0, 0.0, ground_z]) - c)])


def rectifying_homography(K_photo, T_photo, K_train, T_train, ground_z: float) -> np.ndarray:
    """``(3, 3)`` map from photo pixels to training-view pixels (both cameras in the model's world)."""
    H = ground_homography(K_train, T_train, ground_z) @ np.linalg.inv(ground_homography(K_photo, T_photo, ground_z))
    return H / H[2, 2]


def supersampled_K(K: np.ndarray, factor: int) -> np.ndarray:
    """Intrinsics of the same camera at ``factor`` times the resolution (pixel centres at integers)."""
    S = np.diag([factor, factor, 1.0])
    S[0, 2] = S[1, 2] = (factor - 1) / 2.0
    return S @ np.asarray(K, np.float64)


def photo_footprint(K_photo, T_photo, K_view, T_view, ground_z: float, size: int, photo_hw: tuple[int, int]) -> np.ndarray:
    """``(size, size)`` bool: view pixels whose ground point lies in front of the photo camera and
    inside the photo (a homography alone would also map points behind the camera into the photo)."""
    h, w = photo_hw
    u, v = np.meshgrid(np.arange(size, dtype=np.float64), np.arange(size, dtype=np.float64))
    pix = np.stack([u.ravel(), v.ravel(), np.ones(u.size)])
    ground = np.linalg.solve(ground_homography(K_view, T_view, ground_z), pix)
    X, Y = ground[0] / ground[2], ground[1] / ground[2]
    T = np.asarray(T_photo, np.float64)
    x_cam = T[:3, :3].T @ (np.stack([X, Y, np.full_like(X, ground_z)]) - T[:3, 3:4])
    z = x_cam[2]
    with np.errstate(divide="ignore", invalid="ignore"):
        q = np.asarray(K_photo, np.float64) @ x_cam
        pu, pv = q[0] / q[2], q[1] / q[2]
        ok = (z > 0) & (pu >= -0.5) & (pu <= w - 0.5) & (pv >= -0.5) & (pv <= h - 0.5)
    return ok.reshape(size, size)


def rectify(image: np.ndarray, K_photo, T_photo, K_train, T_train, ground_z: float, size: int) -> tuple[np.ndarray, float]:
    """``(view (size, size, C), coverage)``: the undistorted photo as the training camera would see
    the table, rendered at a resolution at least the photo's and area-averaged down to ``size``
    (no aliasing). ``coverage`` is the fraction of the view the photo covers; the rest is filled
    with the median colour of the covered part."""
    import cv2

    h, w = image.shape[:2]
    factor = int(min(16, max(2, math.ceil(max(h, w) / size))))
    K_big = supersampled_K(K_train, factor)
    H = rectifying_homography(K_photo, T_photo, K_big, T_train, ground_z)
    big = size * factor
    view = cv2.warpPerspective(image.astype(np.float32), H, (big, big), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    ok = photo_footprint(K_photo, T_photo, K_big, T_train, ground_z, big, (h, w))
    if ok.any() and not ok.all():
        view[~ok] = np.median(view[ok], axis=0)
    view = cv2.resize(view, (size, size), interpolation=cv2.INTER_AREA)
    return view, float(ok.mean())


def rectify_labels(labels: np.ndarray, K_photo, T_photo, K_train, T_train, ground_z: float, size: int) -> np.ndarray:
    """An integer image (instance ids) of the photo warped to the training view like ``rectify``
    (nearest neighbour, no averaging; 0 outside the photo), so ground truth stays consistent with the
    rectified colours."""
    import cv2

    H = rectifying_homography(K_photo, T_photo, K_train, T_train, ground_z)
    out = cv2.warpPerspective(labels.astype(np.uint8), H, (size, size), flags=cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    out[~photo_footprint(K_photo, T_photo, K_train, T_train, ground_z, size, labels.shape[:2])] = 0
    return out
