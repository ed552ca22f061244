"""Synthetic photos of a chessboard seen by a known camera, for validating the calibration."""

from __future__ import annotations

import numpy as np

from calibration.board import Chessboard

PIXELS_PER_SQUARE = 40
"""Resolution of the board texture that is warped into the photo."""


def board_texture(board: Chessboard) -> tuple[np.ndarray, np.ndarray]:
    """The printed board (white margin of one square) and the 3x3 map from board units to texture pixels."""
    n_cols, n_rows = board.cols + 1, board.rows + 1  # squares
    p = PIXELS_PER_SQUARE
    img = np.full(((n_rows + 2) * p, (n_cols + 2) * p), 255, np.uint8)
    for r in range(n_rows):
        for c in range(n_cols):
            if (r + c) % 2 == 0:
                img[(r + 1) * p : (r + 2) * p, (c + 1) * p : (c + 2) * p] = 0
    # board origin (first inner corner) sits at texture pixel (2p, 2p); pixel centres at integers
    S = np.array([[p / board.square, 0, 2 * p - 0.5], [0, p / board.square, 2 * p - 0.5], [0, 0, 1]])
    return img, S


def render_board(board: Chessboard, K: np.ndarray, T_cam_board: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Greyscale photo ``(H, W)`` of the board on a grey background, pinhole camera without distortion."""
    import cv2

    tex, S = board_texture(board)
    # board plane z = 0: image = K [r1 r2 t] x_board = K [r1 r2 t] S^-1 x_tex
    H = K @ np.column_stack([T_cam_board[:3, 0], T_cam_board[:3, 1], T_cam_board[:3, 3]]) @ np.linalg.inv(S)
    out = cv2.warpPerspective(tex, H, size, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=128)
    return out
