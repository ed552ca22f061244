"""Re-seed idle slots on what the scene leaves unexplained (beyond the paper; test time, no training).

The recurrent encoder of a many-slot model finds a few objects and then hides its remaining slots
(EVALUATION.md, "Why the 1-8 model misses objects"); the pose search only moves a slot near where it is,
so it cannot carry a hidden slot to an object nobody covers. This step does that with the camera's
geometry: in each round, per scene,

1. the pixels the composition does not explain (``StopRule.unexplained``: colour, and depth when the
   input has it; for a model whose anchors read cast shadows, ``AnchorRule.shadows``, not those either) are
   opened (eroded, then dilated back: the one-pixel seams along fitted outlines go, a small object's blob
   stays whole) and split into connected components (OpenCV); the largest with at least ``min_area``
   pixels is the proposal;
2. the slot that explains least (``prismonet.model.prune``: fewer than ``rule.min_gain`` pixels that the
   others do not) is the one moved; a scene without such a slot is left alone, or, with ``replace_least``,
   the slot that explains the fewest pixels alone is tried there instead (for scenes with more objects
   than slots, or a slot spent on half an object);
3. the slot is put where an object resting on the ground would show that component: the ray through
   the component's centroid meets the plane ``z = ground + s``, and the scale ``s`` is the one whose
   disc covers the component's area at that depth (a fixed point, ``PLACE_ITERATIONS`` steps); each
   shape category's medoid code of the prior is tried at ``TRIAL_SCALES`` times that scale (the centre
   kept on the same ray at the new height), with the texture latent fitted to the component's pixels
   (``TEXTURE_STEPS`` Adam steps on that slot alone). With ``on_objects``, each is also tried resting on
   the surface the composition shows under the component (``support_height``: another slot's top, for
   stacked objects, whose ground placement falls behind the object they rest on);
4. the best trial is kept only where it lowers the scene's ``fit_score``, so re-seeding never makes a
   scene fit worse; a component whose trials all fail is not proposed again, so the next round tries
   the next largest.

The pose search afterwards (``prismonet.model.search``) fits the new slots as it fits the others.
Each round costs one single-slot render per shape category and trial scale, and ``TEXTURE_STEPS`` texture-field
steps for all of a round's trials at once (``_fit_textures``: independent fits in one batch).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, replace

import torch

from prismonet.geometry.camera import pixel_grid, unproject
from prismonet.geometry.transforms import transform_points
from prismonet.model.fit_score import fit_score
from prismonet.model.prismonet import ModelOutput, SceneLatents
from prismonet.model.prune import explained_alone, prune_keep
from prismonet.model.stopping import StopRule
from prismonet.model.unexplained import largest_region
from prismonet.render import SceneParams, composite, render_objects
from prismonet.render.renderer import shade_objects

PLACE_ITERATIONS = 8
"""Fixed-point steps between the centre's depth and the scale (both start from the scale range's middle)."""
TEXTURE_STEPS = 30
"""Adam steps of a new slot's texture latent on the component's pixels."""
TEXTURE_LR = 0.1
TRIAL_SCALES = (0.8, 1.0, 1.25)
"""Multipliers of the placed scale tried per shape: a component partly hidden is smaller than its object."""
RAISED_SUPPORT = 0.1
"""With ``on_objects``: a surface under a component counts as a support only this far above the ground (world
units); lower, the ground trials already cover it."""


@dataclass(frozen=True)
class ReseedConfig:
    rounds: int = 0
    """Rounds; each moves at most one idle slot per scene (0: off)."""
    cycles: int = 1
    """With the pose search: re-seed, then search, this many times (the search settles the slots placed, and
    what they still leave unexplained is proposed again)."""
    grow: int = 0
    """Empty slots added to the model's before the first round, for scenes with more objects than it has
    slots (0: the model's slots only)."""
    min_area: int = 20
    """Least pixels of an unexplained component (after the opening) worth a slot."""
    open: int = 1
    """Radius in pixels of the opening of the unexplained pixels, which removes the seams along fitted outlines."""
    rule: StopRule = StopRule(min_gain=10)
    """What an explained pixel is, and how little a slot must explain to count as idle (``min_gain``)."""
    w_image: float = 1.0
    w_depth: float = 0.1
    on_objects: bool = False
    """Also try each proposal resting on the slot surface the composition shows under it, not only on the
    ground (for stacked objects; twice the trials where a slot is under the component)."""
    replace_least: bool = False
    """A scene with no idle slot left tries its proposal with the slot that explains the fewest pixels alone
    (the score test still decides, so the swap is kept only where the scene then fits better)."""

    def __post_init__(self) -> None:
        if self.rounds < 0:
            raise ValueError(f"reseed: the rounds (--reseed) must be >= 0, got {self.rounds}")
        if self.grow < 0:
            raise ValueError(f"reseed: the slots to add (--reseed-grow) must be >= 0, got {self.grow}")
        if self.cycles < 1:
            raise ValueError(f"reseed: the cycles (--reseed-cycles) must be >= 1, got {self.cycles}")
        if self.on_objects and self.rounds == 0:
            raise ValueError("reseed: --reseed-on-objects needs re-seeding rounds (--reseed R, R >= 1)")
        if self.replace_least and self.rounds == 0:
            raise ValueError("reseed: --reseed-replace needs re-seeding rounds (--reseed R, R >= 1)")
        if self.min_area < 1 or self.open < 0:
            raise ValueError(f"reseed: min_area must be >= 1 and open >= 0, got {self.min_area} and {self.open}")


def ray_at_height(uv: torch.Tensor, K: torch.Tensor, T_world_cam: torch.Tensor, height: torch.Tensor) -> torch.Tensor:
    """``(B, 3)`` world points where the rays through pixels ``uv (B, 2)`` come down to world ``z = height (B,)``
    (a ray that never does: its point at camera depth 1e-3)."""
    d_cam = torch.stack([(uv[:, 0] - K[:, 0, 2]) / K[:, 0, 0], (uv[:, 1] - K[:, 1, 2]) / K[:, 1, 1], torch.ones_like(uv[:, 0])], -1)
    d_world = torch.einsum("bij,bj->bi", T_world_cam[:, :3, :3], d_cam)  # camera z = 1 per unit of t
    c = T_world_cam[:, :3, 3]
    t = ((height - c[:, 2]) / d_world[:, 2].clamp(max=-1e-6)).clamp(min=1e-3)  # rays look down: d_world z < 0
    return c + t[:, None] * d_world


def place_on_ground(uv: torch.Tensor, area: torch.Tensor, K: torch.Tensor, T_world_cam: torch.Tensor,
                    ground_z: torch.Tensor, scale_range: tuple[float, float]) -> tuple[torch.Tensor, torch.Tensor]:
    """Centres ``(B, 3)`` and scales ``(B,)`` of objects resting on the ground plane ``z = ground_z (B,)``
    whose image is a disc of ``area (B,)`` pixels centred on pixel ``uv (B, 2)``.

    A ball of radius ``s`` at camera depth ``d`` covers about ``pi (f s / d)^2`` pixels, so
    ``s = d sqrt(area / pi) / f``; its centre lies on the ray through ``uv`` at height ``ground_z + s``.
    Scales are kept in ``scale_range``; a ray that never comes down to that height keeps the largest depth
    on the ray it reaches (the centre is then put where the ray meets the height at the range's end)."""
    lo, hi = scale_range
    f = 0.5 * (K[:, 0, 0] + K[:, 1, 1])
    s = torch.full_like(area, 0.5 * (lo + hi))
    for _ in range(PLACE_ITERATIONS):
        x_cam = (ray_at_height(uv, K, T_world_cam, ground_z + s) - T_world_cam[:, :3, 3])
        depth = torch.einsum("bi,bi->b", x_cam, T_world_cam[:, :3, 2])  # camera z: the camera's z axis in world
        s = (depth * torch.sqrt(area / torch.pi) / f).clamp(lo, hi)
    return ray_at_height(uv, K, T_world_cam, ground_z + s), s


def support_height(comp_depth: torch.Tensor, covered: torch.Tensor, region: torch.Tensor, K: torch.Tensor,
                   T_world_cam: torch.Tensor, min_share: float = 0.5) -> torch.Tensor:
    """``(B,)`` world height of the surface the composition shows under each scene's ``region (B, H, W)`` bool:
    the median world ``z`` of the region's pixels that a slot covers (``covered (B, H, W)`` bool), at their camera
    depth ``comp_depth (B, H, W)``; NaN where slots cover less than ``min_share`` of the region."""
    B, H, W = region.shape
    uv = pixel_grid(H, W, dtype=comp_depth.dtype, device=comp_depth.device).reshape(1, H * W, 2).expand(B, -1, -1)
    z = transform_points(T_world_cam, unproject(uv, comp_depth.reshape(B, H * W, 1), K))[..., 2]
    on = (region & covered).reshape(B, H * W)
    height = torch.where(on, z, torch.full_like(z, float("nan"))).nanmedian(dim=1).values
    enough = on.sum(1) >= (min_share * region.flatten(1).sum(1)).clamp_min(1)
    return torch.where(enough, height, torch.full_like(height, float("nan")))


def category_medoids(prior) -> torch.Tensor:
    """``(C, D_sh)``: per shape category of the prior, the training code nearest the category's mean."""
    codes = prior.latents.detach()
    cats = torch.as_tensor(prior.category_ids, device=codes.device)
    out = []
    for c in torch.unique(cats):
        sel = codes[cats == c]
        out.append(sel[(sel - sel.mean(0)).norm(dim=1).argmin()])
    return torch.stack(out)


def _fit_textures(model, trials: list, target: torch.Tensor, region: torch.Tensor) -> list[torch.Tensor]:
    """Per trial ``(one, obj)`` (a single-slot ``SceneParams`` and its render): its ``(B, 1, D_tex)`` texture latent
    fitted to ``target (B, 3, H, W)`` at its hits inside ``region (B, H, W)`` bool (scenes without such hits keep
    theirs). The trials are independent and fitted together: each trial's loss is the mean over its own hits, and
    Adam acts per element, so every latent takes the steps it would take fitted alone (up to the order of sums)."""
    B, _, H, W = trials[0][1].depth.shape
    want_all = target.permute(0, 2, 3, 1).reshape(B, H * W, 3)
    rows, xs, wants, weights = [], [], [], []
    for t, (one, obj) in enumerate(trials):
        b, pix = obj.hit_slot, obj.hit_pix  # K = 1: the slot index is the scene
        inside = region.reshape(B, -1)[b, pix]
        n = int(inside.sum())
        if n == 0:
            continue
        rows.append(t * B + b[inside])
        xs.append(obj.hit_x_obj[inside])
        wants.append(want_all[b[inside], pix[inside]])
        weights.append(torch.full((n,), 1.0 / n, dtype=target.dtype, device=target.device))
    if not rows:
        return [one.z_tex for one, _ in trials]
    row, x, want, weight = torch.cat(rows), torch.cat(xs), torch.cat(wants), torch.cat(weights)
    z = torch.cat([one.z_tex[:, 0] for one, _ in trials]).detach().clone().requires_grad_(True)  # (T * B, D_tex)
    opt = torch.optim.Adam([z], lr=TEXTURE_LR)
    with torch.enable_grad():
        for _ in range(TEXTURE_STEPS):
            opt.zero_grad(set_to_none=True)
            (((model.color_fn(z[row], x) - want) ** 2).sum(1) * weight).sum().backward()
            opt.step()
    fitted = z.detach().reshape(len(trials), B, 1, -1)
    return [fitted[t] for t in range(len(trials))]


@torch.no_grad()
def reseed(model, out: ModelOutput, batch, cfg: ReseedConfig = ReseedConfig(), use_depth: bool = True) -> ModelOutput:
    """``out`` (the model's output on ``batch``) with idle slots moved onto unexplained parts of the input,
    ``cfg.rounds`` times (see the module docstring); every scene's ``fit_score`` is at most its start's."""
    if cfg.rounds == 0:
        return out
    out = grow_slots(out, cfg.grow, model.cfg.far_depth)
    depth_in = batch.depth if use_depth else None
    target_depth = depth_in if cfg.w_depth > 0 else None
    shapes = category_medoids(model.prior)
    settings = model.render_settings()
    H, W = batch.rgb.shape[-2:]
    bg, bg_depth = out.latents.bg_color, out.bg_depth
    ground_z = torch.as_tensor(batch.ground_z, dtype=batch.rgb.dtype).reshape(-1).expand(batch.rgb.shape[0])
    p = out.latents.params
    params = replace(p, z_sh=p.z_sh.clone(), z_tex=p.z_tex.clone(), position=p.position.clone(),
                     cos_sin=p.cos_sin.clone(), scale=p.scale.clone(),
                     active=None if p.active is None else p.active.clone())
    obj_depth, obj_mask, obj_color = out.obj_depth.clone(), out.obj_mask.clone(), out.obj_color.clone()
    B, N = params.scale.shape
    rows = torch.arange(B)
    anchors = model.anchor_rule() if model.cfg.anchor_shade_min is not None else None  # it reads cast shadows

    def scored(d, m, c):
        comp = composite(d, m, c, bg, bg_depth)
        return fit_score(comp.image, comp.depth, batch.rgb, target_depth, cfg.w_image, cfg.w_depth), comp

    best, comp = scored(obj_depth, obj_mask, obj_color)
    tried = torch.zeros(B, H, W, dtype=torch.bool)  # components proposed in vain
    ys, xs = torch.meshgrid(torch.arange(H, dtype=batch.rgb.dtype), torch.arange(W, dtype=batch.rgb.dtype), indexing="ij")
    lo, hi = model.cfg.scale_range
    upright = torch.tensor([1.0, 0.0], dtype=params.cos_sin.dtype).expand(B, 1, 2).contiguous()
    for _ in range(cfg.rounds):
        current = replace(out, latents=SceneLatents(params, bg), composite=comp, obj_depth=obj_depth,
                          obj_mask=obj_mask, obj_color=obj_color)
        kept = prune_keep(cfg.rule, current, batch.rgb, depth_in)
        idle = ~kept
        unexplained = cfg.rule.unexplained(batch.rgb, depth_in, comp.image, torch.minimum(comp.depth, bg_depth), eroded=False)
        if anchors is not None:  # what the model's anchors read as a cast shadow is not proposed either
            unexplained &= ~anchors.shadows(batch.rgb, comp.image)
        region, found = largest_region(unexplained, cfg.open, cfg.min_area, exclude=tried)
        go = found & (idle.any(1) | cfg.replace_least)
        if not go.any():
            break
        k = idle.float().argmax(1)  # the first idle slot of each scene
        if cfg.replace_least and not bool(idle[go].any(1).all()):
            k = torch.where(idle.any(1), k, least_useful(cfg.rule, current, batch.rgb, depth_in, kept))
        area = region.flatten(1).sum(1).to(batch.rgb.dtype).clamp_min(1)
        uv = torch.stack([(region * xs).flatten(1).sum(1), (region * ys).flatten(1).sum(1)], -1) / area[:, None]
        supports = [(ground_z, go)]
        if cfg.on_objects:  # resting on the slot surface under the component, where that is above the ground
            top = support_height(comp.depth[:, 0], comp.mask[:, 0] > 0, region, batch.K, batch.T_world_cam)
            raised = go & (top > ground_z + RAISED_SUPPORT)
            if raised.any():
                supports.append((torch.where(raised, top, ground_z), raised))
        # each scene's best trial for its slot k: latents and single-slot renders, kept where the score falls
        pick = {name: getattr(params, name)[rows, k].clone() for name in ("z_sh", "z_tex", "position", "scale")}
        pick_d, pick_m, pick_c = obj_depth[rows, k].clone(), obj_mask[rows, k].clone(), obj_color[rows, k].clone()
        round_best = best.clone()
        for base, live in supports:
            _, placed = place_on_ground(uv, area, batch.K, batch.T_world_cam, base, model.cfg.scale_range)
            trials = []
            for z_sh, mult in itertools.product(shapes, TRIAL_SCALES):
                scale = (placed * mult).clamp(lo, hi)
                position = ray_at_height(uv, batch.K, batch.T_world_cam, base + scale)
                one = SceneParams(z_sh.expand(B, -1)[:, None].to(params.z_sh.dtype), params.z_tex[rows, k][:, None],
                                  position[:, None], upright, scale[:, None],
                                  None if params.axis is None else params.axis[rows, k][:, None], live[:, None])
                trials.append((one, render_objects(model.sdf_fn, None, one, batch.K, batch.T_world_cam, H, W, settings)))
            for (one, geo), z_tex in zip(trials, _fit_textures(model, trials, batch.rgb, region)):
                one = replace(one, z_tex=z_tex)
                color = shade_objects(model.color_fn, one, geo)  # the same hits, coloured
                d, m, c = obj_depth.clone(), obj_mask.clone(), obj_color.clone()
                d[rows, k], m[rows, k], c[rows, k] = geo.depth[:, 0], geo.mask[:, 0], color[:, 0]
                score, _ = scored(d, m, c)
                win = live & (score < round_best)
                round_best = torch.where(win, score, round_best)
                for name, t in pick.items():
                    t[win] = getattr(one, name)[win, 0]
                pick_d[win], pick_m[win], pick_c[win] = geo.depth[win, 0], geo.mask[win, 0], color[win, 0]
        win = round_best < best
        tried |= region & ~win.view(-1, 1, 1)
        if not win.any():
            continue
        at = (rows[win], k[win])
        for name, t in pick.items():
            getattr(params, name)[at] = t[win]
        params.cos_sin[at] = upright[win, 0]
        if params.active is not None:
            params.active[at] = True
        obj_depth[at], obj_mask[at], obj_color[at] = pick_d[win], pick_m[win], pick_c[win]
        best, comp = scored(obj_depth, obj_mask, obj_color)
    return ModelOutput(SceneLatents(params, bg), comp, obj_depth, obj_mask, obj_color, bg_depth, None,
                       slot_steps=out.slot_steps)


def least_useful(rule: StopRule, out: ModelOutput, image: torch.Tensor, depth: torch.Tensor | None,
                 kept: torch.Tensor) -> torch.Tensor:
    """``(B,)`` per scene the slot among ``kept (B, N)`` whose removal leaves the fewest more pixels
    unexplained (``prismonet.model.prune``'s measure; ties: the lowest index)."""
    return explained_alone(rule, out, image, depth, kept).argmin(1)


def grow_slots(out: ModelOutput, extra: int, far_depth: float) -> ModelOutput:
    """``out`` with ``extra`` empty slots appended to every scene: inactive, no pixels, at the smallest
    scale ``out`` has; the composition is unchanged."""
    if extra == 0:
        return out
    p = out.latents.params
    B, N = p.scale.shape

    def pad(t: torch.Tensor | None, fill: float = 0.0) -> torch.Tensor | None:
        if t is None:
            return None
        return torch.cat([t, torch.full((B, extra, *t.shape[2:]), fill, dtype=t.dtype)], 1)

    cos_sin = torch.cat([p.cos_sin, torch.tensor([1.0, 0.0], dtype=p.cos_sin.dtype).expand(B, extra, 2)], 1)
    active = p.active if p.active is not None else torch.ones(B, N, dtype=torch.bool)
    params = SceneParams(pad(p.z_sh), pad(p.z_tex), pad(p.position), cos_sin, pad(p.scale, float(p.scale.min())),
                         pad(p.axis), torch.cat([active, torch.zeros(B, extra, dtype=torch.bool)], 1))
    steps = torch.cat([out.encoder_steps(), torch.arange(N, N + extra).expand(B, extra)], 1)
    return ModelOutput(SceneLatents(params, out.latents.bg_color), out.composite, pad(out.obj_depth, far_depth),
                       pad(out.obj_mask, False), pad(out.obj_color), out.bg_depth, None, slot_steps=steps)
