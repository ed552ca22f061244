"""Train and evaluate the rows of an ablation table at one budget (``configs/ablation_5k.json``).

Each row trains the base config with its overrides in ``OUT/<slug>`` (resumable: rerun the same command),
then is evaluated feed-forward on the test split of ``eval_data`` (``OUT/<slug>/eval.json``, kept once
written). ``--only`` picks rows (to run two at once, one thread each); ``--table`` only prints the table of
the rows evaluated so far, with the budget (steps, images seen, CPU hours) of each.

    python3 scripts/ablation.py configs/ablation_5k.json --out runs/ablation --only full no_mask
    python3 scripts/ablation.py configs/ablation_5k.json --out runs/ablation --table
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

COLUMNS = [("mAP", "mAP", 3), ("AP0.5", "AP0.5", 3), ("AR0.5", "AR0.5", 3), ("F1", "F1_0.5", 3), ("allObj", "allObj", 3),
           ("AP0.5 unf.", "AP0.5_unfiltered", 3), ("RMSE", "img_RMSE", 3), ("PSNR", "PSNR", 2), ("SSIM", "SSIM", 3),
           ("D-RMSE", "depth_RMSE", 3), ("AbsRD", "AbsRD", 4), ("SqRD", "SqRD", 4), ("pos", "pos_err", 3), ("rot (sym.)", "rot_err_sym", 1)]


def main() -> None:
    from prismonet.cli import main as cli

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("rows", help="JSON: base config, eval_data and rows of {name, slug, set}")
    ap.add_argument("--out", required=True)
    ap.add_argument("--only", nargs="*", help="slugs of the rows to run (default: all)")
    ap.add_argument("--table", action="store_true", help="print the table of the rows evaluated so far")
    ap.add_argument("--limit", type=int, help="evaluate the first N test scenes only")
    ap.add_argument("--threads", type=int, help="training threads (1 when two rows run at once)")
    args = ap.parse_args()
    from prismonet.threads import use_free_cores

    use_free_cores(exit_on_error=True)  # the cores others leave free; PRISMONET_THREADS=N to choose
    spec = json.loads(Path(args.rows).read_text())
    out = Path(args.out)
    rows = [r for r in spec["rows"] if not args.only or r["slug"] in args.only]
    if args.only and len(rows) != len(args.only):
        raise SystemExit(f"unknown slug in {args.only}; the rows are {[r['slug'] for r in spec['rows']]}")
    if not args.table:
        for r in rows:
            run = out / r["slug"]
            sets = [x for kv in r["set"] + ([f"threads={args.threads}"] if args.threads else []) for x in ("--set", kv)]
            code = cli(["train", spec["base"], "--out", str(run), *sets, "--quiet"])
            if code != 0:
                raise SystemExit(code)
            if not (run / "eval.json").is_file():
                limit = ["--limit", str(args.limit)] if args.limit else []
                code = cli(["evaluate", str(run), spec["eval_data"], "--json", str(run / "eval.json"), "--quiet", *limit])
                if code != 0:
                    raise SystemExit(code)
    print(table(spec, out))


def table(spec: dict, out: Path) -> str:
    """CPU hours: the run's wall time times its thread count at the last log line (1 for the runs here)."""
    from prismonet.config import load_config
    from prismonet.model.trainer import TrainConfig

    head = "| row | steps | images | CPU h | " + " | ".join(c for c, _, _ in COLUMNS) + " |"
    lines = [head, "|" + "---|" * (len(COLUMNS) + 4)]
    for r in spec["rows"]:
        run = out / r["slug"]
        if not (run / "eval.json").is_file():
            continue
        res = json.loads((run / "eval.json").read_text())
        log = [json.loads(x) for x in (run / "log.jsonl").read_text().splitlines() if x.strip()]
        batch = load_config(TrainConfig, spec["base"], r["set"]).batch_size
        steps = log[-1]["step"] if log else 0
        hours = (log[-1]["time_s"] if log else 0.0) / 3600  # wall time, carried across resumptions
        threads = log[-1].get("threads", 1) if log else 1
        cells = [f"{res[k]:.{d}f}" for _, k, d in COLUMNS]
        lines.append(f"| {r['name']} | {steps:,} | {steps * batch:,} | {hours * threads:.2f} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


if __name__ == "__main__":
    main()
