"""The training step on two cores: one process of 2 threads against two processes of 1 thread (DDP, gloo).

    python3 scripts/bench_ddp.py [--data data/clevr3] [--rounds 3] [--steps 20] [--load]

The step is the trainer's (``prismonet.model.trainer``): the inputs of step ``t`` from ``_step_inputs`` (the global
batch's draws, each rank keeping its share), the forward pass, every loss of ``configs/clevr3_shipped.json`` at its
final schedule, backward, clipping and fused Adam, batch 8, from ``clevr3_fc``'s weights (``bench_step.py``'s step).
Variants, run in turn ``--rounds`` times so that the host's load drifts over them alike:

- ``1x2``: one process, 2 threads (the trainer's ``threads: 2``);
- ``2x1``: two processes of one thread each under ``DistributedDataParallel`` (``torchrun --nproc_per_node 2``),
  each with half the batch; the gradients are averaged in DDP's all-reduce during backward;
- ``1x1``: one process, one thread (with ``--load``: what the thread governor falls back to).

Each process times its steps after a barrier; the table gives medians over every step but each block's first three.
``--load`` starts one pure-Python busy loop (a third process) for the whole run.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import time

import torch

sys.path.insert(0, __file__.rsplit("/", 1)[0])

WARM = 3
"""Steps at the start of each block left out of the medians (first calls, allocator warm-up)."""


def _steps(data: str, first: int, count: int, threads: int, rank: int = 0, world: int = 1) -> list[float]:
    """Seconds per step of the trainer's step, steps ``first .. first + count - 1`` (rank ``rank`` of ``world``)."""
    from bench_step import ShippedStep, configure
    from prismonet.allocator import keep_freed_memory
    from prismonet.model.losses import compute_losses
    from prismonet.model.trainer import _step_inputs

    keep_freed_memory()
    torch.set_num_threads(threads)
    configure("poolfirst")
    s = ShippedStep(data)
    cfg, model, dev = s.cfg, s.model, torch.device("cpu")
    net = torch.nn.parallel.DistributedDataParallel(model) if world > 1 else model  # as the trainer wraps it
    times = []
    for t in range(first, first + count):
        if world > 1:
            torch.distributed.barrier()
        t0 = time.perf_counter()
        batch, _, image, depth = _step_inputs(s.ds, None, cfg, t, dev, rank, world)
        out = net(image, batch.K, batch.T_world_cam, batch.ground_z)
        terms = compute_losses(model, out, batch, cfg.loss, cfg.steps, depth)
        s.opt.zero_grad(set_to_none=True)
        terms.total.backward()
        torch.nn.utils.clip_grad_norm_(s.params, cfg.grad_clip)
        s.opt.step()
        times.append(time.perf_counter() - t0)
    return times[WARM:]


def _rank(rank: int, data: str, first: int, count: int, port: int, queue) -> None:
    os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port))
    torch.distributed.init_process_group("gloo", rank=rank, world_size=2)
    try:
        times = _steps(data, first, count, 1, rank, 2)
        if rank == 0:
            queue.put(times)
    finally:
        torch.distributed.destroy_process_group()


def _in_processes(data: str, first: int, count: int, port: int) -> list[float]:
    import torch.multiprocessing as mp

    queue = mp.get_context("spawn").SimpleQueue()
    mp.spawn(_rank, args=(data, first, count, port, queue), nprocs=2, join=True)
    return queue.get()


def _alone(data: str, first: int, count: int, threads: int) -> list[float]:
    """One process of ``threads`` threads, fresh like the DDP ranks (a child, so the variants start alike)."""
    import torch.multiprocessing as mp

    ctx = mp.get_context("spawn")
    queue = ctx.SimpleQueue()
    p = ctx.Process(target=_alone_child, args=(data, first, count, threads, queue))
    p.start()
    times = queue.get()
    p.join()
    return times


def _alone_child(data: str, first: int, count: int, threads: int, queue) -> None:
    queue.put(_steps(data, first, count, threads))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", default="data/clevr3")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--steps", type=int, default=20)
    ap.add_argument("--load", action="store_true")
    ap.add_argument("--variants", default="1x2,2x1")
    ap.add_argument("--port", type=int, default=29541)
    args = ap.parse_args()
    names = args.variants.split(",")
    if args.rounds <= 0 or args.steps <= WARM or any(n not in ("1x2", "2x1", "1x1") for n in names):
        print(f"bench_ddp: error: --rounds > 0, --steps > {WARM}, variants among 1x2, 2x1, 1x1; got {args.variants!r}",
              file=sys.stderr)
        return 2
    load = subprocess.Popen([sys.executable, "-c", "while True: pass"]) if args.load else None
    times: dict[str, list[float]] = {n: [] for n in names}
    try:
        for r in range(args.rounds):
            for n in names:  # the same steps for every variant within a round
                first = 100 * r
                got = (_in_processes(args.data, first, args.steps, args.port + r) if n == "2x1"
                       else _alone(args.data, first, args.steps, int(n[-1])))
                times[n] += got
                print(f"round {r} {n}: median {1e3 * statistics.median(got):.1f} ms", file=sys.stderr)
    finally:
        if load is not None:
            load.kill()
    from bench_step import print_table

    state = "loaded (one busy process)" if args.load else "quiet"
    print(f"training step, batch 8, {state}, {args.rounds} x {args.steps - WARM} steps per variant")
    print_table(times, names, "processes x threads")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
