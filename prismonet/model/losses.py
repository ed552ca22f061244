"""The training losses of the paper, with its schedules and ablation switches.

L_total = l_I L_I + l_D L_D + l_gr L_gr + l_sh(t) L_sh  [+ l_int L_int + l_p L_p + l_pose L_pose]

- L_I: MSE of the Gaussian-blurred images; L_D: L1 of the blurred depths. The blur's sigma falls
  linearly from 16/3 to 1/2 over ``blur_steps``. The blur (``prismonet.model.blur``) has odd
  kernels: 17 taps stand for the paper's 16.
- L_gr: sum_i max(0, -(z_i - ground)) + max(0, -phi_i(z'_i)), z'_i the object's centre dropped
  onto the ground; phi_i in world units.
- L_sh: sum_i |z_sh,i|^2, weight falling linearly from 0.025 to 0.0025 over ``sh_steps``.
- L_int (objects intersecting), L_p (centres projected outside the image), L_pose (pose
  supervision with Hungarian matching), L_mask (BCE of blurred foreground masks): the paper's
  optional extras, off by default. L_mask needs soft silhouettes (``model.soft_mask_tau > 0``):
  the binary masks have no gradient, so a BCE on them alone would train nothing.
- Beyond the paper: L_distill (``prismonet.model.distill``) and L_seek (``prismonet.model.seek``).
"""

from __future__ import annotations

import math

from dataclasses import dataclass

import torch

from prismonet.model.blur import gaussian_blur
from prismonet.model.foreground import at_far_clip, depth_foreground

EPS_BCE = 1e-6
"""Predicted mask probabilities are clamped to [EPS_BCE, 1 - EPS_BCE] before the logarithms."""

BLUR_KERNEL = 17
"""Odd stand-in for the paper's kernel size 16 (a centred Gaussian kernel has an odd size)."""


@dataclass(frozen=True)
class LossConfig:
    """Loss weights, schedules and ablation switches (defaults: the paper's Clevr values)."""

    w_image: float = 1.0
    w_depth: float = 0.1
    w_ground: float = 0.01
    w_shape_start: float = 0.025
    w_shape_end: float = 0.0025
    sh_steps: int = 500_000
    """Steps over which the shape-regulariser weight falls (the paper: the first 500K)."""
    use_image: bool = True
    use_depth: bool = True
    use_ground: bool = True
    use_shape: bool = True
    blur: bool = True
    blur_sigma_start: float = 16 / 3
    blur_sigma_end: float = 0.5
    blur_steps: int = 250_000
    """Steps over which sigma falls (the paper: 250K)."""
    w_intersection: float = 0.0
    intersection_points: int = 16
    w_outside: float = 0.0
    w_pose: float = 0.0
    pose_yaw_periods: tuple[float, ...] | None = None
    """L_pose's yaw term up to each shape's symmetry about z, by the training data's shape ids
    (``prismonet.shapes.symmetry.library_yaw_periods``): ``1 - cos(2 pi / P (yaw - true yaw))`` for period ``P``, nothing
    for 0 (a round shape: every yaw looks alike). None: the paper's ``1 - cos(yaw - true yaw)`` for every shape."""
    w_mask: float = 0.0
    mask_from_depth: bool = False
    """L_mask's target from the depth image alone: pixels in front of the known ground plane by
    more than ``mask_depth_margin``. No labels: the RGB-D input and the plane already imply it."""
    mask_depth_margin: float = 0.05
    far_clip: bool = False
    """Model the depth sensor's far clip (``model.far_depth``, where the input depth is clipped): L_D
    compares the render clipped there too, and L_mask from depth leaves out the pixels whose input depth
    reads the clip. Without it an object beyond the clip is taught away: L_mask's depth-made target
    calls it ground, and L_D charges a correctly placed far object for rendering deeper than the clip.
    Off by default: the runs recorded before it existed trained without it."""
    w_presence: float = 0.0
    """With ``model.presence``: the cost of a present slot (sum of presences per scene), so that a slot
    that explains nothing turns itself off. It must stay below what a small object's pixels are worth in
    L_I, or real objects are dropped too."""
    w_distill: float = 0.0
    """Self-distillation (beyond the paper): weight of the regression onto the test-time fit's
    slots (``prismonet.model.distill``; needs ``TrainConfig.distill``)."""
    distill_texture: float = 0.1
    """Inside L_distill, the weight of the texture latents' squared L2 (``DistillWeights.texture``); 0 leaves
    the colours to L_I alone (the colour fit moves the latents in directions that change no colour)."""
    w_seek: float = 0.0
    """Seeking the unexplained (beyond the paper; ``prismonet.model.seek``): weight of the pull of slots that
    explain nothing towards the largest foreground region (from the depth image) that no slot covers."""
    w_keep: float = 0.0
    """With a refiner that keeps or drops slots (``model.refiner_keep``) and distillation targets that say which
    slots the fit shows: weight of the keep logits' binary cross-entropy against that (``distill.keep_loss``, beyond
    the paper, as in the refiner's first stage, ``refiner_fit.KEEP_WEIGHT``). 0: the keep output gets no gradient."""

    def __post_init__(self) -> None:
        for name in ("w_image", "w_depth", "w_ground", "w_shape_start", "w_shape_end", "w_intersection", "w_outside", "w_pose", "w_mask", "w_presence", "w_distill", "w_seek", "w_keep", "distill_texture"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be non-negative, got {getattr(self, name)}")
        if self.pose_yaw_periods is not None and any(not 0 <= p <= 2 * math.pi for p in self.pose_yaw_periods):
            raise ValueError(f"pose_yaw_periods: expected periods in [0, 2 pi], got {self.pose_yaw_periods}")
        if self.sh_steps <= 0 or self.blur_steps <= 0:
            raise ValueError(f"sh_steps and blur_steps must be positive, got {self.sh_steps}, {self.blur_steps}")


def _linear(start: float, end: float, step: int, steps: int) -> float:
    return start + (end - start) * min(step / steps, 1.0)


def blur_sigma(cfg: LossConfig, step: int) -> float:
    return _linear(cfg.blur_sigma_start, cfg.blur_sigma_end, step, cfg.blur_steps)


def shape_weight(cfg: LossConfig, step: int) -> float:
    return _linear(cfg.w_shape_start, cfg.w_shape_end, step, cfg.sh_steps)


def blur_kernel_size(sigma: float) -> int:
    """Taps of the Gaussian blur: ``2 ceil(6 sigma) + 1``, at most ``BLUR_KERNEL``. The first tap
    left out weighs less than exp(-18) = 1.5e-8 of the centre, so the result is the 17-tap one to
    float rounding; at the final sigma 0.5 it is 7 taps instead of 17 (2.4x less work)."""
    return min(BLUR_KERNEL, 2 * math.ceil(6 * sigma) + 1)


def blur(x: torch.Tensor, cfg: LossConfig, step: int) -> torch.Tensor:
    """``x (..., H, W)`` under the schedule's Gaussian blur at ``step`` (replicated borders; the
    identity with ``cfg.blur`` off)."""
    if not cfg.blur:
        return x
    s = blur_sigma(cfg, step)
    return gaussian_blur(x, s, blur_kernel_size(s))


def ground_loss(model, params, ground_z: torch.Tensor) -> torch.Tensor:
    """``(B,)``: objects above the ground, and no shape reaching below it under its centre (inactive slots,
    which are not objects, are not charged)."""
    height = params.position[..., 2] - ground_z[:, None]
    foot = params.position.clone()
    foot[..., 2] = ground_z[:, None].expand_as(foot[..., 2])
    phi = model.sdf_world(params, foot[:, :, None, :])[..., 0]  # (B, K)
    per_slot = torch.relu(-height) + torch.relu(-phi)
    if params.active is not None:
        per_slot = per_slot * params.active.to(per_slot.dtype)
    return per_slot.sum(1)


def intersection_loss(model, params, points: int) -> torch.Tensor:
    """``(B,)`` the paper's L_int: sample points between object centres inside both shapes."""
    B, K = params.scale.shape
    if K < 2:
        return torch.zeros(B, dtype=params.position.dtype, device=params.position.device)
    t = torch.linspace(0, 1, points, dtype=params.position.dtype, device=params.position.device)
    total = torch.zeros(B, dtype=params.position.dtype, device=params.position.device)
    for i in range(K):
        for j in range(i):
            seg = params.position[:, j, None] + t[:, None] * (params.position[:, i, None] - params.position[:, j, None])  # (B, P, 3)
            phi = model.sdf_world(params, seg[:, None].expand(B, K, points, 3))  # (B, K, P)
            total = total + torch.relu(-(phi[:, i] + phi[:, j])).mean(1)
    return total


def outside_loss(params, K: torch.Tensor, T_world_cam: torch.Tensor, width: int, height: int) -> torch.Tensor:
    """``(B,)`` the paper's L_p: how far object centres project outside the image, in pixels."""
    from prismonet.geometry.camera import project

    T_cam_world = torch.linalg.inv(T_world_cam)
    x_cam = torch.einsum("bij,bkj->bki", T_cam_world[:, :3, :3], params.position) + T_cam_world[:, None, :3, 3]
    x_cam = torch.cat([x_cam[..., :2], x_cam[..., 2:].clamp_min(1e-3)], -1)
    uv = project(x_cam, K)
    u, v = uv[..., 0], uv[..., 1]
    return (torch.relu(-torch.minimum(u, width - u)) + torch.relu(-torch.minimum(v, height - v))).sum(1)


def pose_loss(params, gt_position, gt_yaw, gt_scale, gt_count, yaw_period: torch.Tensor | None = None) -> torch.Tensor:
    """``(B,)`` the paper's L_pose after a Hungarian matching on position distance. ``yaw_period (B, K)``: each true
    object's period of symmetry about z (``LossConfig.pose_yaw_periods``); its yaw term is then ``1 - cos(2 pi / P
    delta)``, and nothing for ``P = 0``."""
    from scipy.optimize import linear_sum_assignment

    B = params.position.shape[0]
    yaw = torch.atan2(params.cos_sin[..., 1], params.cos_sin[..., 0])
    out = []
    for b in range(B):
        n = int(gt_count[b])
        cost = torch.cdist(params.position[b].detach(), gt_position[b, :n])
        rows, cols = linear_sum_assignment(cost.cpu().numpy())
        r, c = torch.as_tensor(rows, device=cost.device), torch.as_tensor(cols, device=cost.device)
        # turns per full turn that leave the shape as it is: 1 (the paper's term), 2 pi / P, or 0 (round: no term)
        k = 1.0 if yaw_period is None else (2 * math.pi / yaw_period[b, c].clamp_min(1e-6)) * (yaw_period[b, c] > 0)
        out.append((params.position[b, r] - gt_position[b, c]).norm(dim=-1).sum()
                   + (1 - torch.cos(k * (yaw[b, r] - gt_yaw[b, c]))).sum() + ((params.scale[b, r] - gt_scale[b, c]) ** 2).sum())
    return torch.stack(out)


def mask_loss(out, batch, cfg: LossConfig, step: int, target_depth: torch.Tensor | None = None,
              far_depth: float | None = None) -> torch.Tensor:
    """``()`` the paper's L_mask: BCE between the blurred foreground target and the blurred union
    of the predicted soft silhouettes. The target is the ground-truth instance mask, or, with
    ``mask_from_depth``, the pixels whose depth lies in front of the known ground plane (with
    ``far_clip`` and ``far_depth``, pixels at the far clip are left out)."""
    if out.obj_soft_mask is None:
        raise ValueError("loss.w_mask > 0 needs soft silhouettes: set model.soft_mask_tau > 0")
    pred = 1 - torch.prod(1 - out.obj_soft_mask, dim=1, keepdim=True)  # union over slots
    if cfg.mask_from_depth:
        d = batch.depth if target_depth is None else target_depth
        gt = depth_foreground(d, out.bg_depth, cfg.mask_depth_margin).to(pred.dtype)
    else:
        gt = (batch.instance > 0).to(pred.dtype)[:, None]
    p = blur(pred, cfg, step).clamp(EPS_BCE, 1 - EPS_BCE)
    g = blur(gt, cfg, step)
    bce = -(g * torch.log(p) + (1 - g) * torch.log(1 - p))
    if cfg.mask_from_depth and cfg.far_clip and far_depth is not None:
        bce = bce * ~at_far_clip(d, far_depth)
    return bce.mean()


@dataclass
class LossTerms:
    """Every term, averaged over the batch (unweighted), and the weighted total."""

    total: torch.Tensor
    image: torch.Tensor
    depth: torch.Tensor
    ground: torch.Tensor
    shape: torch.Tensor
    intersection: torch.Tensor
    outside: torch.Tensor
    pose: torch.Tensor
    mask: torch.Tensor
    distill: torch.Tensor
    presence: torch.Tensor
    seek: torch.Tensor
    keep: torch.Tensor

    def scalars(self) -> dict[str, float]:
        return {k: float(v.detach()) for k, v in self.__dict__.items()}


def _yaw_periods(cfg: LossConfig, batch) -> torch.Tensor | None:
    """``(B, K)`` each true object's period of symmetry about z, from ``cfg.pose_yaw_periods`` by its shape id."""
    if cfg.pose_yaw_periods is None:
        return None
    table = torch.tensor(cfg.pose_yaw_periods, dtype=batch.obj_yaw.dtype, device=batch.obj_yaw.device)
    ids = batch.obj_shape.long()
    if bool((ids >= len(table)).any()):
        raise ValueError(f"pose_yaw_periods: {len(table)} periods, but the data has shape id {int(ids.max())}")
    return table[ids.clamp_min(0)]  # padding slots (id -1) are never matched


def compute_losses(model, out, batch, cfg: LossConfig, step: int, target_depth: torch.Tensor | None = None,
                   distill: tuple[dict, torch.Tensor] | None = None) -> LossTerms:
    """All losses for a model output ``out`` on a ``SceneBatch`` (``target_depth`` overrides the
    batch's depth, e.g. with noise added; ``distill``: the batch's self-distillation targets and
    their mask, ``DistillTargets.lookup``)."""
    p = out.latents.params
    zero = torch.zeros((), dtype=out.composite.image.dtype, device=out.composite.image.device)
    depth_gt = batch.depth if target_depth is None else target_depth
    # the blur is linear: blur(a) - blur(b) = blur(a - b), one blur instead of two
    image = (blur(out.composite.image - batch.rgb, cfg, step) ** 2).sum(1).mean() if cfg.use_image else zero
    far = model.cfg.far_depth
    rendered = out.composite.depth.clamp(max=far) if cfg.far_clip else out.composite.depth
    depth = blur(rendered - depth_gt, cfg, step).abs().mean() if cfg.use_depth else zero
    ground = ground_loss(model, p, batch.ground_z).mean() if cfg.use_ground else zero
    shape = (p.z_sh**2).sum((1, 2)).mean() if cfg.use_shape else zero
    inter = intersection_loss(model, p, cfg.intersection_points).mean() if cfg.w_intersection > 0 else zero
    H, W = batch.rgb.shape[-2:]
    outside = outside_loss(p, batch.K, batch.T_world_cam, W, H).mean() if cfg.w_outside > 0 else zero
    pose = pose_loss(p, batch.obj_position, batch.obj_yaw, batch.obj_scale, batch.obj_count,
                     _yaw_periods(cfg, batch)).mean() if cfg.w_pose > 0 else zero
    mask = mask_loss(out, batch, cfg, step, target_depth, far) if cfg.w_mask > 0 else zero
    if cfg.w_distill > 0 and distill is not None:
        from prismonet.model.distill import DistillWeights, distill_loss

        dist = distill_loss(p, out.latents.bg_color, *distill, DistillWeights(texture=cfg.distill_texture))
    else:
        dist = zero
    if cfg.w_keep > 0 and distill is not None:
        from prismonet.model.distill import keep_loss

        if out.keep_logit is None:
            raise ValueError("loss.w_keep > 0 needs a model whose refiner keeps or drops slots (model.refiner_keep)")
        keep = keep_loss(out.keep_logit, *distill)
    else:
        keep = zero
    presence = out.presence.sum(1).mean() if out.presence is not None else zero
    if cfg.w_seek > 0:
        from prismonet.model.seek import seek_foreground, seek_loss, seek_targets

        fg = seek_foreground(batch.rgb, depth_gt, out.bg_depth, out.latents.bg_color.detach(), far, cfg.mask_depth_margin)
        seek = seek_loss(p.position, *seek_targets(out.composite.instance, p.scale.shape[1], fg, depth_gt[:, 0], batch.K,
                                                   batch.T_world_cam, batch.ground_z, far))
    else:
        seek = zero
    total = (cfg.w_image * image + cfg.w_depth * depth + cfg.w_ground * ground + shape_weight(cfg, step) * shape
             + cfg.w_intersection * inter + cfg.w_outside * outside + cfg.w_pose * pose + cfg.w_mask * mask
             + cfg.w_distill * dist + cfg.w_presence * presence + cfg.w_seek * seek + cfg.w_keep * keep)
    return LossTerms(total, image, depth, ground, shape, inter, outside, pose, mask, dist, presence, seek, keep)
