"""The paper's ShapeNet tables with our rows beside them, from ``evaluate --json`` results.

    python3 scripts/shapenet_table.py cars:seen=runs/cars_eval_seen.json cars:novel=runs/cars_eval_novel.json ...
    python3 scripts/shapenet_table.py --supervised chairs:weak=runs/chairs_eval_seen.json chairs:pose=runs/chairs_pose_eval_seen.json

Each argument is ``SETTING:ROW=JSON``: SETTING one of cars, chairs, tabletop (the paper's name; our
``tableware``); ROW ``seen`` / ``novel`` for the main table, ``weak`` / ``pose`` / ``mask`` for
``--supervised``. The paper's mean rows (and best, main table) are printed above ours. AP0.5 and mAP
are ours with predictions under 25 px filtered, as the paper's text reads; the unfiltered AP0.5 is the
last column.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

PAPER = {  # setting -> row -> (mAP, AP, AR, F1, allObj, RMSE, PSNR, SSIM, D-RMSE, AbsRD, SqRD, pos, rot, rot sym)
    "cars": {"seen best": (0.750, 0.991, 0.991, 0.991, 0.979, 0.064, 24.092, 0.898, 0.158, 0.006, 0.004, 0.144, 23.67, 3.29),
             "seen mean": (0.738, 0.990, 0.990, 0.990, 0.975, 0.064, 23.979, 0.894, 0.160, 0.006, 0.005, 0.146, 22.09, 3.07),
             "novel best": (0.639, 0.980, 0.980, 0.980, 0.955, 0.077, 22.442, 0.843, 0.210, 0.010, 0.008, 0.183, 24.24, 4.53),
             "novel mean": (0.632, 0.977, 0.977, 0.977, 0.944, 0.077, 22.454, 0.842, 0.208, 0.010, 0.008, 0.184, 24.25, 4.41)},
    "chairs": {"seen best": (0.432, 0.897, 0.871, 0.881, 0.640, 0.086, 21.576, 0.803, 0.829, 0.040, 0.117, 0.308, 43.64, 9.13),
               "seen mean": (0.329, 0.642, 0.638, 0.640, 0.188, 0.102, 20.137, 0.772, 1.021, 0.058, 0.196, 0.296, 55.12, 7.25),
               "novel best": (0.377, 0.852, 0.821, 0.833, 0.534, 0.092, 20.994, 0.778, 0.890, 0.052, 0.137, 0.395, 58.79, 10.66),
               "novel mean": (0.278, 0.613, 0.607, 0.609, 0.158, 0.106, 19.740, 0.746, 1.068, 0.069, 0.213, 0.372, 68.29, 9.28)},
    "tabletop": {"seen best": (0.628, 0.936, 0.870, 0.895, 0.659, 0.057, 25.242, 0.908, 0.786, 0.026, 0.132, 0.182, 89.14, None),
                 "seen mean": (0.394, 0.565, 0.537, 0.546, 0.251, 0.078, 22.871, 0.861, 1.022, 0.050, 0.231, 0.155, 88.53, None),
                 "novel best": (0.435, 0.839, 0.816, 0.823, 0.569, 0.083, 21.807, 0.840, 1.034, 0.044, 0.224, 0.275, 89.25, None),
                 "novel mean": (0.285, 0.530, 0.521, 0.523, 0.237, 0.102, 20.160, 0.800, 1.172, 0.061, 0.291, 0.238, 89.99, None)},
}
SUPERVISED = {  # setting -> row -> (mAP, AP, AR, RMSE, PSNR, D-RMSE, pos, rot)
    "cars": {"weak": (0.738, 0.990, 0.990, 0.064, 23.979, 0.160, 0.146, 22.09), "pose": (0.745, 0.988, 0.988, 0.068, 23.567, 0.160, 0.071, 7.28),
             "mask": (0.756, 0.990, 0.990, 0.064, 24.030, 0.152, 0.133, 21.00)},
    "chairs": {"weak": (0.329, 0.642, 0.638, 0.102, 20.137, 1.021, 0.296, 55.12), "pose": (0.533, 0.928, 0.928, 0.085, 21.709, 0.753, 0.126, 10.06),
               "mask": (0.302, 0.559, 0.561, 0.106, 19.788, 1.088, 0.290, 35.31)},
    "tabletop": {"weak": (0.394, 0.565, 0.537, 0.078, 22.871, 1.022, 0.155, 88.53), "pose": (0.667, 0.956, 0.944, 0.054, 25.679, 0.652, 0.099, 54.81),
                 "mask": (0.676, 0.953, 0.942, 0.054, 25.780, 0.638, 0.099, 46.53)},
}
ROW_NAMES = {"weak": "PriSMONet", "pose": "+ 3D pose", "mask": "+ 2D mask"}


def _f(x, digits: int = 3) -> str:
    return "—" if x is None else f"{x:.{digits}f}"


def _rot(rot, sym) -> str:
    return "—" if rot is None else f"{rot:.1f}°" + ("" if sym is None else f" [{sym:.1f}°]")


MAIN_KEYS = ("mAP", "AP0.5", "AR0.5", "F1_0.5", "allObj", "img_RMSE", "PSNR", "SSIM", "depth_RMSE", "AbsRD", "SqRD", "pos_err")
SUPERVISED_KEYS = ("mAP", "AP0.5", "AR0.5", "img_RMSE", "PSNR", "depth_RMSE", "pos_err")
DIGITS = {"PSNR": 2, "AbsRD": 4, "SqRD": 4}


def _line(setting: str, label: str, scenes: str, cells: list[str], rot: str, unfiltered: str) -> str:
    return f"| {setting} | {label} | {scenes} | " + " | ".join(cells) + f" | {rot} | {unfiltered} |"


def _table(head: str, rows: list[tuple[str, str, dict]], groups, keys: tuple[str, ...]) -> str:
    """``groups(setting)`` yields ``(row, [(label, paper values, paper rot, paper rot sym)], our label)``."""
    lines = [head, "|" + "---|" * (len(keys) + 5)]
    for setting in dict.fromkeys(s for s, _, _ in rows):
        for row, papers, ours in groups(setting):
            for label, values, rot, sym in papers:
                lines.append(_line(setting, label, "5,000", [_f(v, 2 if k == "PSNR" else 3) for k, v in zip(keys, values)], _rot(rot, sym), "—"))
            for s, rr, r in rows:
                if s == setting and rr == row:
                    cells = [(f"**{_f(r[k])}**" if k == "AP0.5" else _f(r[k], DIGITS.get(k, 3))) for k in keys]
                    lines.append(_line(setting, ours, f"{r['scenes']:,}", cells, _rot(r["rot_err"], r.get("rot_err_sym")),
                                       _f(r["AP0.5_unfiltered"])))
    return "\n".join(lines)


def main_table(rows: list[tuple[str, str, dict]]) -> str:
    head = ("| setting | row | scenes | mAP | AP0.5 | AR0.5 | F1 | allObj | RMSE | PSNR | SSIM | D-RMSE | AbsRD | SqRD | pos "
            "| rot [sym.] | AP0.5 unf. |")
    groups = lambda setting: [(split, [(f"paper, {split} ({kind} of 5)", PAPER[setting][f"{split} {kind}"][:12],
                                        *PAPER[setting][f"{split} {kind}"][12:]) for kind in ("best", "mean")], f"**ours, {split}**")
                              for split in ("seen", "novel")]
    return _table(head, rows, groups, MAIN_KEYS)


def supervised_table(rows: list[tuple[str, str, dict]]) -> str:
    head = "| setting | variant | scenes | mAP | AP0.5 | AR0.5 | RMSE | PSNR | D-RMSE | pos | rot [sym.] | AP0.5 unf. |"
    groups = lambda setting: [(row, [(f"{ROW_NAMES[row]}: paper (mean of 5)", SUPERVISED[setting][row][:7], SUPERVISED[setting][row][7], None)],
                               f"{ROW_NAMES[row]}: **ours**") for row in ("weak", "pose", "mask")]
    return _table(head, rows, groups, SUPERVISED_KEYS)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("rows", nargs="+", help="SETTING:ROW=JSON")
    ap.add_argument("--supervised", action="store_true", help="the supervised-training table (rows weak, pose, mask)")
    args = ap.parse_args(argv)
    allowed = ("weak", "pose", "mask") if args.supervised else ("seen", "novel")
    rows = []
    for item in args.rows:
        key, _, path = item.partition("=")
        setting, _, row = key.partition(":")
        if setting not in PAPER or row not in allowed or not path:
            print(f"shapenet_table: error: expected SETTING:ROW=JSON with SETTING in {tuple(PAPER)} and ROW in {allowed}, got {item!r}",
                  file=sys.stderr)
            return 2
        if not Path(path).is_file():
            print(f"shapenet_table: error: no such results file: {path}", file=sys.stderr)
            return 2
        rows.append((setting, row, json.loads(Path(path).read_text())))
    print(supervised_table(rows) if args.supervised else main_table(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
