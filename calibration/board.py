"""Calibration boards: a chessboard's inner-corner grid or a ChArUco board, in the board frame.

Board frame (OpenCV's): x along the columns, y along the rows, z = x cross y, origin at the
first inner corner; units are those of ``square`` (metres, say).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


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

    @staticmethod
    def parse(text: str, square: float) -> "Chessboard":
        """``"9x6"`` -> 9 x 6 inner corners."""
        try:
            c, r = (int(v) for v in text.lower().split("x"))
        except ValueError:
            raise ValueError(f"board: expected inner corners as COLSxROWS like 9x6, got {text!r}") from None
        return Chessboard(c, r, square)
