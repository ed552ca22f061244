"""The test-time steps after the encoder, as one configuration and one function (beyond the paper,
which decodes feed-forward).

In order, each off by default:

0. stopping: the encoder stops once the slots found explain the input (``prismonet.model.stopping``);
1. over-complete decoding: ``extra_slots`` more encoder steps, the best-explaining slots kept
   (``prismonet.model.select``);
1b. re-seeding: idle slots moved onto what no slot explains (``prismonet.model.reseed``); with the
   search, steps 1b and 2 repeat ``reseed.cycles`` times;
2. pose search: each slot's scale, position and yaw, by coordinate search (``prismonet.model.search``);
3. refinement: gradient steps on all latents against the training losses (``prismonet.model.refine``);
4. colour fit: texture latents and background colour against the image, geometry held
   (``prismonet.model.color_fit``);
5. pruning: the slots that explain nothing are dropped (``prismonet.model.prune``).

``use_depth`` says whether steps 0-3 (1b included) and 5 may read the scene's depth; ``False`` is the paper's test-time
input (colour alone) and what a photo gives. Every command that decodes scenes (``evaluate``,
``reconstruct``, ``demo``, ``real reconstruct``, ``distill``) builds one ``InferenceConfig`` from the
same flags and calls ``infer``, so a setting means the same thing everywhere.
"""

from __future__ import annotations

import json

from dataclasses import asdict, dataclass, field, replace
from typing import Callable

import torch

from prismonet.model.color_fit import ColorFitConfig, fit_colors
from prismonet.model.losses import LossConfig
from prismonet.model.prismonet import ModelOutput
from prismonet.model.prune import PRUNE_RULE, prune
from prismonet.model.refine import RefineConfig, refine
from prismonet.model.reseed import ReseedConfig, reseed
from prismonet.model.search import SearchConfig, search_latents, with_shape_trials
from prismonet.model.select import check_extra_slots, decode_overcomplete
from prismonet.model.stopping import StopRule


@dataclass(frozen=True)
class InferenceConfig:
    """What runs after the encoder at test time (every step off: the paper's feed-forward decoding)."""

    extra_slots: int = 0
    """Decode this many more encoder steps and keep the slots that best explain the input."""
    search: SearchConfig = field(default_factory=lambda: SearchConfig(rounds=0))
    """Pose search (``rounds`` 0: none; 3 is the measured setting)."""
    refine: RefineConfig = field(default_factory=lambda: RefineConfig(steps=0))
    """Gradient refinement of all latents (``steps`` 0: none)."""
    color_fit: ColorFitConfig = field(default_factory=lambda: ColorFitConfig(steps=0))
    """Colour fit, last (``steps`` 0: none; 50 is the measured setting)."""
    use_depth: bool = True
    """Whether stopping, slot selection, search and refinement may read the scene's depth."""
    stop: StopRule | None = None
    """Stop the encoder when the slots so far explain the input (``None``: every slot is decoded)."""
    prune: StopRule | None = None
    """Last, drop the slots that explain nothing by this rule's ``min_gain`` (``None``: keep every slot)."""
    reseed: ReseedConfig = field(default_factory=ReseedConfig)
    """Move idle slots onto unexplained parts of the input, after the slot choice (``rounds`` 0: none)."""

    def __post_init__(self) -> None:
        check_extra_slots(self.extra_slots)

    @classmethod
    def of(cls, extra_slots: int = 0, search: int = 0, refine: int = 0, fit_color: int = 0, use_depth: bool = True,
           refine_lr: float | None = None, refine_pose_lr_scale: float | None = None, stop: bool = False,
           prune: bool = False, search_scales: tuple[float, ...] | None = None,
           search_far_clip: bool = False, search_coarse: int = 0, search_grid: int | None = None,
           search_shapes: int = 0, reseed: int = 0, reseed_cycles: int = 1, reseed_grow: int = 0,
           search_set: list[str] | None = None, shape_trials: bool = False,
           reseed_on_objects: bool = False, reseed_replace: bool = False) -> "InferenceConfig":
        """From step counts, with every other setting at its measured default (validates each). ``shape_trials``: the
        search takes ``SHAPE_TRIAL_SETTINGS`` (``search`` must be 3 or more; with ``search_grid`` its passes render from
        that table and one more with the MLP follows, ``with_shape_trials``); ``search_grid`` ``None``: 0, the MLP.
        ``search_set``: more ``FIELD=VALUE`` settings of the search (``SearchConfig``, values as JSON), applied last."""
        overrides = {"lr": refine_lr, "pose_lr_scale": refine_pose_lr_scale}
        scales = {} if search_scales is None else {"scales": tuple(search_scales)}
        search_cfg = SearchConfig(rounds=search, far_clip=search_far_clip, coarse_rounds=search_coarse, grid=search_grid or 0,
                                  shape_nearest=search_shapes, **scales)
        if shape_trials:
            search_cfg = with_shape_trials(search_cfg)
        if search_set:
            from prismonet.config import ConfigError, load_config, to_dict

            now = [f"{k}={json.dumps(v)}" for k, v in to_dict(search_cfg).items()]
            try:
                search_cfg = load_config(SearchConfig, "-", now + list(search_set))
            except ConfigError as e:
                raise ValueError(f"search setting: {e}") from None
        return cls(extra_slots, search_cfg,
                   RefineConfig(refine, **{k: v for k, v in overrides.items() if v is not None}),
                   ColorFitConfig(fit_color), use_depth, StopRule() if stop else None, PRUNE_RULE if prune else None,
                   ReseedConfig(rounds=reseed, cycles=reseed_cycles, grow=reseed_grow, on_objects=reseed_on_objects,
                                replace_least=reseed_replace))

    @property
    def feed_forward(self) -> bool:
        """True when nothing runs after the encoder."""
        return not (self.extra_slots or self.reseed.rounds or self.search.rounds or self.refine.steps or self.color_fit.steps or self.stop
                    or self.prune)

    def without_depth(self) -> "InferenceConfig":
        return replace(self, use_depth=False)

    def describe(self) -> str:
        """One line, e.g. ``encoder, then 3 pose-search rounds, 50 colour-fit steps``."""
        steps = [f"{self.extra_slots} extra slots" if self.extra_slots else "",
                 (f"{self.reseed.rounds} re-seeding rounds" + (f" (then the search, {self.reseed.cycles} times)"
                  if self.reseed.cycles > 1 and self.search.rounds else "")
                  + (f" with {self.reseed.grow} slots added" if self.reseed.grow else "")
                  + (", also on other objects" if self.reseed.on_objects else "")
                  + (", replacing the least useful slot when none is idle" if self.reseed.replace_least else "")) if self.reseed.rounds else "",
                 (f"{self.search.rounds} pose-search rounds" + ("" if self.search.scales == SearchConfig().scales else
                  " (scales " + ", ".join(f"{v:g}" for v in self.search.scales) + ")")
                  + (", depth clipped" if self.search.far_clip else "")
                  + (f", the first {self.search.coarse_rounds} at half size" if self.search.coarse_rounds else "")
                  + (f", shapes tabulated at {self.search.grid}^3" if self.search.grid else "")
                  + (f" in the first {self.search.rounds - self.search.exact_rounds}" if self.search.exact_rounds else "")
                  + (f", the {self.search.shape_nearest} nearest prior codes tried" if self.search.shape_nearest else "")
                  + ((", every code of each category tried at the slot's footprint" if self.search.shape_footprint else
                      ", each category's nearest code tried") if self.search.shape_trials else "")) if self.search.rounds else "",
                 f"{self.refine.steps} refinement steps" if self.refine.steps else "",
                 f"{self.color_fit.steps} colour-fit steps" if self.color_fit.steps else "",
                 "pruning the slots that explain nothing" if self.prune else ""]
        steps = [s for s in steps if s]
        where = "" if self.use_depth or not (steps or self.stop) else " (colour only)"
        enc = "encoder stopping when explained" if self.stop else "encoder"
        if not steps:
            return enc + where if self.stop else "encoder only, as the paper"
        return f"{enc}, then " + ", ".join(steps) + where

    def record(self) -> dict:
        """The settings as plain JSON values."""
        return asdict(self)


def infer(model, batch, cfg: InferenceConfig = InferenceConfig(), loss_cfg: LossConfig | None = None,
          num_slots: int | None = None, on_step: Callable[[str, ModelOutput], None] | None = None,
          start: Callable[[ModelOutput], ModelOutput] | None = None) -> ModelOutput:
    """``model``'s decomposition of ``batch`` after the steps of ``cfg``.

    Args:
        model: a ``PriSMONet``.
        batch: a ``Batch`` (``rgb (B, 3, H, W)``, ``depth (B, 1, H, W)``, camera, ground height).
        cfg: the test-time steps.
        loss_cfg: the training losses (selection weights and refinement objective; default ``LossConfig()``).
        num_slots: slots kept (default: the model's).
        on_step: called as ``on_step(name, output)`` after each step that ran: ``"encoder"``,
            ``"reseeded"``, ``"searched"``, ``"refined"``, ``"color_fit"``, ``"pruned"``.
        start: maps the encoder's output to the one the test-time steps start from (distillation targets at the
            true poses, ``prismonet.model.pose_targets.start_at_truth``); ``None``: the encoder's own.
    """
    loss_cfg = loss_cfg or LossConfig()
    report = on_step or (lambda name, out: None)
    with torch.no_grad():
        out = decode_overcomplete(model, batch, num_slots, cfg.extra_slots, use_depth=cfg.use_depth,
                                  w_image=loss_cfg.w_image, w_depth=loss_cfg.w_depth, stop=cfg.stop)
    report("encoder", out)
    if start is not None:
        out = start(out)
    for cycle in range(cfg.reseed.cycles if cfg.reseed.rounds and cfg.search.rounds else 1):
        if cfg.reseed.rounds > 0:
            step = cfg.reseed if cycle == 0 else replace(cfg.reseed, grow=0)  # slots are added once
            out = reseed(model, out, batch, step, use_depth=cfg.use_depth)
            report("reseeded", out)
        if cfg.search.rounds > 0:
            with torch.no_grad():
                out = search_latents(model, out, batch, cfg.search, use_depth=cfg.use_depth)
            report("searched", out)
    if cfg.refine.steps > 0:
        out = refine(model, out, batch, loss_cfg, cfg.refine, use_depth=cfg.use_depth)
        report("refined", out)
    if cfg.color_fit.steps > 0:
        out = fit_colors(model, out, batch, cfg.color_fit)
        report("color_fit", out)
    if cfg.prune is not None:
        with torch.no_grad():
            out = prune(out, batch.rgb, batch.depth if cfg.use_depth else None, cfg.prune)
        report("pruned", out)
    return out
