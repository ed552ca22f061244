"""Usage: python3 scripts/bench_rays.py CONFIG [--batches 8,64] [--rounds 5] [--steps 3] [--threads 2]

Training-step time of CONFIG's model (its ``init_from`` weights) with ``object_rays`` as it was at commit 4d22b9c (a
Python loop over the objects, one pixel grid each; read from git) against the current one-mask version, interleaved
in one run on the same batches; medians over every timed step. The two give identical rays (tests/test_render.py)."""

from __future__ import annotations

import argparse
import statistics
import subprocess
import time
import types

import torch

from prismonet.config import load_config
from prismonet.data.dataset import SceneDataset
from prismonet.model.io import load_model
from prismonet.model.losses import compute_losses
from prismonet.model.prismonet import PriSMONet
from prismonet.model.trainer import TrainConfig, make_inputs
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
ds = SceneDataset(cfg.data, cfg.split)
model = PriSMONet(cfg.model)
model.load_state_dict(load_model(cfg.init_from)[0].state_dict())
model.train()
opt = torch.optim.Adam([p for p in model.parameters() if p.requires_grad], lr=1e-6)
for B in map(int, args.batches.split(",")):
    times = {k: [] for k in VARIANTS}
    for r in range(args.rounds + 1):
        for name, fn in VARIANTS.items():
            renderer.object_rays = fn
            for s in range(args.steps):
                g = torch.Generator().manual_seed(1000 * r + s)
                t0 = time.perf_counter()
                batch = ds.batch(torch.randint(len(ds), (B,), generator=g).tolist())
                image, depth = make_inputs(batch, cfg, g)
                out = model(image, batch.K, batch.T_world_cam, batch.ground_z)
                terms = compute_losses(model, out, batch, cfg.loss, 5000, depth, None)
                opt.zero_grad(set_to_none=True)
                terms.total.backward()
                opt.step()
                if r > 0:  # round 0 warms up
                    times[name].append(time.perf_counter() - t0)
    base = statistics.median(times[next(iter(VARIANTS))])
    for name, t in times.items():
        m = statistics.median(t)
        print(f"| {B} | {name} | {1000 * m:.1f} | {base / m:.2f}x | {len(t)} |", flush=True)
renderer.object_rays = VARIANTS["one mask (now)"]
