"""The ground plane: ``T_world_cam`` from one photo of a board lying on the table (cv2.solvePnP).

The world is the project's: z up, the table at z = 0. The board frame has z = x cross y pointing
into the table when the board is seen from above (OpenCV's x along the columns, y along the
rows), so ``T_world_board`` turns it over: a half turn about the board's x axis, placing the
world origin at the board's first inner corner.
"""

from __future__ import annotations

import numpy as np

from calibration.intrinsics import CalibrationError

T_WORLD_BOARD = np.diag([1.0, -1.0, -1.0, 1.0])
"""Board frame -> z-up world frame (half turn about x)."""


def ground_pose(image: np.ndarray, K: np.ndarray, dist: np.ndarray, board) -> tuple[np.ndarray, float]:
    """``(T_world_cam (4, 4), rms reprojection error in px)`` from a photo of the board on the table."""
    import cv2

    gray = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) if image.ndim == 3 else image
    found = board.detect(gray)
    if found is None:
        raise CalibrationError("the board was not found in the ground-plane photo")
    obj, corners = found
    ok, rvec, tvec = cv2.solvePnP(obj, corners, K, dist, flags=cv2.SOLVEPNP_ITERATIVE)
    if not ok:
        raise CalibrationError("solvePnP failed on the ground-plane photo")
    proj, _ = cv2.projectPoints(obj, rvec, tvec, K, dist)
    rms = float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - corners) ** 2, axis=-1))))
    T_cam_board = np.eye(4)
    T_cam_board[:3, :3] = cv2.Rodrigues(rvec)[0]
    T_cam_board[:3, 3] = tvec.reshape(3)
    T_world_cam = T_WORLD_BOARD @ np.linalg.inv(T_cam_board)
    return T_world_cam, rms
