"""The calibrated real-photo path end to end, with a known answer (``realdata.synthetic``).

Renders a rig (board views, the board on the table, Clevr-style scenes from a metric camera that is
not the training camera), runs the README's three commands on it (``calibrate intrinsics``,
``calibrate ground``, ``real reconstruct``), and reports the reconstructed objects' position error
in model units against the truth, beside the same model's error on the same layouts seen by its own
training camera (so the loss due to the calibrated path shows apart from the model's own error).
Both are scored by ``prismonet evaluate`` (``realdata.synthetic.write_rig_datasets``: the rectified
photos with their true instances and objects mapped by the recovered world map, and the direct
renders), colour only, with the same test-time flags; a last line gives every true object's error
against the nearest found object (one to one), which counts misses the IoU-matched figure leaves out.

    python3 scripts/calibrated_rig.py --scenes 32 --out runs/rig
    python3 scripts/calibrated_rig.py --scenes 32 --out runs/rig --elevation 28.33 --tag same-elevation
    python3 scripts/calibrated_rig.py --scenes 32 --out runs/rig -- --search 3 --fit-color 50
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np


def main() -> None:
    from prismonet.cli import main as cli
    from realdata.synthetic import RigConfig, position_errors, render_rig, write_rig_datasets

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="runs/rig")
    ap.add_argument("--scenes", type=int, default=16)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--elevation", type=float, default=RigConfig.elevation)
    ap.add_argument("--heading", type=float, default=RigConfig.heading_offset)
    ap.add_argument("--model", default="shipped")
    ap.add_argument("--tag", default="")
    ap.add_argument("inference", nargs=argparse.REMAINDER, help="after --: test-time step flags for real reconstruct")
    args = ap.parse_args()
    from prismonet.threads import use_free_cores

    use_free_cores(exit_on_error=True)  # the cores others leave free; PRISMONET_THREADS=N to choose
    flags = [a for a in args.inference if a != "--"]
    out = Path(args.out)
    rig = replace(RigConfig(), elevation=args.elevation, heading_offset=args.heading)
    truth = render_rig(out, args.scenes, args.seed, rig)
    board = ["--board", f"{rig.board[0]}x{rig.board[1]}", "--square", str(rig.square_m)]
    assert cli(["calibrate", "intrinsics", *map(str, sorted((out / "boards").glob("*.png"))), *board, "--out", str(out / "cam.yml")]) == 0
    assert cli(["calibrate", "ground", str(out / "ground.png"), "--camera", str(out / "cam.yml"), *board, "--out", str(out / "ground.yml")]) == 0
    photos = [str(out / s["photo"]) for s in truth["scenes"]]
    assert cli(["real", "reconstruct", *photos, "--camera", str(out / "ground.yml"), "--out", str(out / "recon"), "--quiet",
                "--model", args.model, *flags]) == 0
    summary = json.loads((out / "recon" / "summary.json").read_text())
    rect, direct = write_rig_datasets(out, out / "recon", out / "eval", args.model)
    rows = {}
    for name, data in (("calibrated", rect), ("direct", direct)):
        assert cli(["evaluate", args.model, str(data), "--color-only", "--quiet", "--json", str(out / f"eval_{name}.json"), *flags]) == 0
        rows[name] = json.loads((out / f"eval_{name}.json").read_text())
    errs = [e for sc, rec in zip(truth["scenes"], summary) for e in position_errors(sc, rec["objects"], rig.metres_per_unit)]
    world = summary[0]["prepare"]["world"]
    keys = ("AP0.5", "AR0.5", "allObj", "AP0.5_unfiltered", "pos_err", "rot_err_sym", "PSNR", "matched_objects")
    row = {"tag": args.tag, "scenes": args.scenes, "elevation": args.elevation, "heading": args.heading, "flags": " ".join(flags),
           "metres_per_unit": round(world["metres_per_unit"], 6), "true_metres_per_unit": rig.metres_per_unit,
           **{f"{n}_{k}": round(r[k], 4) for n, r in rows.items() for k in keys},
           "nearest_found_pos_err_mean": round(float(np.mean(errs)), 4), "nearest_found_pos_err_median": round(float(np.median(errs)), 4),
           "warnings": sorted({w for r in summary for w in r["warnings"]})}
    print(json.dumps(row))
    sys.stdout.flush()


if __name__ == "__main__":
    main()
