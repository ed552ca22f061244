"""Camera calibration with OpenCV (chessboard / ChArUco intrinsics, ground-plane pose).

Planned in the real-photos issue; the package exists now so that the layout and the single
``pyproject.toml`` that installs ``prismonet``, ``realdata`` and ``calibration`` are in place.
"""
