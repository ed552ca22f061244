"""Training-step time with freed memory kept for reuse (``prismonet.allocator``) against glibc's default, in one run.

    python3 scripts/bench_malloc.py [--data data/clevr3] [--rounds 6] [--steps 20] [--threads 1,2]

The allocator is set per process, so each measurement is a fresh process: ``bench_step.py``'s step (the shipped
recipe, batch 8, from `clevr3_fc`'s weights), 3 warm-up steps, then ``--steps`` timed ones. The two settings alternate
(``PRISMONET_MALLOC=keep`` / ``default``), ``--rounds`` processes each per thread count, so that the host's load
drifts over both alike. The table gives, per setting, the median and minimum step over every timed step, and per step
the minor page faults, system and user CPU time (``getrusage``), and the largest resident set reached.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys

CHILD = """
import json, resource, sys, time
sys.path.insert(0, "scripts")
import torch
from prismonet.allocator import keep_freed_memory
applied = keep_freed_memory()
from bench_step import ShippedStep
torch.set_num_threads({threads})
step = ShippedStep({data!r})
for i in range(3):
    step(i)
r0 = resource.getrusage(resource.RUSAGE_SELF)
times = [step(100 + i) for i in range({steps})]
r1 = resource.getrusage(resource.RUSAGE_SELF)
n = len(times)
print(json.dumps({{"applied": applied, "times": times, "faults": (r1.ru_minflt - r0.ru_minflt) / n,
                  "sys": (r1.ru_stime - r0.ru_stime) / n, "user": (r1.ru_utime - r0.ru_utime) / n, "maxrss_mb": r1.ru_maxrss / 1024}}))
"""


def run_child(setting: str, threads: int, data: str, steps: int) -> dict:
    env = dict(os.environ, PRISMONET_MALLOC=setting, OMP_NUM_THREADS=str(threads))
    out = subprocess.run([sys.executable, "-c", CHILD.format(threads=threads, data=data, steps=steps)], env=env,
                         capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", default="data/clevr3")
    ap.add_argument("--rounds", type=int, default=6)
    ap.add_argument("--steps", type=int, default=20)
    ap.add_argument("--threads", default="1,2")
    args = ap.parse_args(argv)
    threads = [int(t) for t in args.threads.split(",")]
    if args.rounds <= 0 or args.steps <= 0 or any(t <= 0 for t in threads):
        print("bench_malloc: error: rounds, steps and thread counts must be positive", file=sys.stderr)
        return 2
    settings = ("default", "keep")
    runs = {(s, t): [] for s in settings for t in threads}
    for r in range(args.rounds):
        for t in threads:
            for s in (settings if r % 2 == 0 else settings[::-1]):
                runs[(s, t)].append(run_child(s, t, args.data, args.steps))
                print(f"round {r + 1}/{args.rounds}, {t} thread(s), {s}: median "
                      f"{1e3 * statistics.median(runs[(s, t)][-1]['times']):.1f} ms", file=sys.stderr)
    print(f"training step, batch 8, {args.rounds} processes x {args.steps} steps per setting and thread count")
    print("| threads | malloc | median ms | min ms | page faults / step | system ms / step | user ms / step | max RSS MB | speed-up |")
    print("|---|---|---|---|---|---|---|---|---|")
    for t in threads:
        base = statistics.median([x for r in runs[("default", t)] for x in r["times"]])
        for s in settings:
            rs = runs[(s, t)]
            times = [x for r in rs for x in r["times"]]
            med = statistics.median(times)
            label = s + ("" if all(r["applied"] == (s == "keep") for r in rs) else " (not applied)")
            print(f"| {t} | {label} | {1e3 * med:.1f} | {1e3 * min(times):.1f} | {statistics.median(r['faults'] for r in rs):.0f} | "
                  f"{1e3 * statistics.median(r['sys'] for r in rs):.1f} | {1e3 * statistics.median(r['user'] for r in rs):.1f} | "
                  f"{max(r['maxrss_mb'] for r in rs):.0f} | {base / med:.2f}x |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
