"""What the far-clip and seek terms add to a training step: forward + backward of one model on the same
batches, with and without ``loss.far_clip`` and ``loss.w_seek``, alternating in one run; medians.

    python3 scripts/bench_seek.py runs/clevr1to8 data/clevr1to8 --rounds 6
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

from prismonet.data.dataset import SceneDataset
from prismonet.model.io import load_model
from prismonet.model.losses import LossConfig, compute_losses


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("model")
    ap.add_argument("data")
    ap.add_argument("--rounds", type=int, default=6, help="batches; the first is a warm-up")
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--w-seek", type=float, default=0.01)
    args = ap.parse_args()
    if args.rounds < 2 or args.batch < 1:
        raise SystemExit("bench_seek: --rounds must be at least 2 and --batch positive")
    torch.set_num_threads(1)
    net, _ = load_model(args.model)
    net.train()
    ds = SceneDataset(args.data, "train")
    ways = {"without": LossConfig(w_mask=0.1, mask_from_depth=True),
            "far_clip + seek": LossConfig(w_mask=0.1, mask_from_depth=True, far_clip=True, w_seek=args.w_seek)}
    times = {k: [] for k in ways}
    for r in range(args.rounds):
        b = ds.batch(list(range(args.batch * r, args.batch * (r + 1))))
        for name, cfg in ways.items():
            net.zero_grad()
            t0 = time.perf_counter()
            out = net(b.rgb, b.K, b.T_world_cam, b.ground_z)
            compute_losses(net, out, b, cfg, 10**6).total.backward()
            times[name].append(time.perf_counter() - t0)
    med = {k: 1000 * statistics.median(v[1:]) for k, v in times.items()}
    for k, v in med.items():
        print(f"{k}: {v:.1f} ms per step (median of {args.rounds - 1})")
    print(f"ratio: {med['far_clip + seek'] / med['without']:.3f}x")


if __name__ == "__main__":
    main()
