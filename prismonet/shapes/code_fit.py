"""Encoding a shape the prior was not trained on: its code by gradient descent on the shape's SDF samples, the
decoder frozen (DeepSDF's inference step). What a prior can draw of a shape it never saw is the most a scene model
built on it can recover of that shape."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from prismonet.shapes.pretrain import clamped_l1


@dataclass(frozen=True)
class CodeFitConfig:
    steps: int = 800
    lr: float = 5e-3
    """Adam on the code; divided by 10 for the last fifth of the steps (DeepSDF's schedule)."""
    points: int = 4096
    """SDF samples per step, drawn at random from the shape's."""
    clamp_delta: float = 0.1
    """The prior's training clamp (``PretrainConfig.clamp_delta``)."""
    code_reg: float = 1e-4
    """Weight of the code's squared norm."""
    seed: int = 0

    def __post_init__(self) -> None:
        if self.steps <= 0 or not self.lr > 0 or self.points <= 0 or not self.clamp_delta > 0 or self.code_reg < 0:
            raise ValueError(f"code fit: steps, lr, points and clamp_delta must be positive and code_reg >= 0, got {self}")


def fit_code(prior, points: torch.Tensor, sdf: torch.Tensor, cfg: CodeFitConfig = CodeFitConfig()) -> tuple[torch.Tensor, float]:
    """The code ``(D,)`` of the shape sampled by ``points (N, 3)`` and ``sdf (N,)`` (its object frame, the prior's
    normalisation), started at the mean of the prior's training codes; and its clamped L1 on all the samples."""
    if points.dim() != 2 or points.shape[-1] != 3 or sdf.shape != points.shape[:1]:
        raise ValueError(f"fit_code: expected points (N, 3) and sdf (N,), got {tuple(points.shape)} and {tuple(sdf.shape)}")
    gen = torch.Generator().manual_seed(cfg.seed)
    z = prior.latents.detach().mean(0).clone().requires_grad_(True)
    opt = torch.optim.Adam([z], lr=cfg.lr)
    with torch.enable_grad():
        for step in range(cfg.steps):
            if step == (4 * cfg.steps) // 5:
                opt.param_groups[0]["lr"] = cfg.lr / 10
            idx = torch.randint(0, len(points), (min(cfg.points, len(points)),), generator=gen)
            pred = prior.sdf(z.expand(len(idx), -1), points[idx])
            loss = clamped_l1(pred, sdf[idx], cfg.clamp_delta) + cfg.code_reg * (z ** 2).sum()
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
    with torch.no_grad():
        err = float(clamped_l1(prior.sdf(z.expand(len(points), -1), points), sdf, cfg.clamp_delta))
    return z.detach(), err


def nearest_code(prior, points: torch.Tensor, sdf: torch.Tensor, clamp_delta: float = 0.1) -> tuple[int, float]:
    """The index of the prior's training code whose SDF fits the samples best (clamped L1), and that error: what a
    search over the training codes (``--search-shapes``) can give a shape."""
    errs = []
    with torch.no_grad():
        for z in prior.latents.detach():
            errs.append(float(clamped_l1(prior.sdf(z.expand(len(points), -1), points), sdf, clamp_delta)))
    best = min(range(len(errs)), key=errs.__getitem__)
    return best, errs[best]
