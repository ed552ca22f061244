"""Synthetic photos of a chessboard seen by a known camera, for validating the calibration."""

from __future__ import annotations

import numpy as np


def render_board(board, K: np.ndarray, T_cam_board: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Greyscale photo ``(H, W)`` of a board (``Chessboard`` or ``Charuco``) on a grey background,
    pinhole camera without distortion."""
    import cv2

    tex, S = board.texture()
    # board plane z = 0: image = K [r1 r2 t] x_board = K [r1 r2 t] S^-1 x_tex
    H = K @ np.column_stack([T_cam_board[:3, 0], T_cam_board[:3, 1], T_cam_board[:3, 3]]) @ np.linalg.inv(S)
    return cv2.warpPerspective(tex, H, size, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=128)
