"""Camera calibration with OpenCV: chessboard / ChArUco intrinsics, OpenCV FileStorage YAML,
and the ground-plane pose ``T_world_cam`` from one photo of a board lying on the table.

The real-photo preparation (``realdata``) and the reconstruction of real images build on it.
"""
