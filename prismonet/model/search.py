"""Test-time pose search (beyond the paper): gradient-free coordinate search on each slot's scale,
ground-plane position and yaw against the input RGB-D.

The encoder's slots come out too small, most of all at its last step (first 512 validation scenes:
the median predicted / true scale of matched objects is 0.86 at step 3), and a shrunken object fails
the IoU 0.5 test. Gradient refinement does not fix this reliably: its objective, the training loss,
is the same one that taught the encoder to hedge. Here each slot in turn is re-rendered alone at a
few trial scales (then positions), composed with the others by z-buffering, and scored with
``fit_score`` (unblurred colour MSE + 0.1 x depth L1); a trial is kept per scene
only when it lowers the score, so the search never makes the fit worse. Each trial costs one
single-object render, no gradients.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from prismonet.model.fit_score import fit_score
from prismonet.model.prismonet import ModelOutput, SceneLatents
from prismonet.render import SceneParams, composite, render_objects


@dataclass(frozen=True)
class SearchConfig:
    scales: tuple[float, ...] = (0.9, 1.1, 1.2, 1.3, 1.45)
    """Trial multipliers of a slot's scale (1 is the current scale and always a candidate)."""
    shifts: tuple[float, ...] = (-0.2, 0.2)
    """Trial offsets (world units) of a slot's position along world x, then y."""
    yaws: tuple[float, ...] = (-30.0, 30.0)
    """Trial rotations (degrees) of a slot about the vertical axis."""
    rounds: int = 3
    """Passes over all slots; a later pass starts from the previous one's result."""
    decay: float = 0.5
    """Each pass after the first takes steps this much smaller (pattern search): shifts and yaws are
    multiplied by ``decay ** r`` and scale multipliers raised to that power in pass ``r``."""
    w_image: float = 1.0
    w_depth: float = 0.1
    shape_trials: bool = False
    """Also try, once per slot in the first pass, the prior's training code nearest to the slot's
    shape latent within each shape category (sphere, cylinder, cube for Clevr): the encoder's
    latents drift towards one category (cubes come out nearest a cylinder code, EVALUATION.md)."""

    far_clip: bool = False
    """Score the render with its depth clipped at the model's ``far_depth``, like the sensor's (off by
    default: the recorded search figures were measured without it)."""

    def __post_init__(self) -> None:
        if self.rounds < 0 or any(s <= 0 for s in self.scales) or self.w_image < 0 or self.w_depth < 0 or not 0 < self.decay <= 1:
            raise ValueError(f"search: rounds and weights must be non-negative and scales positive, got {self}")

    @property
    def trials_per_slot(self) -> int:
        return len([s for s in self.scales if s != 1]) + 2 * len([d for d in self.shifts if d != 0]) + len([a for a in self.yaws if a != 0])


def _trials(cfg: SearchConfig, step: float, scale: torch.Tensor, position: torch.Tensor, cos_sin: torch.Tensor):
    """``(scale (B,), position (B, 3), cos_sin (B, 2))`` of each trial for one slot, with steps
    multiplied by ``step``."""
    for m in cfg.scales:
        if m != 1:
            yield scale * m**step, position, cos_sin
    for axis in (0, 1):
        for d in cfg.shifts:
            if d != 0:
                p = position.clone()
                p[:, axis] += d * step
                yield scale, p, cos_sin
    for a in cfg.yaws:
        if a != 0:
            c, s = math.cos(math.radians(a * step)), math.sin(math.radians(a * step))
            x, y = cos_sin.unbind(-1)
            yield scale, position, torch.stack([c * x - s * y, s * x + c * y], -1)


@torch.no_grad()
def search_latents(model, out: ModelOutput, batch, cfg: SearchConfig = SearchConfig(), use_depth: bool = True) -> ModelOutput:
    """``out`` (the model's output on ``batch``) with each slot's scale, position and yaw improved by
    coordinate search; every scene's score is at most the one it started with."""
    if cfg.rounds == 0 or (cfg.trials_per_slot == 0 and not cfg.shape_trials):
        return out
    p = out.latents.params
    B, N = p.scale.shape
    H, W = batch.rgb.shape[-2:]
    target_depth = batch.depth if use_depth and cfg.w_depth > 0 else None
    far = model.cfg.far_depth if cfg.far_clip else None
    bg = out.latents.bg_color
    depth, mask, color = out.obj_depth.clone(), out.obj_mask.clone(), out.obj_color.clone()
    scale, position, cos_sin, z_sh = p.scale.clone(), p.position.clone(), p.cos_sin.clone(), p.z_sh.clone()
    comp = composite(depth, mask, color, bg, out.bg_depth)
    best = fit_score(comp.image, comp.depth, batch.rgb, target_depth, cfg.w_image, cfg.w_depth, far)
    settings = model.render_settings()
    one = lambda t, k: None if t is None else t[:, k : k + 1]
    codes = model.prior.latents.to(p.z_sh.dtype)
    cats = torch.as_tensor(model.prior.category_ids)

    def attempt(k, z_try, s_try, p_try, cs_try):
        """Render slot ``k`` alone with the trial latents, keep them per scene where the score falls."""
        nonlocal best
        s_try = s_try.clamp(max=model.cfg.scale_range[1])  # the encoder's own bound
        q = SceneParams(z_try[:, None], one(p.z_tex, k), p_try[:, None], cs_try[:, None], s_try[:, None], one(p.axis, k),
                        one(p.active, k))
        obj = render_objects(model.sdf_fn, model.color_fn, q, batch.K, batch.T_world_cam, H, W, settings)
        d_try, m_try, c_try = depth.clone(), mask.clone(), color.clone()
        d_try[:, k], m_try[:, k], c_try[:, k] = obj.depth[:, 0], obj.mask[:, 0], obj.color[:, 0]
        c = composite(d_try, m_try, c_try, bg, out.bg_depth)
        score = fit_score(c.image, c.depth, batch.rgb, target_depth, cfg.w_image, cfg.w_depth, far)
        win = score < best
        best = torch.where(win, score, best)
        w = win.view(B, 1, 1)
        depth[:, k] = torch.where(w, d_try[:, k], depth[:, k])
        mask[:, k] = torch.where(w, m_try[:, k], mask[:, k])
        color[:, k] = torch.where(w[:, None], c_try[:, k], color[:, k])
        scale[:, k] = torch.where(win, s_try, scale[:, k])
        position[:, k] = torch.where(win[:, None], p_try, position[:, k])
        cos_sin[:, k] = torch.where(win[:, None], cs_try, cos_sin[:, k])
        z_sh[:, k] = torch.where(win[:, None], z_try, z_sh[:, k])

    for r in range(cfg.rounds):
        for k in range(N):
            if p.active is not None and not p.active[:, k].any():
                continue  # never decoded (a stopped encoder): nothing to search
            if cfg.shape_trials and r == 0:
                for c in torch.unique(cats):
                    sel = codes[cats == c]  # (n_c, D)
                    nearest = sel[torch.cdist(z_sh[:, k], sel).argmin(1)]  # (B, D)
                    attempt(k, nearest, scale[:, k], position[:, k], cos_sin[:, k])
            for s_try, p_try, cs_try in _trials(cfg, cfg.decay**r, scale[:, k], position[:, k], cos_sin[:, k]):
                attempt(k, z_sh[:, k], s_try, p_try, cs_try)
    params = SceneParams(z_sh, p.z_tex, position, cos_sin, scale, p.axis, p.active)
    comp = composite(depth, mask, color, bg, out.bg_depth)
    return ModelOutput(SceneLatents(params, bg), comp, depth, mask, color, out.bg_depth, None, slot_steps=out.slot_steps)
