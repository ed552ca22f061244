"""The step loop shared by the fits of one part of a trained model, the rest frozen (the refiner,
``prismonet.model.refiner_fit``; the colour step, ``prismonet.model.color_step_fit``): a step size per step, one descent
step per batch, a logged row and an atomic checkpoint every so many steps, and a checkpoint on interrupt."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Callable

import torch


def batch_indices(seed: int, step: int, count: int, batch_size: int) -> torch.Tensor:
    """``(batch_size,)`` scene indices in ``[0, count)`` for ``step``: a function of the seed and the step alone, so a
    resumed run draws the batches the uninterrupted one would have."""
    gen = torch.Generator().manual_seed(seed * 1_000_003 + step)
    return torch.randint(0, count, (batch_size,), generator=gen)


def append_row(log: Path, row: dict) -> None:
    with log.open("a") as f:
        f.write(json.dumps(row) + "\n")


def read_rows(log: Path) -> list[dict]:
    return [json.loads(line) for line in log.read_text().splitlines() if line.strip()]


def fit_steps(step: int, steps: int, opt: torch.optim.Optimizer, lr_at: Callable[[int], float],
              loss_at: Callable[[int], torch.Tensor], every: int, report: Callable[[int, float], str],
              save: Callable[[int], None], desc: str, progress: bool = True) -> int:
    """Optimise from ``step`` to ``steps``: each step sets the step size ``lr_at(step)`` and takes the scalar
    ``loss_at(step)`` down once; every ``every`` steps and at the last, ``report(step, mean training loss)`` logs a row
    (it returns the progress bar's note) and ``save(step)`` checkpoints. An interrupt checkpoints, then propagates.
    Returns the step reached."""
    from tqdm import tqdm

    losses: list[float] = []
    bar = tqdm(total=steps, initial=step, desc=desc, unit="step", disable=not progress)
    try:
        while step < steps:
            for g in opt.param_groups:
                g["lr"] = lr_at(step)
            loss = loss_at(step)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            losses.append(float(loss.detach()))
            step += 1
            bar.update(1)
            if step % every == 0 or step == steps:
                bar.set_postfix_str(report(step, sum(losses) / len(losses)))
                losses = []
                save(step)
    except KeyboardInterrupt:
        save(step)
        raise
    finally:
        bar.close()
    return step
