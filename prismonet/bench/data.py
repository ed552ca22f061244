"""``prismonet bench data``: time to generate a CLEVR-style dataset, per worker count.

Each worker count is timed ``repeats`` times in one run, interleaved, and the median is
reported with its speed-up over the first worker count listed (the baseline).
"""

from __future__ import annotations

import platform
import shutil
import statistics
import tempfile
import time
from pathlib import Path

from prismonet.data.clevr import ClevrConfig
from prismonet.data.generate import generate_clevr


def bench_data(scenes: int, objects: int, workers: list[int], repeats: int) -> str:
    """Run the benchmark; returns a Markdown table."""
    if scenes <= 0 or repeats <= 0 or not workers or min(workers) <= 0:
        raise ValueError(f"scenes, repeats and workers must be positive, got {scenes}, {repeats}, {workers}")
    train, val = round(scenes * 0.72), round(scenes * 0.08)
    split = (train, val, scenes - train - val)
    times: dict[int, list[float]] = {w: [] for w in workers}
    for r in range(repeats):
        for w in workers:
            tmp = Path(tempfile.mkdtemp(prefix="prismonet-bench-"))
            try:
                t0 = time.perf_counter()
                generate_clevr(tmp / "ds", ClevrConfig(num_objects=objects), split=split, seed=r, workers=w, progress=False)
                times[w].append(time.perf_counter() - t0)
            finally:
                shutil.rmtree(tmp, ignore_errors=True)
            print(f"  repeat {r + 1}/{repeats}, workers={w}: {times[w][-1]:.1f} s", flush=True)
    base = statistics.median(times[workers[0]])
    lines = [
        f"{scenes} scenes, {objects} objects, 64x64, {repeats} repeats; machine: {platform.processor() or platform.machine()}",
        "",
        "| workers | median s | min s | max s | scenes/s | speed-up |",
        "|---|---|---|---|---|---|",
    ]
    for w in workers:
        med = statistics.median(times[w])
        lines.append(
            f"| {w} | {med:.1f} | {min(times[w]):.1f} | {max(times[w]):.1f} | {scenes / med:.0f} | {base / med:.2f}x |"
        )
    return "\n".join(lines)
