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
from dataclasses import dataclass, replace

import torch
import torch.nn.functional as F

from prismonet.geometry.camera import resize_intrinsics
from prismonet.model.fit_score import fit_score
from prismonet.model.prismonet import ModelOutput, SceneLatents
from prismonet.render import SceneParams, composite, render_objects
from prismonet.render.background import plane_depth
from prismonet.shapes.extents import shape_extents
from prismonet.shapes.sdf_grid import SdfGrid


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
    """Also try, once per slot in the first pass (or pass ``shape_round``), the prior's training code nearest to the
    slot's shape latent within each shape category (sphere, cylinder, cube for Clevr): the encoder's
    latents drift towards one category (cubes come out nearest a cylinder code, EVALUATION.md)."""
    shape_yaws: tuple[float, ...] = ()
    """With ``shape_trials``, also try each category's code turned by these angles (degrees) about the
    vertical axis: the encoder's yaw for a slot it draws round is arbitrary, and a cube code at an
    arbitrary yaw fits worse than the round shape it would replace (EVALUATION.md, sharp shapes)."""
    shape_scales: tuple[float, ...] = ()
    """With ``shape_trials``, also try each category's code at the slot's scale times these multipliers (with
    every turn of ``shape_yaws``): the encoder's scale is the one its own latent needed, and a cube's code
    normalised to the unit sphere needs a smaller one than the rounded shape drawn in its place. The slot's
    centre moves with its scale so that its height above the ground scales too (an object resting on the
    ground stays on it)."""
    shape_siblings: bool = False
    """With ``shape_trials``, also try every other code of the category at the pose of its best variant (after the
    ``shape_scales`` x ``shape_yaws`` variants, before ``shape_polish``). The encoder's latent says little of a shape's
    proportions: on Clevr val the cube code nearest to a cube's slot has the cube's own proportions in 10 % of cases,
    while at the true pose the best of the nine cube codes is the true one in 98.5 % (EVALUATION.md, session 75)."""
    shape_footprint: bool = False
    """With ``shape_trials``, try every code of each category (not only the one nearest to the slot's latent), each
    scaled so that its footprint radius equals the slot's shape's and placed with its bottom where the slot's was
    (``prismonet.shapes.extents``), at each turn of ``shape_yaws`` and multiplier of ``shape_scales``. A code of other
    proportions than the slot's shape needs another scale: a cube drawn as a round puck is 1 / sqrt(2) of the
    puck's scale (EVALUATION.md, session 75)."""
    shape_margin: float = 0.0
    """With ``shape_siblings``, ``shape_footprint`` or ``shape_polish``: a shape trial replaces the slot only in the
    scenes whose score it lowers by at least this fraction. Trials of many codes, turns and poses can fit a round
    object slightly better with a box than with its own shape; a margin keeps the slot unless the new shape pays
    clearly (EVALUATION.md, session 75)."""
    shape_polish: int = 0
    """With ``shape_trials``, passes of pose trials (scales, shifts, yaws, as passes 0, 1, ... of the search) on a
    slot after it takes a category's code and before that code is judged against the slot as it was: the
    encoder's pose was fitted to its own shape, and a cube code needs its own (0: judged at once)."""
    shape_round: int = 0
    """The pass (0-based) in which the shape trials run: 0, before any pose trial; 1, after a pass of pose trials on
    the encoder's shapes (a slot then starts its shape trials nearer its object, and its footprint is measured
    there)."""
    shape_w_image: float | None = None
    """With ``shape_trials``: the image term's weight while the shape trials are judged (``None``: ``w_image``, as
    every other trial). The trials keep the slot's texture latent, which the encoder fitted to its own shape, and the
    colour fit comes after them; 0 judges shapes by depth alone (without depth in the input, no shape trial can then
    win). The pose trials keep ``w_image``."""
    shape_nearest: int = 0
    """Also try, once per slot in the first pass, the prior's ``N`` training codes nearest to the slot's
    shape latent, whatever their category (0: none). For priors of many similar shapes (chairs), where
    the encoder's code lies between several models' codes and renders none of them."""

    far_clip: bool = False
    """Score the render with its depth clipped at the model's ``far_depth``, like the sensor's (off by
    default: the recorded search figures were measured without it)."""
    coarse_rounds: int = 0
    """The first this many passes render and score at half the image size: a quarter of the rays,
    against the input averaged over 2 x 2 pixels, the camera scaled by ``resize_intrinsics``. The later
    passes run at full size; a scene whose full-size score the coarse passes made worse keeps the
    encoder's latents, so the search still never fits worse."""
    grid: int = 0
    """With G > 0 the trials render each slot's shape from a ``G^3`` table of its signed distances
    (``SdfGrid``, tabulated once per search) instead of the MLP; the result is then rendered once with the
    MLP, and a scene whose score that makes worse than the encoder's keeps the encoder's latents. 0: the
    MLP throughout. With ``shape_trials`` or ``shape_nearest`` the table also holds the prior's codes, the only other
    shapes a trial can take."""
    exact_rounds: int = 0
    """With ``grid``: the last this many passes render with the MLP, after the MLP has confirmed the table passes'
    result (a final polish of poses chosen against the tabulated shapes)."""

    def __post_init__(self) -> None:
        if not 0 <= self.coarse_rounds <= max(self.rounds, 0):
            raise ValueError(f"search: coarse_rounds must lie in [0, rounds], got {self.coarse_rounds} of {self.rounds}")
        if self.grid < 0 or self.grid == 1:
            raise ValueError(f"search: grid must be 0 (off) or at least 2 nodes per axis, got {self.grid}")
        if self.exact_rounds and not (self.grid and 0 < self.exact_rounds <= self.rounds - self.coarse_rounds):
            raise ValueError(f"search: exact_rounds needs a grid and must leave the coarse passes to it, got {self.exact_rounds} "
                             f"of {self.rounds} passes ({self.coarse_rounds} coarse, grid {self.grid})")
        if (self.shape_yaws or self.shape_scales or self.shape_polish or self.shape_siblings or self.shape_footprint) \
                and not self.shape_trials:
            raise ValueError("search: shape_yaws, shape_scales, shape_siblings, shape_footprint and shape_polish act on the "
                             "shape trials, so they need shape_trials=True")
        if not 0 <= self.shape_margin < 1:
            raise ValueError(f"search: shape_margin must lie in [0, 1), got {self.shape_margin}")
        if self.shape_round and not (self.shape_trials and 0 <= self.shape_round < self.rounds):
            raise ValueError(f"search: shape_round must name one of the {self.rounds} passes and needs shape_trials, got {self.shape_round}")
        if self.shape_polish < 0:
            raise ValueError(f"search: shape_polish must be >= 0, got {self.shape_polish}")
        if self.shape_w_image is not None and not (self.shape_trials and self.shape_w_image >= 0):
            raise ValueError(f"search: shape_w_image must be >= 0 and needs shape_trials, got {self.shape_w_image}")
        if any(m <= 0 for m in self.shape_scales):
            raise ValueError(f"search: shape_scales must be positive, got {self.shape_scales}")
        if self.shape_nearest < 0:
            raise ValueError(f"search: shape_nearest must be >= 0, got {self.shape_nearest}")
        if self.rounds < 0 or any(s <= 0 for s in self.scales) or self.w_image < 0 or self.w_depth < 0 or not 0 < self.decay <= 1:
            raise ValueError(f"search: rounds and weights must be non-negative and scales positive, got {self}")

    @property
    def trials_per_slot(self) -> int:
        return len([s for s in self.scales if s != 1]) + 2 * len([d for d in self.shifts if d != 0]) + len([a for a in self.yaws if a != 0])


SHAPE_TRIAL_SETTINGS: dict = {"shape_trials": True, "shape_footprint": True, "shape_yaws": (30.0, 60.0), "shape_polish": 3,
                              "shape_round": 2, "w_depth": 0.5}
"""The measured shape-trial search (``--shape-trials``; EVALUATION.md, sessions 75-78, "sharp shapes"): in the third
pass every prior code of each category is tried at each slot's footprint, turned by 0, 30 and 60 degrees, the best
variant's pose searched for 3 passes before it is judged against the slot as it was; depth weighs 0.5 in the score."""


SHAPE_TRIAL_GRID = 24
"""Nodes per axis of the table that the demo's shape trials render from for the 3-object model (``with_trial_table``;
EVALUATION.md, session 87: on 512 new-seed validation scenes 2.0x faster than the MLP throughout, with unfiltered
AP0.5 and AR0.5 +0.001, mAP +0.011, PSNR +0.28 dB, and 0.595 of cubes drawn as cubes against 0.606; it passed the same
bars on the 2- and 4-object models, not on the 5-object one, whose cubes fell by 0.06)."""


def with_trial_table(cfg: SearchConfig, grid: int = SHAPE_TRIAL_GRID) -> SearchConfig:
    """``cfg``'s passes rendered from a ``grid``-cubed table of the slots' shapes and the prior's codes, then one more
    pass with the MLP (``exact_rounds`` 1, so ``rounds`` is one more than ``cfg``'s)."""
    return replace(cfg, grid=grid, rounds=cfg.rounds + 1, exact_rounds=1)


def with_shape_trials(cfg: SearchConfig) -> SearchConfig:
    """``cfg`` with ``SHAPE_TRIAL_SETTINGS``; the trials run in pass 3, so ``cfg.rounds`` must be 3 or more. With a
    table (``cfg.grid``), one more pass with the MLP follows its passes (``with_trial_table``)."""
    if cfg.rounds <= SHAPE_TRIAL_SETTINGS["shape_round"]:
        raise ValueError(f"shape trials run in the search's third pass, so they need --search 3 or more, got {cfg.rounds}")
    trials = replace(cfg, **SHAPE_TRIAL_SETTINGS)
    return with_trial_table(trials, cfg.grid) if cfg.grid else trials


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
            yield scale, position, _turn(cos_sin, a * step)


def _turn(cos_sin: torch.Tensor, degrees: float) -> torch.Tensor:
    """``cos_sin`` (..., 2) of a yaw turned by ``degrees`` about the vertical axis."""
    if degrees == 0:
        return cos_sin
    c, s = math.cos(math.radians(degrees)), math.sin(math.radians(degrees))
    x, y = cos_sin.unbind(-1)
    return torch.stack([c * x - s * y, s * x + c * y], -1)


class _Level:
    """The per-object renders of B scenes at one image size, and each scene's fit score against the
    input at that size: what a trial changes and is judged by. With ``shapes`` the objects render from
    its table (slot ``k`` of scene ``b`` is row ``b * K + k``; a slot whose latent is one of ``prior_codes (C, D)``,
    row ``B * K + i`` of code ``i``), else with the model's MLP."""

    def __init__(self, model, bg: torch.Tensor, bg_depth: torch.Tensor, K: torch.Tensor, T_world_cam: torch.Tensor,
                 rgb: torch.Tensor, target_depth: torch.Tensor | None, cfg: SearchConfig, far: float | None,
                 shapes: SdfGrid | None = None, prior_codes: torch.Tensor | None = None) -> None:
        self.model, self.bg, self.bg_depth, self.K, self.T_world_cam = model, bg, bg_depth, K, T_world_cam
        self.rgb, self.target_depth, self.cfg, self.far = rgb, target_depth, cfg, far
        self.H, self.W = rgb.shape[-2:]
        self.settings = replace(model.render_settings(), soft_mask_tau=0.0)  # no soft silhouettes are read here
        self.sdf_fn = model.sdf_fn if shapes is None else shapes
        self.prior_codes = prior_codes
        self.codes = None  # (B, K, 1): each slot's own row
        if shapes is not None:
            own = shapes.values.shape[0] - (0 if prior_codes is None else len(prior_codes))
            self.codes = shapes.codes[:own].view(bg.shape[0], -1, 1)

    def rows(self, z_sh: torch.Tensor, k: int | None) -> torch.Tensor:
        """``(B, K', 1)`` table rows of the latents ``z_sh (B, K', D)`` (all slots, or slot ``k`` alone): a prior
        code's own row where a latent equals it exactly (the shape trials copy the codes), else the slot's."""
        own = self.codes if k is None else self.codes[:, k : k + 1]
        if self.prior_codes is None or len(self.prior_codes) == 0:
            return own
        same = (z_sh[:, :, None, :] == self.prior_codes[None, None]).all(-1)  # (B, K', C)
        hit, i = same.any(-1, keepdim=True), same.to(torch.uint8).argmax(-1, keepdim=True)
        return torch.where(hit, (self.codes.numel() + i).to(own.dtype), own)

    def score(self, depth: torch.Tensor, mask: torch.Tensor, color: torch.Tensor) -> torch.Tensor:
        c = composite(depth, mask, color, self.bg, self.bg_depth)
        return fit_score(c.image, c.depth, self.rgb, self.target_depth, self.cfg.w_image, self.cfg.w_depth, self.far)

    def set_renders(self, depth: torch.Tensor, mask: torch.Tensor, color: torch.Tensor) -> None:
        self.depth, self.mask, self.color = depth, mask, color
        self.best = self.score(depth, mask, color)

    def render(self, params: SceneParams, k: int | None = None):
        """``(depth, mask, color)`` of every slot of ``params`` at this level's size (of slot ``k`` alone
        when ``params`` holds only that slot)."""
        if self.codes is not None:
            params = replace(params, z_sh=self.rows(params.z_sh, k))
        obj = render_objects(self.sdf_fn, self.model.color_fn, params, self.K, self.T_world_cam, self.H, self.W,
                             self.settings)
        return obj.depth, obj.mask, obj.color

    def confirm(self, state: "_State", renders, start_renders, start_best: torch.Tensor) -> None:
        """Take ``renders`` of ``state``'s latents as this level's, except in the scenes they score worse
        than ``start_best`` (the start's score): those revert to the start latents and ``start_renders``."""
        score = self.score(*renders)
        worse = score > start_best
        state.revert(worse)
        w = worse.view(-1, 1, 1, 1)
        (d, m, c), (d0, m0, c0) = renders, start_renders
        self.depth, self.mask = torch.where(w, d0, d), torch.where(w, m0, m)
        self.color, self.best = torch.where(w[..., None], c0, c), torch.where(worse, start_best, score)

    def attempt(self, state: "_State", k: int, z_try, s_try, p_try, cs_try) -> None:
        """Render slot ``k`` alone with the trial latents; keep them per scene where the score falls."""
        s_try = s_try.clamp(max=self.model.cfg.scale_range[1])  # the encoder's own bound
        d, m, c = self.render(state.slot(k, z_try, s_try, p_try, cs_try), k)
        d_try, m_try, c_try = self.depth.clone(), self.mask.clone(), self.color.clone()
        d_try[:, k], m_try[:, k], c_try[:, k] = d[:, 0], m[:, 0], c[:, 0]
        score = self.score(d_try, m_try, c_try)
        win = score < self.best
        self.best = torch.where(win, score, self.best)
        w = win.view(-1, 1, 1)
        self.depth[:, k] = torch.where(w, d_try[:, k], self.depth[:, k])
        self.mask[:, k] = torch.where(w, m_try[:, k], self.mask[:, k])
        self.color[:, k] = torch.where(w[:, None], c_try[:, k], self.color[:, k])
        state.keep(win, k, z_try, s_try, p_try, cs_try)

    def try_shape(self, state: "_State", k: int, starts, cos_sin: torch.Tensor, siblings: torch.Tensor | None = None) -> None:
        """Shape trial: slot ``k`` with each ``(z (B, D), scale (B,), position (B, 3))`` of ``starts`` at the
        ``shape_scales`` x ``shape_yaws`` variants of that pose (turned from ``cos_sin (B, 2)``), kept per scene where
        the score falls; then each code of ``siblings (n, D)`` (if given) at the best variant's pose. With
        ``shape_siblings``, ``shape_footprint`` or ``shape_polish`` the best variant is taken whatever its score, the
        siblings tried at its pose, the winner's pose searched for ``shape_polish`` passes, and only then is the result
        judged against the slot as it was."""
        cfg = self.cfg
        if cfg.shape_w_image is not None and cfg.shape_w_image != cfg.w_image:  # judged with the shape trials' weights
            self.cfg = replace(cfg, w_image=cfg.shape_w_image, shape_w_image=None)
            self.best = self.score(self.depth, self.mask, self.color)
            try:
                self.try_shape(state, k, starts, cos_sin, siblings)
            finally:
                self.cfg = cfg
                self.best = self.score(self.depth, self.mask, self.color)
            return
        late = bool(cfg.shape_polish or cfg.shape_siblings or cfg.shape_footprint)  # the variants' best is taken, judged at the end
        if late:
            saved = (self.depth.clone(), self.mask.clone(), self.color.clone(), self.best.clone(), state.snapshot())
            self.best = torch.full_like(self.best, float("inf"))  # the first variant is taken, then the best of them
        for z, scale, position in starts:
            for m in (1.0, *(m for m in cfg.shape_scales if m != 1)):
                p = position.clone()
                p[:, 2] = state.ground_z + (p[:, 2] - state.ground_z) * m
                for a in (0.0, *(y for y in cfg.shape_yaws if y % 360 != 0)):
                    self.attempt(state, k, z, scale * m, p, _turn(cos_sin, a))
        for zs in () if siblings is None else siblings:
            self.attempt(state, k, zs.expand_as(state.z_sh[:, k]), state.scale[:, k], state.position[:, k], state.cos_sin[:, k])
        if not late:
            return
        for r in range(cfg.shape_polish):
            for s_try, p_try, cs_try in _trials(cfg, cfg.decay**r, state.scale[:, k], state.position[:, k], state.cos_sin[:, k]):
                self.attempt(state, k, state.z_sh[:, k], s_try, p_try, cs_try)
        depth, mask, color, best, snap = saved
        worse = self.best >= best * (1 - cfg.shape_margin)
        state.restore(worse, snap)
        w = worse.view(-1, 1, 1, 1)
        self.depth, self.mask = torch.where(w, depth, self.depth), torch.where(w, mask, self.mask)
        self.color, self.best = torch.where(w[..., None], color, self.color), torch.where(worse, best, self.best)

    def footprint_start(self, state: "_State", k: int, z: torch.Tensor, i: int, scale: torch.Tensor, position: torch.Tensor):
        """``(z (B, D), scale (B,), position (B, 3))``: prior code ``z`` (row ``i``) where slot ``k`` was drawn at ``scale``
        and ``position``: scaled to the footprint radius of the slot's starting shape, its bottom where that shape's was."""
        r_code, d_code = state.code_extents
        r_slot, d_slot = state.slot_extents[0][:, k], state.slot_extents[1][:, k]
        s = scale * r_slot / r_code[i].clamp_min(1e-6)
        p = position.clone()
        p[:, 2] = position[:, 2] - scale * d_slot + s * d_code[i]
        return z.expand(len(scale), -1), s, p

    def run_round(self, state: "_State", r: int) -> None:
        """One pass over all slots: shape trials (first pass, if asked), scales, shifts, yaws."""
        cfg, p = self.cfg, state.start
        codes = self.model.prior.latents.to(p.z_sh.dtype)
        exact = "donot_use_mm_for_euclid_dist"  # cdist's matmul path leaves a code ~1e-4 from itself
        ids = [int(c) for c in self.model.prior.category_ids]
        for k in range(state.scale.shape[1]):
            if p.active is not None and not p.active[:, k].any():
                continue  # never decoded (a stopped encoder): nothing to search
            if cfg.shape_trials and r == cfg.shape_round:
                # every category's variants start from the slot's pose before any of them (no compounding)
                z0, scale, position, cos_sin = (getattr(state, n)[:, k].clone() for n in ("z_sh", "scale", "position", "cos_sin"))
                for c in sorted(set(ids)):
                    rows = [i for i, ci in enumerate(ids) if ci == c]
                    sel = codes[rows]  # (n_c, D)
                    if cfg.shape_footprint:  # every code of the category, each at the slot's footprint
                        starts = [self.footprint_start(state, k, z, i, scale, position) for z, i in zip(sel, rows)]
                    else:
                        starts = [(sel[torch.cdist(z0, sel, compute_mode=exact).argmin(1)], scale, position)]
                    self.try_shape(state, k, starts, cos_sin, siblings=sel if cfg.shape_siblings else None)
            if cfg.shape_nearest and r == 0:
                n = min(cfg.shape_nearest, codes.shape[0])
                dist = torch.cdist(state.z_sh[:, k], codes, compute_mode=exact)
                order = dist.topk(n, dim=1, largest=False).indices  # (B, n), nearest first
                for i in range(n):
                    self.attempt(state, k, codes[order[:, i]], state.scale[:, k], state.position[:, k], state.cos_sin[:, k])
            for s_try, p_try, cs_try in _trials(cfg, cfg.decay**r, state.scale[:, k], state.position[:, k], state.cos_sin[:, k]):
                self.attempt(state, k, state.z_sh[:, k], s_try, p_try, cs_try)


class _State:
    """The searched latents (copies of the encoder's, changed in place as trials win)."""

    FIELDS = ("scale", "position", "cos_sin", "z_sh")

    def __init__(self, start: SceneParams, ground_z: torch.Tensor) -> None:
        self.start, self.ground_z = start, ground_z.to(start.position)  # ground_z (B,)
        self.scale, self.position = start.scale.clone(), start.position.clone()
        self.cos_sin, self.z_sh = start.cos_sin.clone(), start.z_sh.clone()
        self.code_extents = self.slot_extents = None  # (radius, depth) of the prior's codes, (B, K) of the start's slots

    def params(self) -> SceneParams:
        p = self.start
        return SceneParams(self.z_sh, p.z_tex, self.position, self.cos_sin, self.scale, p.axis, p.active)

    def slot(self, k: int, z_sh, scale, position, cos_sin) -> SceneParams:
        """Slot ``k`` alone (K = 1) with the given latents."""
        p = self.start
        one = lambda t: None if t is None else t[:, k : k + 1]
        return SceneParams(z_sh[:, None], one(p.z_tex), position[:, None], cos_sin[:, None], scale[:, None], one(p.axis),
                           one(p.active))

    def keep(self, win: torch.Tensor, k: int, z_sh, scale, position, cos_sin) -> None:
        self.scale[:, k] = torch.where(win, scale, self.scale[:, k])
        self.position[:, k] = torch.where(win[:, None], position, self.position[:, k])
        self.cos_sin[:, k] = torch.where(win[:, None], cos_sin, self.cos_sin[:, k])
        self.z_sh[:, k] = torch.where(win[:, None], z_sh, self.z_sh[:, k])

    def snapshot(self) -> tuple[torch.Tensor, ...]:
        return tuple(getattr(self, n).clone() for n in _State.FIELDS)

    def restore(self, scenes: torch.Tensor, snap: tuple[torch.Tensor, ...]) -> None:
        """Back to ``snap`` (``snapshot()``) in the scenes ``scenes`` (``(B,)`` bool)."""
        for name, t0 in zip(_State.FIELDS, snap):
            getattr(self, name)[scenes] = t0[scenes]

    def revert(self, scenes: torch.Tensor) -> None:
        """Back to the start latents in the scenes ``scenes`` (``(B,)`` bool)."""
        p = self.start
        for name in _State.FIELDS:
            t, t0 = getattr(self, name), getattr(p, name)
            t[scenes] = t0[scenes]


@torch.no_grad()
def search_latents(model, out: ModelOutput, batch, cfg: SearchConfig = SearchConfig(), use_depth: bool = True) -> ModelOutput:
    """``out`` (the model's output on ``batch``) with each slot's scale, position and yaw improved by
    coordinate search; every scene's score is at most the one it started with.

    The first ``cfg.coarse_rounds`` passes render and score at half the size (``batch.ground_z`` is
    read for the ground's depth there); the rest, and the score that decides what is kept, at full size.
    With ``cfg.grid`` the trials render from tabulated shapes and the result is rendered with the MLP (which then runs the
    last ``cfg.exact_rounds`` passes itself)."""
    if cfg.rounds == 0 or (cfg.trials_per_slot == 0 and not cfg.shape_trials and not cfg.shape_nearest):
        return out
    p = out.latents.params
    target_depth = batch.depth if use_depth and cfg.w_depth > 0 else None
    far = model.cfg.far_depth if cfg.far_clip else None
    bg = out.latents.bg_color
    state = _State(p, batch.ground_z)
    if cfg.shape_trials and cfg.shape_footprint:
        state.code_extents = tuple(t.to(p.z_sh.dtype) for t in model.prior.code_extents())  # computed once per prior
        r, d = shape_extents(model.sdf_fn, p.z_sh.reshape(-1, p.z_sh.shape[-1]), model.prior.bounds)
        state.slot_extents = (r.view(p.scale.shape), d.view(p.scale.shape))
    B, Kslots = p.z_sh.shape[:2]
    # the trials' shapes: each slot's own, and with shape trials the prior's codes (copied exactly, so found by equality)
    prior_codes = model.prior.latents.to(p.z_sh.dtype) if cfg.grid and (cfg.shape_trials or cfg.shape_nearest) else None
    shapes = SdfGrid.tabulate(model.sdf_fn, p.z_sh.reshape(B * Kslots, -1), model.prior.bounds, cfg.grid) if cfg.grid else None
    if prior_codes is not None:  # the codes' rows follow the slots' (search._Level.rows), tabulated once per prior
        codes = model.prior.code_table(cfg.grid)
        shapes = SdfGrid(torch.cat([shapes.values, codes.values.to(shapes.values.dtype)]), shapes.box)
    start = (out.obj_depth, out.obj_mask, out.obj_color)  # the MLP's renders of the encoder's latents
    exact = _Level(model, bg, out.bg_depth, batch.K, batch.T_world_cam, batch.rgb, target_depth, cfg, far)
    exact.set_renders(*(t.clone() for t in start))
    full = exact
    if shapes is not None:
        full = _Level(model, bg, out.bg_depth, batch.K, batch.T_world_cam, batch.rgb, target_depth, cfg, far, shapes, prior_codes)
        full.set_renders(*full.render(p))
    if cfg.coarse_rounds:
        H, W = batch.rgb.shape[-2:]
        Kc = resize_intrinsics(batch.K, 0.5, 0.5)  # pixel (i, j) of the half-size image covers pixels 2i..2i+1
        bg_depth = plane_depth(Kc, batch.T_world_cam, H // 2, W // 2, batch.ground_z, model.cfg.far_depth)
        coarse = _Level(model, bg, bg_depth, Kc, batch.T_world_cam, F.avg_pool2d(batch.rgb, 2),
                        None if target_depth is None else F.avg_pool2d(target_depth, 2), cfg, far, shapes, prior_codes)
        coarse.set_renders(*coarse.render(p))
        for r in range(cfg.coarse_rounds):
            coarse.run_round(state, r)
        # a coarse win that the full-size score does not confirm reverts
        full.confirm(state, full.render(state.params()), (full.depth, full.mask, full.color), full.best)
    table_rounds = cfg.rounds - cfg.exact_rounds
    for r in range(cfg.coarse_rounds, table_rounds):
        full.run_round(state, r)
    if shapes is not None:  # the MLP's render decides, against the encoder's own; then its own passes, if any
        exact.confirm(state, exact.render(state.params()), start, exact.best)
        for r in range(table_rounds, cfg.rounds):
            exact.run_round(state, r)
    comp = composite(exact.depth, exact.mask, exact.color, bg, out.bg_depth)
    return ModelOutput(SceneLatents(state.params(), bg), comp, exact.depth, exact.mask, exact.color, out.bg_depth, None,
                       slot_steps=out.slot_steps)
