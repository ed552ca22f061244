"""Test-time refinement (beyond the paper): gradient descent on the encoder's scene latents
against the input RGB-D, through the differentiable renderer.

The encoder's output is the starting point; shape and texture latents, poses, scales and the
background colour are then optimised with Adam (poses at a larger step) for ``steps`` steps on
the training losses at their end-of-training schedule (least blur, final shape-regulariser weight). The network weights
stay fixed. Without depth (real photos) only the image term is used.

Only what a test input gives may enter (``test_time_losses``): the supervised terms a model may have been
trained with (L_pose on true poses, L_mask on true masks, the distillation targets) are left out, and
L_mask, where the model was trained with it, reads the silhouette off the input depth.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import torch

from prismonet.model.losses import LossConfig, compute_losses
from prismonet.model.prismonet import ModelOutput, SceneLatents
from prismonet.render import RenderSettings, SceneParams, composite, render_objects
from prismonet.render.background import plane_depth

FINAL_STEP = 10**9
"""Schedule step at which blur and shape weight have reached their final values."""


@dataclass(frozen=True)
class RefineConfig:
    steps: int = 10
    lr: float = 0.01
    """Adam step size of the shape and texture latents, scales and background colour."""
    pose_lr_scale: float = 3.0
    """Positions and in-plane rotations step at ``lr * pose_lr_scale`` (world units / unit circle).
    The encoder's largest residual errors are misplaced objects, and a faster pose step fixes more
    of them in K steps (first 64 test scenes, K=10: AP0.5 0.867 at x1, 0.911 at x3; EVALUATION.md)."""
    min_scale: float = 0.05

    def __post_init__(self) -> None:
        if self.steps < 0 or self.lr <= 0 or self.pose_lr_scale <= 0:
            raise ValueError("refine: steps must be >= 0, lr and pose_lr_scale > 0, got "
                             f"{self.steps}, {self.lr}, {self.pose_lr_scale}")


def render_latents(model, params: SceneParams, bg_color: torch.Tensor, K: torch.Tensor, T_world_cam: torch.Tensor,
                   ground_z: torch.Tensor, height: int, width: int, settings: RenderSettings | None = None) -> ModelOutput:
    """Render given latents with the model's renderer (or ``settings``) into a ``ModelOutput``, as its forward pass does."""
    settings = model.render_settings() if settings is None else settings
    obj = render_objects(model.sdf_fn, model.color_fn, params, K, T_world_cam, height, width, settings)
    bg_depth = plane_depth(K, T_world_cam, height, width, ground_z, settings.far_depth)
    comp = composite(obj.depth, obj.mask, obj.color, bg_color, bg_depth)
    return ModelOutput(SceneLatents(params, bg_color), comp, obj.depth, obj.mask, obj.color, bg_depth, obj.soft_mask)


def test_time_losses(loss_cfg: LossConfig, use_depth: bool, soft_silhouettes: bool) -> LossConfig:
    """``loss_cfg`` with every term that reads more than the input RGB(-D) switched off: L_pose (true
    poses), the distillation regression, L_mask unless it can take its silhouettes from the input depth
    (then it does, whatever the model was trained with), and the depth terms without depth."""
    return replace(loss_cfg, use_depth=loss_cfg.use_depth and use_depth, w_pose=0.0, w_distill=0.0,
                   w_mask=loss_cfg.w_mask if use_depth and soft_silhouettes else 0.0, mask_from_depth=True)


def refine(model, out: ModelOutput, batch, loss_cfg: LossConfig, cfg: RefineConfig = RefineConfig(),
           use_depth: bool = True) -> ModelOutput:
    """Refine ``out`` (the model's output on ``batch``) for ``cfg.steps`` steps; returns the new output."""
    if cfg.steps == 0:
        return out
    p0 = out.latents.params
    H, W = batch.rgb.shape[-2:]
    loss_cfg = test_time_losses(loss_cfg, use_depth, model.cfg.soft_mask_tau > 0)
    leaf = lambda t: t.detach().clone().requires_grad_(True)
    z_sh, z_tex, pos, cs, scale, bg = (leaf(t) for t in (p0.z_sh, p0.z_tex, p0.position, p0.cos_sin, p0.scale, out.latents.bg_color))
    opt = torch.optim.Adam([{"params": [z_sh, z_tex, scale, bg]},
                            {"params": [pos, cs], "lr": cfg.lr * cfg.pose_lr_scale}], lr=cfg.lr)
    lo, hi = model.cfg.scale_range
    with torch.enable_grad():
        for _ in range(cfg.steps):
            params = SceneParams(z_sh, z_tex, pos, cs, scale, p0.axis, p0.active)
            o = render_latents(model, params, bg, batch.K, batch.T_world_cam, batch.ground_z, H, W)
            loss = compute_losses(model, o, batch, loss_cfg, FINAL_STEP).total
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            with torch.no_grad():
                scale.clamp_(max(lo, cfg.min_scale), hi)
                bg.clamp_(0.0, 1.0)
                cs.div_(cs.norm(dim=-1, keepdim=True).clamp_min(1e-6))
    with torch.no_grad():
        params = SceneParams(z_sh.detach(), z_tex.detach(), pos.detach(), cs.detach(), scale.detach(), p0.axis, p0.active)
        new = render_latents(model, params, bg.detach(), batch.K, batch.T_world_cam, batch.ground_z, H, W)
    new.slot_steps = out.slot_steps
    return new
