"""Calibration against OpenCV's own reference on real photos, and exact answers on synthetic boards."""

from pathlib import Path

import cv2
import numpy as np
import pytest

from calibration.board import Chessboard
from calibration.ground import ground_pose
from calibration.intrinsics import CalibrationError, calibrate_folder, calibrate_images
from calibration.storage import load_calibration, save_calibration, to_camera
from calibration.synthetic import render_board

SAMPLES = Path(__file__).resolve().parents[1] / "calibration" / "samples" / "opencv_chessboard"
K_TRUE = np.array([[600.0, 0, 319.5], [0, 600.0, 239.5], [0, 0, 1]])
BOARD = Chessboard(9, 6, 0.03)


def pose(rvec, t):
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(np.asarray(rvec, float))[0]
    T[:3, 3] = t
    return T


def synthetic_views(n=8, seed=0):
    rng = np.random.default_rng(seed)
    Ts = [pose(rng.uniform(-0.4, 0.4, 3), np.array([-0.12, -0.08, 0.55]) + rng.uniform(-0.05, 0.05, 3)) for _ in range(n)]
    return [render_board(BOARD, K_TRUE, T, (640, 480)) for T in Ts], Ts


def test_real_photos_agree_with_opencv_reference_calibration():
    paths = sorted(SAMPLES.glob("left*.jpg"))
    assert len(paths) == 13
    cal = calibrate_folder(paths, Chessboard(9, 6, 0.025), fix_aspect_ratio=True)
    ref, _ = load_calibration(SAMPLES / "left_intrinsics.yml")  # OpenCV's own file
    assert all(p["found"] for p in cal.per_image)
    assert np.abs(cal.K - ref.K).max() < 2.0  # fx = fy ~ 535.9, cx ~ 342.3, cy ~ 235.6
    assert ref.K[0, 0] == pytest.approx(535.92, abs=0.01)
    assert cal.rms == pytest.approx(0.39, abs=0.05)
    assert all(0 < p["rms_px"] < 1.5 for p in cal.per_image)


def test_synthetic_boards_give_the_true_intrinsics():
    imgs, _ = synthetic_views()
    cal = calibrate_images(imgs, BOARD)
    assert np.abs(cal.K - K_TRUE).max() < 1.0
    assert cal.rms < 0.2
    # the true camera has no distortion. The fitted coefficients (k3 is weakly constrained and soaks
    # up detection noise) must move no observed corner by more than a fraction of a pixel; outside
    # the area the boards cover (the image corners) the fit is an extrapolation and is not checked.
    from calibration.board import find_corners

    pts = np.concatenate([find_corners(im, BOARD) for im in imgs]).astype(np.float64)[:, None]
    moved = cv2.undistortPoints(pts, cal.K, cal.dist, P=cal.K).reshape(-1, 2)
    assert np.abs(moved - pts.reshape(-1, 2)).max() < 0.3


def test_ground_plane_pose_from_one_photo():
    imgs, Ts = synthetic_views(2, seed=1)
    T_world_cam, rms = ground_pose(imgs[0], K_TRUE, np.zeros(5), BOARD)
    expected = np.diag([1.0, -1.0, -1.0, 1.0]) @ np.linalg.inv(Ts[0])
    assert rms < 0.2
    assert np.abs(T_world_cam[:3, :3] - expected[:3, :3]).max() < 2e-3
    assert np.abs(T_world_cam[:3, 3] - expected[:3, 3]).max() < 2e-3
    # the camera looks down at the table from above: positive height, optical axis pointing down
    assert T_world_cam[2, 3] > 0 and T_world_cam[2, 2] < 0
    # board corners map to z = 0 in the world, and project back onto their pixels through the kornia camera
    import torch

    from prismonet.geometry.camera import Camera

    cam = Camera(torch.tensor(K_TRUE, dtype=torch.float64), torch.tensor(T_world_cam), 480, 640)
    corners_world = (np.diag([1.0, -1.0, -1.0]) @ BOARD.object_points().T).T
    assert np.allclose(corners_world[:, 2], 0)
    uv = cam.world_to_pixels(torch.tensor(corners_world, dtype=torch.float64)).numpy()
    from calibration.board import find_corners

    assert np.abs(uv - find_corners(imgs[0], BOARD)).max() < 0.5


def test_filestorage_round_trip_and_opencv_readability(tmp_path):
    imgs, _ = synthetic_views(4)
    cal = calibrate_images(imgs, BOARD)
    T = pose([0.1, 0.2, 0.3], [1, 2, 3])
    path = save_calibration(cal, tmp_path / "cam.yml", T)
    back, T_back = load_calibration(path)
    assert np.allclose(back.K, cal.K) and np.allclose(back.dist, cal.dist) and back.image_size == (640, 480)
    assert np.allclose(T_back, T)
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)  # what OpenCV tools do
    assert np.allclose(fs.getNode("camera_matrix").mat(), cal.K)
    cam = to_camera(back, T_back)
    assert (cam.height, cam.width) == (480, 640) and abs(float(cam.K[0, 0]) - cal.K[0, 0]) < 1e-3


def test_photo_without_board_is_skipped_with_a_warning():
    from calibration.intrinsics import BoardNotFoundWarning

    imgs, _ = synthetic_views(4)
    blank = np.full_like(imgs[0], 128)
    with pytest.warns(BoardNotFoundWarning, match="blank.png: the 9x6 board was not found"):
        cal = calibrate_images(imgs + [blank], BOARD, names=[f"v{i}.png" for i in range(4)] + ["blank.png"])
    assert [p["found"] for p in cal.per_image] == [True] * 4 + [False]


def test_bad_inputs(tmp_path):
    with pytest.raises(CalibrationError, match="no photos given"):
        calibrate_folder([], BOARD)
    (tmp_path / "x.jpg").write_bytes(b"not an image")
    with pytest.raises(CalibrationError, match="cannot be read as an image"):
        calibrate_folder([tmp_path / "x.jpg"], BOARD)
    blank = [np.full((480, 640), 128, np.uint8)] * 4
    with pytest.raises(CalibrationError, match=r"found in 0 of 4 photos; need at least 3"):
        calibrate_images(blank, BOARD)
    imgs, _ = synthetic_views(3)
    with pytest.raises(CalibrationError, match="other photos are 640x480"):
        calibrate_images(imgs + [imgs[0][:240, :320]], BOARD)
    with pytest.raises(CalibrationError, match="board was not found in the ground-plane photo"):
        ground_pose(blank[0], K_TRUE, np.zeros(5), BOARD)
    with pytest.raises(CalibrationError, match="no such calibration file"):
        load_calibration(tmp_path / "none.yml")
    with pytest.raises(ValueError, match="COLSxROWS"):
        Chessboard.parse("nine by six", 0.025)


def test_calibrate_cli(tmp_path, capsys):
    from prismonet.cli import main

    photos = [str(p) for p in sorted(SAMPLES.glob("left*.jpg"))]
    assert main(["calibrate", "intrinsics", *photos, "--fix-aspect", "--out", str(tmp_path / "cam.yml")]) == 0
    out = capsys.readouterr().out
    assert "13 of 13 photos" in out and "left01.jpg: found" in out
    assert main(["calibrate", "ground", photos[0], "--camera", str(tmp_path / "cam.yml"), "--out", str(tmp_path / "g.yml")]) == 0
    _, T = load_calibration(tmp_path / "g.yml")
    assert T is not None and T[2, 3] > 0
    assert main(["calibrate", "ground", photos[0], "--camera", str(tmp_path / "none.yml"), "--out", str(tmp_path / "g.yml")]) == 2
    assert "no such calibration file" in capsys.readouterr().err


def test_charuco_synthetic_calibration_and_ground_pose():
    from calibration.board import Charuco

    board = Charuco(7, 5, 0.04, 0.03)
    # 24 corners per view: with few, near-frontal views the principal point trades off against
    # the distortion terms (8 views at +-0.35 rad gave cx 3 px off), so use 16 at +-0.5 rad
    rng = np.random.default_rng(3)
    Ts = [pose(rng.uniform(-0.5, 0.5, 3), np.array([-0.14, -0.1, 0.6]) + rng.uniform(-0.04, 0.04, 3)) for _ in range(16)]
    imgs = [render_board(board, K_TRUE, T, (640, 480)) for T in Ts]
    cal = calibrate_images(imgs, board)
    assert all(p["found"] for p in cal.per_image)
    assert np.abs(cal.K - K_TRUE).max() < 1.0 and cal.rms < 0.3
    T_world_cam, rms = ground_pose(imgs[0], K_TRUE, np.zeros(5), board)
    expected = np.diag([1.0, -1.0, -1.0, 1.0]) @ np.linalg.inv(Ts[0])
    assert rms < 0.3 and np.abs(T_world_cam - expected).max() < 3e-3
    with pytest.raises(ValueError, match="unknown ArUco dictionary"):
        Charuco(dictionary="DICT_NOPE")
