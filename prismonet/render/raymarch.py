"""Root search along rays: equidistant samples, first sign change, optional bisection, and the
differentiable linear interpolation of the paper.

The search runs without autograd, in blocks. Only the two samples that bracket the crossing are
evaluated again with autograd, and the surface depth is their linear interpolation,
``t* = t_a + (t_b - t_a) f_a / (f_a - f_b)``. Its gradient is the one that running every sample
under autograd would give, since the other samples do not enter ``t*``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import torch

SdfFn = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]
"""``sdf_fn(z_sh (R, D), x_obj (R, S, 3)) -> (R, S)`` signed distance in object units."""

SEARCH_CHUNK = 4
"""Samples per ray evaluated at a time on the CPU, front to back. A ray stops once it has a crossing: every
sample before its first sign change is still evaluated, so the result is that of the full
search, and rays that hit early skip the rest."""

BLOCK_POINTS = 16384
"""SDF evaluations per block on the CPU: the buffers stay cache-sized."""

ACCEL_BLOCK_POINTS = 1 << 21
"""SDF evaluations per block on an accelerator, where every sample of a ray is evaluated at once: a GPU step is
bound by kernel launches and host syncs, not arithmetic, so fewer and larger blocks pay (BENCHMARKS.md, "Training on
a GPU": 3.3x faster steps at batch 64 on an H200, the same losses)."""


def search_plan(device: torch.device, samples: int, block_points: int = 0, chunk: int = 0) -> tuple[int, int]:
    """``(block_points, chunk)`` of the root search: the values given, or for 0 the device's (on the CPU
    ``BLOCK_POINTS`` and ``SEARCH_CHUNK``; elsewhere ``ACCEL_BLOCK_POINTS`` and all ``samples`` at once).
    The crossings found are the same either way."""
    cpu = device.type == "cpu"
    block = block_points if block_points > 0 else (BLOCK_POINTS if cpu else ACCEL_BLOCK_POINTS)
    step = chunk if chunk > 0 else (SEARCH_CHUNK if cpu else samples)
    return block, min(step, samples)

EPS_DENOM = 1e-9
"""Lower bound of ``f_a - f_b`` in the interpolation. The search guarantees ``f_a > 0 >= f_b``,
but the autograd re-evaluation can round differently (other batch shapes), so the difference
can reach 0; the bound keeps the weight finite, and the weight is clamped to [0, 1]."""


@dataclass
class Crossings:
    """Rays with a crossing: index into the ray bundle, and the bracket ``[t_a, t_b]`` (detached).
    With ``track_min``, also the rays without one (``miss_ray``) and their sample of least SDF
    (``t_min``), for soft silhouettes."""

    ray: torch.Tensor
    t_a: torch.Tensor
    t_b: torch.Tensor
    sdf_evals: int
    miss_ray: torch.Tensor | None = None
    t_min: torch.Tensor | None = None


@torch.no_grad()
def find_crossings(
    sdf_fn: SdfFn, z: torch.Tensor, o: torch.Tensor, d: torch.Tensor, t_near: torch.Tensor, t_far: torch.Tensor,
    samples: int, refine_steps: int = 0, block_points: int = 0, track_min: bool = False,
    chunk: int = 0,
) -> Crossings:
    """First +/- sign change of the SDF along each ray, from ``samples`` equidistant samples.

    Args:
        sdf_fn: the SDF callable (object frame).
        z: ``(R, D)`` shape latent per ray.
        o, d: ``(R, 3)`` ray origin and direction in the object frame; ``x(t) = o + t d``.
        t_near, t_far: ``(R,)`` interval; samples at ``t_near + j (t_far - t_near) / (samples - 1)``.
        samples: samples per ray (>= 2).
        refine_steps: bisection steps on the bracket after the search.
        block_points: SDF evaluations per block (bounds memory, keeps buffers cache-sized; 0: by device,
            ``search_plan``).
        track_min: also return, for rays without a crossing, the sample with the least SDF.
        chunk: samples per ray evaluated at a time (0: by device, ``search_plan``; >= samples: all at once,
            the plain search that the chunked one reproduces).
    """
    if samples < 2:
        raise ValueError(f"samples per ray must be at least 2, got {samples}")
    R = o.shape[0]
    dev = o.device
    frac = torch.linspace(0.0, 1.0, samples, dtype=o.dtype, device=dev)
    block_points, chunk = search_plan(dev, samples, block_points, chunk)
    rays_per_block = max(1, block_points // chunk)  # ~block_points per SDF call
    # start from empty tensors so that zero rays (all slots culled) give zero crossings
    hit_idx = [torch.zeros(0, dtype=torch.long, device=dev)]
    ta_all = [torch.zeros(0, dtype=o.dtype, device=dev)]
    tb_all = [torch.zeros(0, dtype=o.dtype, device=dev)]
    evals = 0
    miss_all = [torch.zeros(0, dtype=torch.long, device=dev)]
    tmin_all = [torch.zeros(0, dtype=o.dtype, device=dev)]
    for s in range(0, R, rays_per_block):
        sl = slice(s, min(s + rays_per_block, R))
        t = t_near[sl, None] + (t_far[sl] - t_near[sl])[:, None] * frac  # (r, S)
        o_b, d_b, z_b = o[sl], d[sl], z[sl]
        active = torch.arange(t.shape[0], device=dev)
        last_pos = torch.zeros(t.shape[0], dtype=torch.bool, device=dev)  # sign of each ray's previous sample
        best_f = torch.full((t.shape[0],), float("inf"), dtype=o.dtype, device=dev)
        best_t = t[:, 0].clone()
        for c0 in range(0, samples, chunk):
            c1 = min(c0 + chunk, samples)
            ta = t[active, c0:c1]  # (n, c)
            f = sdf_fn(z_b[active], o_b[active, None, :] + ta[..., None] * d_b[active, None, :])
            evals += f.numel()
            pos = f > 0
            if c0 > 0:  # the pair straddling the chunk boundary counts too
                pos = torch.cat([last_pos[active, None], pos], dim=1)
            change = pos[:, :-1] & ~pos[:, 1:]  # outside -> inside between samples j and j+1
            has = change.any(dim=1)
            j = change.to(torch.uint8).argmax(dim=1) + (c0 - 1 if c0 > 0 else 0)  # first change
            rows = active[has]
            hit_idx.append(rows + s)
            ta_all.append(t[rows, j[has]])
            tb_all.append(t[rows, j[has] + 1])
            last_pos[active] = pos[:, -1]
            if track_min:
                fmin, jmin = f.min(dim=1)
                better = fmin < best_f[active]
                best_f[active[better]] = fmin[better]
                best_t[active[better]] = ta[better, jmin[better]]
            active = active[~has]
            if active.numel() == 0:
                break
        if track_min:
            miss_all.append(active + s)
            tmin_all.append(best_t[active])
    order = torch.argsort(torch.cat(hit_idx))
    ray = torch.cat(hit_idx)[order]
    t_a = torch.cat(ta_all)[order]
    t_b = torch.cat(tb_all)[order]
    for _ in range(refine_steps):
        if ray.numel() == 0:
            break
        tm = 0.5 * (t_a + t_b)
        fm = torch.cat([
            sdf_fn(z[ray[s : s + block_points]], (o[ray[s : s + block_points]] + tm[s : s + block_points, None] * d[ray[s : s + block_points]])[:, None, :])[:, 0]
            for s in range(0, ray.numel(), block_points)
        ])
        outside = fm > 0
        t_a = torch.where(outside, tm, t_a)
        t_b = torch.where(outside, t_b, tm)
        evals += ray.numel()
    if not track_min:
        return Crossings(ray, t_a, t_b, evals)
    return Crossings(ray, t_a, t_b, evals, torch.cat(miss_all), torch.cat(tmin_all))


def linear_root(t_a: torch.Tensor, t_b: torch.Tensor, f_a: torch.Tensor, f_b: torch.Tensor) -> torch.Tensor:
    """Zero of the line through ``(t_a, f_a)`` and ``(t_b, f_b)``, kept inside ``[t_a, t_b]``."""
    w = (f_a / (f_a - f_b).clamp_min(EPS_DENOM)).clamp(0.0, 1.0)
    return t_a + w * (t_b - t_a)


def interpolate_surface(
    sdf_fn: SdfFn, z: torch.Tensor, o: torch.Tensor, d: torch.Tensor, t_a: torch.Tensor, t_b: torch.Tensor
) -> torch.Tensor:
    """Differentiable surface parameter ``t*`` ``(n,)`` from the bracket, by linear interpolation.

    ``z``, ``o``, ``d`` carry gradients (latent, pose); ``t_a``, ``t_b`` are constants.
    """
    x = torch.stack([o + t_a[:, None] * d, o + t_b[:, None] * d], dim=1)  # (n, 2, 3)
    f = sdf_fn(z, x)
    return linear_root(t_a, t_b, f[:, 0], f[:, 1])
