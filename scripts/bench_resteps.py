"""What the encoder steps after refinement cost (``ModelConfig.reanchor_steps``): the feed-forward decoding of one model
on the same batches with its own setting, with it but every slot rendered again after each step and pass (as before
session 111, when only the changed slots are), and with ``reanchor_steps = 0``, alternating in one run; medians.

    python3 scripts/bench_resteps.py clevr5 data/clevr5_val109 --split val --rounds 7 --batch 50

Prints one row per setting (median ms per scene, min and max over the timed rounds) and the ratios of the medians.
Run it on a quiet machine (``uptime``): the figures go to BENCHMARKS.md, never into a test.
"""

from __future__ import annotations

import argparse
import statistics
import time
from dataclasses import replace

import torch

from prismonet.data.dataset import SceneDataset
from prismonet.model.io import load_model
from prismonet.model.prismonet import PriSMONet


def variant(model: PriSMONet, steps: int, render_all: bool = False) -> PriSMONet:
    m = PriSMONet(replace(model.cfg, reanchor_steps=steps), prior=model.prior)
    m.load_state_dict(model.state_dict())
    if render_all:  # the baseline: no slot's render reused
        m._render_changed = lambda out, params, changed, *a: PriSMONet._render_changed(m, out, params, None, *a)
    return m.eval()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("model", help="a shipped name or a run folder")
    ap.add_argument("data")
    ap.add_argument("--split", default="val")
    ap.add_argument("--rounds", type=int, default=7, help="batches per setting; the first of each is a warm-up")
    ap.add_argument("--batch", type=int, default=50)
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    if args.rounds < 2 or args.batch < 1 or args.threads < 1:
        raise SystemExit("bench_resteps: --rounds must be at least 2, --batch and --threads positive")
    torch.set_num_threads(args.threads)
    model, _ = load_model(args.model)
    if model.cfg.reanchor_steps == 0:
        raise SystemExit(f"bench_resteps: {args.model} takes no steps after refinement (reanchor_steps 0): "
                         "nothing to compare")
    ds = SceneDataset(args.data, split=args.split)
    if len(ds) < args.batch * args.rounds:
        raise SystemExit(f"bench_resteps: {args.data} {args.split} has {len(ds)} scenes, "
                         f"needs {args.batch * args.rounds}")
    n = model.cfg.reanchor_steps
    settings = {f"{n} steps": variant(model, n), f"{n} steps, all again": variant(model, n, True),
                "0 steps": variant(model, 0)}
    times: dict[str, list[float]] = {k: [] for k in settings}
    with torch.no_grad():
        for r in range(args.rounds):
            b = ds.batch(list(range(r * args.batch, (r + 1) * args.batch)))
            for name, m in settings.items():
                t0 = time.perf_counter()
                m(b.rgb, b.K, b.T_world_cam, b.ground_z)
                if r:  # the first round warms up
                    times[name].append(1000 * (time.perf_counter() - t0) / args.batch)
    med = {k: statistics.median(v) for k, v in times.items()}
    for k, v in times.items():
        print(f"{args.model:8s} {k:18s} ms per scene: median {med[k]:6.1f} (min {min(v):.1f}, max {max(v):.1f}), "
              f"{len(v)} batches of {args.batch}")
    a, full, none = med.values()
    print(f"{args.model}: the steps after refinement cost {a / none:.2f}x the decoding without them "
          f"({full / none:.2f}x rendering every slot again; {full / a:.2f}x speed-up)")


if __name__ == "__main__":
    main()
