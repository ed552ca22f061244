"""The thread governor's rules against fixed thread counts, on real training steps, quiet or loaded.

    python3 scripts/bench_governor.py [--data data/clevr3] [--rounds 4] [--block 50] [--load]

Each variant runs ``--block`` ordinary training steps of the shipped recipe in turn (the steps of
``scripts/bench_step.py``), ``--rounds`` times, so that the host's load drifts over all alike; a
governor keeps its state from one block to its next. ``--load`` starts one pure-Python busy loop (a
second process on one of the two cores) for the whole run. The table gives each variant's mean time per
step over all its steps, the governor's probes included, and how many probes it ran. Variants: ``1`` and
``2`` threads fixed; ``eager``: the governor before session 42 (a probe every 200 steps, and at once after
one slow step); ``backoff``: the rule of sessions 42-58 (the wait doubles to 1,600 steps while probes keep the
choice; two slow steps in a row start an early probe); ``cut``: the default now (session 59), ``backoff`` with a
probe that stops timing a candidate whose first step is 1.5x slower than one already timed.

The step is the code as it is (``bench_step.py``'s last variant; before session 59 this script switched the losses
back to the kornia blur, so session 58's governor figures timed that older step).
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys

import torch

sys.path.insert(0, __file__.rsplit("/", 1)[0])
from bench_step import VARIANTS, ShippedStep, configure  # noqa: E402  (the same step, the code as it is)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", default="data/clevr3")
    ap.add_argument("--rounds", type=int, default=4)
    ap.add_argument("--block", type=int, default=50)
    ap.add_argument("--load", action="store_true")
    ap.add_argument("--variants", default="1,2,eager,backoff,cut")
    args = ap.parse_args()
    if args.rounds <= 0 or args.block <= 0:
        print("bench_governor: error: --rounds and --block must be positive", file=sys.stderr)
        return 2

    from prismonet.threads import ThreadGovernor

    configure(VARIANTS[-1])
    step = ShippedStep(args.data)

    names = args.variants.split(",")
    govs = {"eager": ThreadGovernor((1, 2), max_period=200, slow_steps=1, cut_factor=None),
            "backoff": ThreadGovernor((1, 2), cut_factor=None), "cut": ThreadGovernor((1, 2))}
    bad = [n for n in names if n not in ("1", "2", *govs)]
    if bad:
        print(f"bench_governor: error: unknown variants {bad}", file=sys.stderr)
        return 2
    load = subprocess.Popen([sys.executable, "-c", "while True: pass"]) if args.load else None
    times: dict[str, list[float]] = {n: [] for n in names}
    try:
        step(0)  # warm up
        for r in range(args.rounds):
            for n in names:
                gov = govs.get(n)
                if gov is None:
                    torch.set_num_threads(int(n))
                else:
                    gov._current = None  # another variant changed the count: set it again
                for i in range(args.block):
                    if gov is not None:
                        gov.before_step()
                    t = step(1 + 1000 * r + i)
                    if gov is not None:
                        gov.after_step(t)
                    times[n].append(t)
    finally:
        if load is not None:
            load.kill()
    state = "loaded (one busy process)" if args.load else "quiet"
    print(f"training step, batch {step.cfg.batch_size}, {state}, {args.rounds} x {args.block} steps per variant")
    print("| variant | mean ms per step | median | probes |")
    print("|---|---|---|---|")
    for n in names:
        probes = len(govs[n].history) if n in govs else ""
        print(f"| {n} | {1e3 * statistics.mean(times[n]):.1f} | {1e3 * statistics.median(times[n]):.1f} | {probes} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
