"""Calibration boards: a chessboard's inner-corner grid or a ChArUco board, in the board frame.

Board frame (OpenCV's): x along the columns, y along the rows, z = x cross y; units are those of
``square`` (metres, say). Origin: the first inner corner (chessboard), the board's outer corner
(ChArUco, as OpenCV defines it).

Each board detects its own points (``detect``: matched object and image points) and draws its
own printable texture (``texture``), which the synthetic renderer warps into photos.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

SUBPIX_WINDOW = (11, 11)
"""Largest half-size of cv2.cornerSubPix's search window (OpenCV's sample value)."""
SUBPIX_SPACING_FRACTION = 0.5
"""The half-window is at most this fraction of the smallest spacing between neighbouring corners
(rounded): a window wider than a square takes in the next corner's edges and biases the fit (a board
seen at a grazing angle has squares 10-15 px tall: with the full window, ground-pose RMS 3.5 px against
0.09 px). Boards with squares of 21 px or more keep OpenCV's full window."""
SUBPIX_CRITERIA = (3, 30, 1e-3)  # cv2.TERM_CRITERIA_EPS + MAX_ITER, 30 iterations, 1e-3 px


@dataclass(frozen=True)
class Chessboard:
    """A chessboard by its inner corners (``cols`` x ``rows``) and square side."""

    cols: int = 9
    rows: int = 6
    square: float = 0.025

    def __post_init__(self) -> None:
        if self.cols < 2 or self.rows < 2 or self.square <= 0:
            raise ValueError(f"chessboard: need at least 2x2 inner corners and a positive square, got {self}")

    def object_points(self) -> np.ndarray:
        """``(cols*rows, 3)`` float32 corner positions, row-major as OpenCV detects them."""
        g = np.mgrid[0 : self.cols, 0 : self.rows].T.reshape(-1, 2)
        return np.concatenate([g * self.square, np.zeros((len(g), 1))], 1).astype(np.float32)

    def detect(self, gray: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """``(object points (N, 3), image points (N, 2))`` or ``None`` when the board is not found."""
        corners = find_corners(gray, self)
        return None if corners is None else (self.object_points(), corners)

    def texture(self, pixels_per_square: int = 40) -> tuple[np.ndarray, np.ndarray]:
        """The printed board (one square of white margin) and the 3x3 map board units -> texture pixels."""
        p = pixels_per_square
        n_cols, n_rows = self.cols + 1, self.rows + 1  # squares
        img = np.full(((n_rows + 2) * p, (n_cols + 2) * p), 255, np.uint8)
        for r in range(n_rows):
            for c in range(n_cols):
                if (r + c) % 2 == 0:
                    img[(r + 1) * p : (r + 2) * p, (c + 1) * p : (c + 2) * p] = 0
        # the first inner corner sits at texture pixel (2p, 2p); pixel centres at integers
        S = np.array([[p / self.square, 0, 2 * p - 0.5], [0, p / self.square, 2 * p - 0.5], [0, 0, 1]])
        return img, S

    @staticmethod
    def parse(text: str, square: float) -> "Chessboard":
        """``"9x6"`` -> 9 x 6 inner corners."""
        try:
            c, r = (int(v) for v in text.lower().split("x"))
        except ValueError:
            raise ValueError(f"board: expected inner corners as COLSxROWS like 9x6, got {text!r}") from None
        return Chessboard(c, r, square)


MIN_CHARUCO_CORNERS = 6
"""Fewer ChArUco corners than this in a view cannot constrain a pose."""


@dataclass(frozen=True)
class Charuco:
    """A ChArUco board (opencv-contrib's aruco): ``squares_x`` x ``squares_y`` squares of side
    ``square``, ArUco markers of side ``marker`` from the predefined dictionary ``dictionary``."""

    squares_x: int = 7
    squares_y: int = 5
    square: float = 0.04
    marker: float = 0.03
    dictionary: str = "DICT_4X4_50"

    def __post_init__(self) -> None:
        import cv2

        if self.squares_x < 3 or self.squares_y < 3 or not 0 < self.marker < self.square:
            raise ValueError(f"charuco: need at least 3x3 squares and 0 < marker < square, got {self}")
        if not hasattr(cv2.aruco, self.dictionary):
            raise ValueError(f"charuco: unknown ArUco dictionary {self.dictionary!r}")

    def cv_board(self):
        import cv2

        d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        return cv2.aruco.CharucoBoard((self.squares_x, self.squares_y), self.square, self.marker, d)

    def detect(self, gray: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        import cv2

        board = self.cv_board()
        corners, ids, _, _ = cv2.aruco.CharucoDetector(board).detectBoard(gray)
        if ids is None or len(ids) < MIN_CHARUCO_CORNERS:
            return None
        obj, img = board.matchImagePoints(corners, ids)
        return obj.reshape(-1, 3).astype(np.float32), img.reshape(-1, 2).astype(np.float32)

    def texture(self, pixels_per_square: int = 40) -> tuple[np.ndarray, np.ndarray]:
        p, m = pixels_per_square, pixels_per_square
        img = self.cv_board().generateImage((self.squares_x * p + 2 * m, self.squares_y * p + 2 * m), marginSize=m)
        S = np.array([[p / self.square, 0, m - 0.5], [0, p / self.square, m - 0.5], [0, 0, 1]])
        return img, S


def find_corners(gray: np.ndarray, board: "Chessboard") -> np.ndarray | None:
    """Sub-pixel inner corners ``(N, 2)`` float32, or ``None`` when the board is not found.

    (OpenCV 4 returns ``(N, 1, 2)`` and OpenCV 5 ``(N, 2)``; this always gives ``(N, 2)``.)"""
    import cv2

    flags = cv2.CALIB_CB_ADAPTIVE_THRESH + cv2.CALIB_CB_NORMALIZE_IMAGE
    ok, corners = cv2.findChessboardCorners(gray, (board.cols, board.rows), flags=flags)
    if not ok:
        return None
    grid = corners.reshape(board.rows, board.cols, 2)
    spacing = min(np.linalg.norm(np.diff(grid, axis=0), axis=-1).min(), np.linalg.norm(np.diff(grid, axis=1), axis=-1).min())
    half = int(max(2, min(SUBPIX_WINDOW[0], round(SUBPIX_SPACING_FRACTION * spacing))))
    return cv2.cornerSubPix(gray, corners, (half, half), (-1, -1), SUBPIX_CRITERIA).reshape(-1, 2)
