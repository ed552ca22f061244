"""GENESIS training step with the spatial broadcast decoder computed untiled (the code) against the
tiled latent (``BroadcastDecoder.tiled``, as before), interleaved in one run on the same batches.

    python3 scripts/bench_broadcast.py [--rounds 5] [--steps 2] [--threads 1]
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

from prismonet.baselines.blocks import BroadcastDecoder
from prismonet.baselines.genesis import Genesis, GenesisConfig
from prismonet.data.dataset import SceneDataset


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default="data/clevr3")
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--steps", type=int, default=2)
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    model = Genesis(GenesisConfig())
    opt = torch.optim.Adam(model.parameters(), lr=1e-4)
    ds = SceneDataset(args.data, "train")
    untiled = BroadcastDecoder.forward
    times: dict[str, list[float]] = {"tiled (before)": [], "untiled": []}
    for r in range(args.rounds + 1):  # round 0 warms up
        for name in times:
            BroadcastDecoder.forward = BroadcastDecoder.tiled if name.startswith("tiled") else untiled
            for i in range(args.steps):
                first = 8 * (r * args.steps + i)
                rgb = ds.batch(list(range(first, first + 8))).rgb
                t = time.perf_counter()
                loss = model.loss(rgb, torch.Generator().manual_seed(i))
                opt.zero_grad(set_to_none=True)
                loss.backward()
                opt.step()
                if r > 0:
                    times[name].append(time.perf_counter() - t)
    BroadcastDecoder.forward = untiled
    base = statistics.median(times["tiled (before)"])
    print(f"GENESIS training step, batch 8, {args.threads} thread(s), {args.rounds} x {args.steps} steps each")
    print("| decoder | median ms | speed-up |")
    print("|---|---|---|")
    for name, v in times.items():
        print(f"| {name} | {1e3 * statistics.median(v):.0f} | {base / statistics.median(v):.2f}x |")


if __name__ == "__main__":
    main()
