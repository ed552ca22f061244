"""Usage: python3 scripts/bench_search_plan.py CONFIG OUT.json [cuda|cpu] [BATCHES, e.g. 8,32,64]

Training-step time of CONFIG's model (its ``init_from`` weights) under the root search's block sizes and chunks, in one
run: medians of 15 steps after 5 warm-up on CUDA (2 after 1 on the CPU). The search finds the same crossings under
every plan; the loss of one fixed batch, printed per variant, shows it. "The CPU plan" is also what every device used
before session 50 (BENCHMARKS.md, "Training on a GPU", both tables)."""

import dataclasses
import json
import statistics
import sys

import torch

from prismonet.bench.train import step_from, timed_step
from prismonet.config import load_config
from prismonet.model.losses import compute_losses
from prismonet.model.trainer import TrainConfig

cfg = load_config(TrainConfig, sys.argv[1])
device = sys.argv[3] if len(sys.argv) > 3 else "cuda"
batches = [int(b) for b in sys.argv[4].split(",")] if len(sys.argv) > 4 else [8, 32, 64]
warm, n = (5, 15) if device == "cuda" else (1, 2)
VARIANTS = {"block 16K, chunk 4 (the CPU plan)": (16384, 4), "block 2M, chunk 4": (1 << 21, 4),
            "block 2M, all samples at once (the accelerator plan)": (1 << 21, 10_000), "block 256K, chunk 8": (1 << 18, 8)}
res = {"config": sys.argv[1], "torch": torch.__version__, "device": device,
       "gpu": torch.cuda.get_device_name(0) if device == "cuda" else None, "rows": []}
for B in batches:
    for name, (block, chunk) in VARIANTS.items():
        model, opt, ds = step_from(cfg, cfg.init_from, device)
        plan = model.render_settings
        model.render_settings = lambda plan=plan, block=block, chunk=chunk: dataclasses.replace(
            plan(), block_points=block, search_chunk=chunk)
        fixed = ds.batch(torch.randint(len(ds), (B,), generator=torch.Generator().manual_seed(123)).tolist()).to(device)
        with torch.no_grad():
            out = model(fixed.rgb, fixed.K, fixed.T_world_cam, fixed.ground_z)
            ref = float(compute_losses(model, out, fixed, cfg.loss, 5000, fixed.depth, None).total)
        times = [timed_step(model, opt, ds, cfg, B, s) for s in range(warm + n)][warm:]
        m = statistics.median(times)
        row = {"variant": name, "batch": B, "median_ms": round(1000 * m, 1), "images_per_s": round(B / m, 1),
               "loss_fixed_batch": ref}
        print(row, flush=True)
        res["rows"].append(row)
json.dump(res, open(sys.argv[2], "w"), indent=2)
