"""Usage: python3 scripts/bench_rays.py CONFIG [--batches 8,64] [--rounds 5] [--steps 3] [--threads 2]

Training-step time of CONFIG's model (its ``init_from`` weights) with ``object_rays`` as it was at commit 4d22b9c (a
Python loop over the objects, one pixel grid each; read from git) against the current one-mask version, interleaved
in one run on the same batches; medians over every timed step. The two give identical rays (tests/test_render.py)."""

from __future__ import annotations

import argparse
import statistics
import subprocess
import types

import torch

from prismonet.bench.train import step_from, timed_step
from prismonet.config import load_config
from prismonet.model.trainer import TrainConfig
from prismonet.render import renderer

ap = argparse.ArgumentParser()
ap.add_argument("config")
ap.add_argument("--batches", default="8,64")
ap.add_argument("--rounds", type=int, default=5)
ap.add_argument("--steps", type=int, default=3)
ap.add_argument("--threads", type=int, default=2)
args = ap.parse_args()
torch.set_num_threads(args.threads)

old = types.ModuleType("rays_4d22b9c")
exec(subprocess.run(["git", "show", "4d22b9c:prismonet/render/rays.py"], capture_output=True, text=True, check=True).stdout,
     old.__dict__)
VARIANTS = {"loop over objects (4d22b9c)": old.object_rays, "one mask (now)": renderer.object_rays}
cfg = load_config(TrainConfig, args.config)
model, opt, ds = step_from(cfg, cfg.init_from)
for B in map(int, args.batches.split(",")):
    times = {k: [] for k in VARIANTS}
    for r in range(args.rounds + 1):  # round 0 warms up
        for name, fn in VARIANTS.items():
            renderer.object_rays = fn
            for s in range(args.steps):
                t = timed_step(model, opt, ds, cfg, B, 1000 * r + s)
                if r > 0:
                    times[name].append(t)
    base = statistics.median(times[next(iter(VARIANTS))])
    for name, t in times.items():
        m = statistics.median(t)
        print(f"| {B} | {name} | {1000 * m:.1f} | {base / m:.2f}x | {len(t)} |", flush=True)
renderer.object_rays = VARIANTS["one mask (now)"]
