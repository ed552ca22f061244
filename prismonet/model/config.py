"""Model configuration."""

from __future__ import annotations

import math
from dataclasses import dataclass

INPUT_MODES = ("I", "I+dI", "I+M", "I+dI+M")
SHADE_MAX = 0.97
"""The least darkening an anchor rule reads as a shadow (``anchor_shade_min``, ``AnchorRule.shade_min``): 3 %."""


@dataclass(frozen=True)
class ModelConfig:
    """Architecture of the scene model (the paper's Clevr settings where it states them)."""

    num_slots: int = 3
    """N, recurrent encoding steps (objects per scene); reset it to evaluate on other counts."""
    image_size: int = 64
    inputs: str = "I+dI+M"
    """Encoder input ablation: the image I, the difference image dI, the occlusion mask M."""
    tex_dim: int = 7
    """D_tex (the paper: 7 for Clevr)."""
    channels: tuple[int, ...] = (32, 32, 64, 64)
    """Conv blocks (3x3, stride 1, ReLU, 2x2 max-pool) of the object encoder."""
    fc: tuple[int, ...] = (256, 256)
    bg_channels: tuple[int, ...] = (16, 16, 32, 32)
    texture_width: int = 64
    texture_depth: int = 4
    scale_range: tuple[float, float] = (0.25, 0.9)
    """[s_min, s_max]: the sigmoid squashes the regressed scale into it."""
    position_offset: tuple[float, float, float] = (0.0, 0.0, 0.4)
    """Position = offset + scale * raw output: starts objects mid-scene, just above the ground."""
    position_scale: tuple[float, float, float] = (1.5, 1.5, 0.5)
    full_rotation: bool = False
    """Regress an extra rotation axis (the paper's full-6-DoF variant)."""
    pose_frame: str = "world"
    """``world``: positions and yaw in the world, as the paper (one training camera); ``camera``: the
    centre's pixel, its height and the yaw from the camera's heading (``prismonet.model.pose_frame``), for
    models trained on many cameras."""
    presence: bool = False
    """An explicit presence output per slot (issue 21, the alternative to hiding unused slots): in training
    the slots are composed as layers of opacity p (``render.composite.presence_composite``) and
    ``loss.w_presence`` charges each present slot; at inference a slot with p < 0.5 is dropped, and with
    ``stop`` the encoder stops at a scene's first absent slot."""
    presence_straight_through: bool = False
    """With ``presence``: compose in training with the presences rounded to 0 or 1 (the z-buffer of the
    present slots, as at inference) and pass the gradient through the layered composition as if they were
    not rounded. Without it, fractional presences blend slots like semi-transparent layers, which the
    image loss can exploit (measured on 1-8 objects, EVALUATION.md)."""
    presence_in_mask_loss: bool = False
    """With ``presence``: ``True`` lets L_mask, which sees each slot's soft silhouette times its presence,
    train the presence too. That collapses every presence to 0 on 1-8 objects (the silhouettes' leak
    outside their objects pushes each down; EVALUATION.md), so by default L_mask passes the presence no
    gradient."""
    detach_partials: bool = True
    """Feed the partial compositions to the encoder without gradients (cheaper, more stable)."""
    prior: str = "shipped"
    """Shape prior: ``"shipped"`` (the packaged Clevr prior), the name of another packaged prior
    (``prismonet.assets.PRIORS``, e.g. ``"cars"``) or a path stem."""
    render_samples: int = 12
    render_refine_steps: int = 0
    far_depth: float = 12.0
    soft_mask_tau: float = 0.0
    """> 0: also render soft silhouettes (world units of SDF per unit logit), needed by L_mask."""
    refine_passes: int = 0
    """Learnt refinement passes after the encoder (beyond the paper; ``prismonet.model.refiner``): each
    looks at every slot's render against the image and corrects its pose, scale and texture latent,
    then renders again. 0: the paper's model."""
    refiner_channels: tuple[int, ...] = (32, 32, 64, 64)
    """Conv blocks of the refiner (as ``channels``)."""
    refiner_fc: tuple[int, ...] = (256, 256)
    refiner_coords: bool = False
    """The refiner also sees each pixel's image position (two more input channels)."""
    refiner_glimpse: float = 0.0
    """> 0: the refiner sees each slot through a window of this fraction of the image side centred on the
    slot's projected centre, resampled to the image size (a zoom of 1 / ``refiner_glimpse``); 0: the whole image."""
    refiner_shape: bool = False
    """The refiner also corrects each slot's shape latent (a step added to it); else the shape is the encoder's."""
    refiner_shape_codes: bool = False
    """With ``refiner_shape``: instead of a step of the shape latent, the refiner chooses the slot's shape among the
    prior's training codes or the slot's own latent (a logit each, ``refiner.choose_shapes``), fitted by cross-entropy to
    the search's choice. Search targets are noisy labels; a regression of the latent onto them draws their mean, a blend
    of codes, where a choice draws the most likely one (beyond the paper; EVALUATION.md, "Session 77")."""
    refiner_keep: bool = False
    """The refiner also says whether each slot is worth keeping (a logit, trained on whether the search's fit shows
    the slot); a slot it drops becomes inactive and renders nothing, so slivers and hidden slots cost nothing."""
    refiner_turn: bool = True
    """The refinement passes turn each slot's yaw as the refiner says (inference; beyond the paper). ``False`` keeps the
    encoder's yaw: for an encoder taught yaws by L_pose, whose refiner was fitted to a weakly supervised search's yaws
    (EVALUATION.md, "Session 59"). The refiner's fit ignores it."""
    refiner_keep_logit: float = 0.0
    """With ``refiner_keep`` (inference; beyond the paper): a slot is dropped where its keep logit is at or below this, in
    every refinement pass (0: the logit's own decision, as fitted). A higher bar trades recall for precision."""
    refiner_keep_passes: int | None = None
    """With ``refiner_keep`` (inference; beyond the paper): the keep output drops slots in the first this many
    refinement passes only; the later passes move slots and never drop them (re-anchored slots' passes likewise).
    A pass added to a model for its geometry need not also add its drops (EVALUATION.md, "Session 96").
    ``None``: every pass may drop, as fitted."""
    refiner_rescue_px: int = 0
    """With ``refiner_keep`` (inference; beyond the paper): after the refinement passes, a slot the keep output dropped
    is taken back where it would show at least this many pixels of the input that the kept slots leave unexplained in
    colour, and these are half of all it would show at least (``prismonet.model.rescue``): the keep output, fitted to
    a search that fits unseen shapes badly, drops slots that are the only ones on their object. 0: off, as fitted."""
    refiner_snap_shape: bool = False
    """After each refinement pass at inference (beyond the paper), each slot's shape latent is replaced by the prior's
    nearest training code (Euclidean, in latent space; ``refiner.snap_shapes``). For a refiner fitted to targets
    searched at the true poses (``distill --true-poses --search-shapes N``), whose codes are mostly the objects' own:
    its steps can land between codes and draw a shrunken object. On weakly supervised refiners it costs accuracy
    (EVALUATION.md, "Session 65"). The refiner's fit ignores it."""
    refiner_hold_cells_from: int | None = None
    """With ``refiner_shape`` (inference; beyond the paper): refinement passes from this index on (0 is the first) step
    a slot's shape latent only within the cell of the prior training code nearest it before the pass: a slot whose step
    would make another code the nearest keeps its latent (``refiner.hold_cells``; pose, scale and texture steps as
    ever). A later pass may then sharpen a shape but not change which of the prior's shapes it draws
    (EVALUATION.md, "Session 98"). ``None``: off, as fitted. The refiner's fit ignores it."""
    color_step: bool = False
    """A learnt colour step at inference (beyond the paper; ``prismonet.model.color_step``): after the refinement
    passes, one more look at every slot (through the refiner's view: ``refiner_glimpse``, ``refiner_coords``) moves
    its texture latent, the test-time colour fit in one pass; the geometry is not touched. Training ignores it."""
    color_step_channels: tuple[int, ...] = (32, 32, 64, 64)
    """Conv blocks of the colour step (as ``channels``)."""
    color_step_fc: tuple[int, ...] = (256,)
    """Its fully connected layers."""
    color_step_passes: int = 1
    """How many times the colour step looks and moves the texture latents, each time at the image the last one made
    (the same weights; a step fitted with N passes is meant to be run with N)."""
    anchor: bool = False
    """Anchored slots (beyond the paper; ``prismonet.model.unexplained``): each encoder step is pointed at the
    deepest pixel of the largest part of the image that the slots so far leave unexplained in colour, sees that
    part as one more input channel, and regresses its centre's pixel relative to that anchor; a scene with no
    such part left stops. For scenes of many objects, whose later steps otherwise hide their slots."""
    anchor_color_tol: float = 0.25
    """With ``anchor``: the largest per-channel colour difference of an explained pixel."""
    anchor_min_area: int = 20
    """With ``anchor``: the fewest pixels of an unexplained part worth a slot."""
    anchor_shade_min: float | None = None
    """With ``anchor`` (inference; beyond the paper): a pixel the slots miss in colour still counts as explained where
    it is their composition darkened evenly by a factor of at least this (a cast shadow: ``AnchorRule.shade_min``).
    None: off, as trained."""
    anchor_shade_tol: float = 0.03
    """With ``anchor_shade_min``: how far each channel's darkening may stray from their mean."""
    anchor_gray_tol: float | None = None
    """With ``anchor`` (inference; beyond the paper): in a greyscale input image, a pixel is unexplained where the
    composition's luminance misses the input's by more than this, and no pixel reads as a shadow
    (``AnchorRule.gray_tol``). None: grey images are read as colour ones, as trained."""
    reanchor_steps: int = 0
    """With a refiner, at inference (beyond the paper): after the refinement passes, up to this many more encoder
    steps on what the *refined* slots leave unexplained, then the refiner's passes on the new slots alone. The encoder
    stopped on a composition that the refiner then corrected; a part it had given up on may now stand alone. An
    anchored model's steps are anchored, each into the scene's first empty slot (a scene with no unexplained part left
    takes none); an unanchored model's are its plain recurrent step, seeing the refined composition, each into a slot
    the keep output dropped (a slot a stop rule left empty stays empty). 0: off. Training ignores it."""
    reanchor_keep_logit: float | None = 0.0
    """With ``reanchor_steps`` and ``refiner_keep``: a re-anchored slot is dropped where its keep logit is at or below
    this (the encoder's own slots: at or below 0). The keep output was fitted on the encoder's slots, and drops most
    re-anchored ones; a lower bar keeps more of them. ``None``: re-anchored slots are never dropped."""

    def __post_init__(self) -> None:
        if self.pose_frame not in ("world", "camera"):
            raise ValueError(f"pose_frame: expected 'world' or 'camera', got {self.pose_frame!r}")
        if self.inputs not in INPUT_MODES:
            raise ValueError(f"inputs: expected one of {INPUT_MODES}, got {self.inputs!r}")
        if self.num_slots <= 0 or self.image_size <= 0 or self.tex_dim <= 0:
            raise ValueError(f"num_slots, image_size and tex_dim must be positive, got {self.num_slots}, {self.image_size}, {self.tex_dim}")
        from prismonet.files import MAX_IMAGE_SIDE, MAX_SLOTS

        if self.num_slots > MAX_SLOTS or self.image_size > MAX_IMAGE_SIDE:
            raise ValueError(f"num_slots must be at most {MAX_SLOTS} and image_size at most {MAX_IMAGE_SIDE}, got {self.num_slots}, {self.image_size}")
        if self.anchor and self.presence:
            raise ValueError("anchor and presence are two ways of leaving slots empty: choose one")
        if self.anchor_gray_tol is not None and not self.anchor_gray_tol > 0:
            raise ValueError(f"anchor_gray_tol must be > 0 (or None), got {self.anchor_gray_tol}")
        if self.anchor_shade_min is not None and not (0 < self.anchor_shade_min < SHADE_MAX and self.anchor_shade_tol > 0):
            raise ValueError(f"anchor_shade_min must be in (0, {SHADE_MAX}) and anchor_shade_tol > 0, got {self.anchor_shade_min} and {self.anchor_shade_tol}")
        if self.anchor_min_area < 1 or not self.anchor_color_tol > 0:
            raise ValueError(f"anchor_min_area must be >= 1 and anchor_color_tol > 0, got {self.anchor_min_area} and {self.anchor_color_tol}")
        if self.reanchor_steps < 0 or (self.reanchor_steps and not self.refine_passes):
            raise ValueError(f"reanchor_steps must be >= 0 and needs refine_passes >= 1, got {self.reanchor_steps}")
        if self.reanchor_keep_logit is not None and not math.isfinite(self.reanchor_keep_logit):
            raise ValueError(f"reanchor_keep_logit must be a finite number or None (never drop), got {self.reanchor_keep_logit}")
        if self.refiner_rescue_px < 0 or (self.refiner_rescue_px and not (self.refine_passes and self.refiner_keep)):
            raise ValueError(f"refiner_rescue_px must be >= 0 and needs refine_passes >= 1 and refiner_keep, got {self.refiner_rescue_px}")
        if self.refiner_keep_passes is not None and (self.refiner_keep_passes < 1 or not self.refiner_keep):
            raise ValueError(f"refiner_keep_passes must be >= 1 (or None) and needs refiner_keep, got {self.refiner_keep_passes}")
        if not math.isfinite(self.refiner_keep_logit):
            raise ValueError(f"refiner_keep_logit must be a finite number, got {self.refiner_keep_logit}")
        if (self.refiner_snap_shape or self.refiner_keep_logit != 0.0) and not self.refine_passes:
            raise ValueError("refiner_snap_shape and refiner_keep_logit act in the refinement passes: they need refine_passes >= 1")
        if self.refiner_hold_cells_from is not None and not (
                0 <= self.refiner_hold_cells_from < self.refine_passes and self.refiner_shape):
            raise ValueError(f"refiner_hold_cells_from must index a refinement pass (0 to refine_passes - 1 = "
                             f"{self.refine_passes - 1}) of a refiner that steps shapes (refiner_shape), "
                             f"got {self.refiner_hold_cells_from}")
        if self.refiner_shape_codes and not (self.refine_passes and self.refiner_shape):
            raise ValueError("refiner_shape_codes chooses the refiner's shapes: it needs refine_passes >= 1 and refiner_shape (refiner --shape)")
        if self.refine_passes < 0 or (self.refine_passes and self.presence):
            raise ValueError(f"refine_passes must be >= 0 and cannot be used with presence, got {self.refine_passes}")
        if not 0.0 <= self.refiner_glimpse <= 1.0:
            raise ValueError(f"refiner_glimpse must be in [0, 1], got {self.refiner_glimpse}")
        if self.refine_passes and self.image_size % (2 ** len(self.refiner_channels)) != 0:
            raise ValueError(f"image_size {self.image_size} must be divisible by 2^{len(self.refiner_channels)} (refiner_channels)")
        if self.color_step and self.image_size % (2 ** len(self.color_step_channels)) != 0:
            raise ValueError(f"image_size {self.image_size} must be divisible by 2^{len(self.color_step_channels)} (color_step_channels)")
        if self.color_step_passes < 1:
            raise ValueError(f"color_step_passes must be at least 1, got {self.color_step_passes}")
        if self.color_step and self.presence:
            raise ValueError("color_step cannot be used with presence (a slot's colour there is its layer's, not its own)")
        lo, hi = self.scale_range
        if not 0 < lo < hi:
            raise ValueError(f"scale_range must satisfy 0 < min < max, got {self.scale_range}")
        if self.image_size % (2 ** len(self.channels)) != 0:
            raise ValueError(f"image_size {self.image_size} must be divisible by 2^{len(self.channels)} (one pool per block)")

    @property
    def in_channels(self) -> int:
        return {"I": 3, "I+dI": 6, "I+M": 4, "I+dI+M": 7}[self.inputs] + (1 if self.anchor else 0)
