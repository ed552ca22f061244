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


class BestHeldOut:
    """The weights of a fitted part at its lowest held-out loss so far, kept in a file beside the run's checkpoint (so a
    resumed fit still knows them). ``offer`` after each logged held-out loss; ``restore`` at the end loads them back,
    so the fit saves the part where it generalised best rather than where it stopped (early stopping on the held-out
    scenes of the training split, with the logged rows' granularity)."""

    def __init__(self, path: str | Path, prefix: str, record: dict, error: type[Exception] = ValueError):
        from prismonet.checkpoint import load_checkpoint

        self.path, self.prefix, self.record = Path(path), prefix, json.loads(json.dumps(record))
        self.step, self.loss = None, float("inf")
        if self.path.is_file():
            _, meta = load_checkpoint(self.path)
            if meta.get("record") != self.record:
                raise error(f"{self.path}: the best weights of a run with other settings; use a new folder")
            self.step, self.loss = int(meta["step"]), float(meta["held_out"])

    def offer(self, step: int, loss: float, module: torch.nn.Module) -> None:
        """Keep ``module``'s weights if ``loss`` is lower than every loss offered before (ties keep the earlier)."""
        from prismonet.checkpoint import save_checkpoint

        if loss < self.loss:
            save_checkpoint(self.path, {f"{self.prefix}{k}": v for k, v in module.state_dict().items()},
                            {"step": step, "held_out": loss, "record": self.record})
            self.step, self.loss = step, loss

    def restore(self, module: torch.nn.Module) -> None:
        """Load the kept weights into ``module`` (nothing offered yet: ``module`` stays as it is)."""
        from prismonet.checkpoint import load_checkpoint

        if self.step is None:
            return
        tensors, _ = load_checkpoint(self.path)
        module.load_state_dict({k[len(self.prefix):]: v for k, v in tensors.items() if k.startswith(self.prefix)})
