"""``prismonet calibrate``: the camera with OpenCV: intrinsics from board photos, and the ground
plane's pose from one photo of the board lying on the table."""

from __future__ import annotations

import argparse


def board(args):
    """The calibration board of ``add_board_args``'s flags."""
    from calibration.board import Charuco, Chessboard

    grid = Chessboard.parse(args.board, args.square)
    return Charuco(grid.cols, grid.rows, args.square, args.marker, args.dictionary) if args.charuco else grid


def add_board_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--board", default="9x6", help="inner corners COLSxROWS (default 9x6); with --charuco: squares")
    p.add_argument("--square", type=float, default=0.025, help="square side in world units")
    p.add_argument("--charuco", action="store_true", help="a ChArUco board (with --marker, --dictionary)")
    p.add_argument("--marker", type=float, default=0.03, help="ChArUco marker side")
    p.add_argument("--dictionary", default="DICT_4X4_50", help="ArUco dictionary name")


def cmd_intrinsics(args) -> int:
    from calibration.intrinsics import calibrate_folder
    from calibration.storage import save_calibration

    cal = calibrate_folder(args.photos, board(args), fix_aspect_ratio=args.fix_aspect)
    for p in cal.per_image:
        status = f"found, reprojection RMS {p['rms_px']:.3f} px" if p["found"] else "board NOT found (skipped)"
        print(f"  {p['image']}: {status}")
    K = cal.K
    print(f"fx {K[0, 0]:.2f}  fy {K[1, 1]:.2f}  cx {K[0, 2]:.2f}  cy {K[1, 2]:.2f}  RMS {cal.rms:.3f} px  "
          f"({sum(p['found'] for p in cal.per_image)} of {len(cal.per_image)} photos)")
    print(f"wrote {save_calibration(cal, args.out)}")
    return 0


def cmd_ground(args) -> int:
    import cv2

    from calibration.ground import ground_pose
    from calibration.storage import load_calibration, save_calibration
    from prismonet.files import read_image

    cal, _ = load_calibration(args.camera)
    img = read_image(args.photo, cv2.IMREAD_GRAYSCALE)
    T, rms = ground_pose(img, cal.K, cal.dist, board(args))
    print(f"camera height above the table {T[2, 3]:.3f}, reprojection RMS {rms:.3f} px")
    print(f"wrote {save_calibration(cal, args.out, T)} (with T_world_cam: z up, table at z = 0)")
    return 0


def add_parsers(sub) -> None:
    cal = sub.add_parser("calibrate", help="camera calibration with OpenCV (intrinsics, ground plane)")
    csub = cal.add_subparsers(dest="calibrate_command", required=True)
    ci = csub.add_parser("intrinsics", help="intrinsics and distortion from chessboard photos")
    ci.add_argument("photos", nargs="+")
    add_board_args(ci)
    ci.add_argument("--fix-aspect", action="store_true", help="fx = fy (as OpenCV's sample calibration)")
    ci.add_argument("--out", required=True, help="OpenCV FileStorage YAML")
    ci.set_defaults(func=cmd_intrinsics, outputs=[("out", "file")])
    cg = csub.add_parser("ground", help="T_world_cam from one photo of the board lying on the table")
    cg.add_argument("photo")
    cg.add_argument("--camera", required=True, help="YAML from 'calibrate intrinsics'")
    add_board_args(cg)
    cg.add_argument("--out", required=True)
    cg.set_defaults(func=cmd_ground, outputs=[("out", "file")])
