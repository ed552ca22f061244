"""Test-time colour fit (beyond the paper): gradient descent on the texture latents and the
background colour only, against the input image, with every object's shape, pose and scale held.

Geometry is fixed, so the scene is ray-cast once: the surface points that win the z-buffer stay
where they are, and each step only re-evaluates the texture field at them (``shade_winners``),
which costs a small fraction of a render; the output recolours the same hits (``shade_objects``). Instance masks and depth come out exactly as they went in;
only the colours change. The objective is the unblurred colour error (summed over channels, mean
over pixels), the quantity PSNR measures. Adam does not descend monotonically, so each scene keeps
the step at which its error was lowest: a scene's error never rises above where it started.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import torch

from prismonet.model.fit_score import fit_score
from prismonet.model.prismonet import ModelOutput, SceneLatents
from prismonet.render.composite import composite, zbuffer
from prismonet.render.renderer import render_objects, shade_objects, shade_winners


@dataclass(frozen=True)
class ColorFitConfig:
    steps: int = 50
    """Adam steps (each one texture-field evaluation at the visible surface points)."""
    lr: float = 0.05
    """Adam step size of the texture latents and the background colour (chosen on 128 validation
    scenes after the pose search: 50 steps at 0.05 gave +0.77 dB; 200 steps, +0.83 dB; EVALUATION.md)."""

    def __post_init__(self) -> None:
        if self.steps < 0 or not self.lr > 0:
            raise ValueError(f"color fit: steps must be >= 0 and lr > 0, got {self.steps}, {self.lr}")


def color_error(image: torch.Tensor, rgb: torch.Tensor) -> torch.Tensor:
    """``(B,)`` squared colour error summed over channels, mean over pixels: ``fit_score`` without depth."""
    return fit_score(image, None, rgb, None)


def fit_colors(model, out: ModelOutput, batch, cfg: ColorFitConfig = ColorFitConfig()) -> ModelOutput:
    """``out`` (the model's output on ``batch``, any geometry) with its texture latents and
    background colour fitted to ``batch.rgb`` for ``cfg.steps`` steps; geometry unchanged."""
    if cfg.steps == 0:
        return out
    p = out.latents.params
    H, W = batch.rgb.shape[-2:]
    rgb = batch.rgb.to(p.z_tex.dtype)
    with torch.no_grad():
        obj = render_objects(model.sdf_fn, None, p, batch.K, batch.T_world_cam, H, W, model.render_settings())
        winner, hit = zbuffer(obj.depth, obj.mask)
    z = p.z_tex.detach().clone().requires_grad_(True)
    bg = out.latents.bg_color.detach().clone().requires_grad_(True)
    best_z, best_bg = z.detach().clone(), bg.detach().clone()
    best = torch.full((rgb.shape[0],), float("inf"), dtype=rgb.dtype, device=rgb.device)
    opt = torch.optim.Adam([z, bg], lr=cfg.lr)
    with torch.enable_grad():
        for i in range(cfg.steps + 1):  # the last pass only scores the final step
            err = color_error(shade_winners(model.color_fn, replace(p, z_tex=z), obj, bg, winner, hit), rgb)
            with torch.no_grad():
                better = err.detach() < best
                best = torch.where(better, err.detach(), best)
                best_z[better], best_bg[better] = z.detach()[better], bg.detach()[better]
            if i == cfg.steps:
                break
            opt.zero_grad(set_to_none=True)
            err.sum().backward()
            opt.step()
            with torch.no_grad():
                bg.clamp_(0.0, 1.0)
    with torch.no_grad():  # recolour the same hits: no second ray cast
        params = replace(p, z_tex=best_z)
        color = shade_objects(model.color_fn, params, obj)
        comp = composite(obj.depth, obj.mask, color, best_bg, out.bg_depth)
    return ModelOutput(SceneLatents(params, best_bg), comp, obj.depth, obj.mask, color, out.bg_depth, obj.soft_mask,
                       slot_steps=out.slot_steps)
