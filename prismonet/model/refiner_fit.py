"""Training the refiner (``prismonet.model.refiner``) on self-distillation targets, the encoder frozen.

1. The trained model decodes the scenes that have targets (``prismonet distill``: the test-time search and
   colour fit on *training* scenes, from their RGB-D alone), once, without refinement; its composite, slot
   silhouettes and latents are kept in memory.
2. The refiner learns to move those slots onto their targets: ``distill.distill_loss`` on the corrected
   latents (position, scale, yaw, texture, and the shape when the refiner corrects it and the targets have shapes;
   hidden slots are not targets). A refiner with a keep output also learns which slots the fit shows
   (``KEEP_WEIGHT``), hidden ones included. No render is needed, so a step
   costs a few milliseconds. Optional later-pass terms fit it on what its later passes see as well, each from a cache
   made once by the refiner the fit starts from: the slots the re-anchoring adds (``reanchored``, ``reanchor_cache``)
   and the first pass's output (``second_pass``, ``second_pass_cache``); ``subjects_term`` is their loss.
3. The last ``holdout`` scenes with targets are held out: their loss is logged beside the loss of no
   correction at all, so a run shows how much of the way to the search it goes on scenes it did not fit.

Resumable: ``RUN/checkpoint.safetensors`` (refiner, Adam, step) is written atomically every
``checkpoint_every`` steps; rerunning the same command resumes. The result is a whole scene model,
``RUN/model.safetensors`` + ``RUN/model.json`` (the encoder's weights, the refiner's, ``refine_passes`` 1).
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import torch

from prismonet.model.distill import (MIN_VISIBLE, SHAPE, VISIBLE, DistillError, DistillTargets, DistillWeights,
                                     distill_loss, keep_loss, seen_slots, shown_mean)
from prismonet.model.refiner import apply_correction, shape_labels, split_keep

KEEP_WEIGHT = 0.2
"""Weight of the keep logit's binary cross-entropy (a refiner with ``refiner_keep``): the target is whether the
search's fit shows the slot (``distill.MIN_VISIBLE`` pixels or more), over every slot of a scene with targets."""
SHAPE_CODE_WEIGHT = 0.1
"""Weight of the shape choice's cross-entropy (a refiner with ``refiner_shape_codes``), in place of the shape latent's
regression: the target class is the search's (``refiner.shape_labels``), over the slots the fit shows."""


@dataclass(frozen=True)
class RefinerFitConfig:
    """One refiner training run."""

    steps: int = 3000
    batch_size: int = 32
    """Scenes per step (each gives ``num_slots`` slot views)."""
    lr: float = 3e-4
    """Adam; a cosine from it down to 1 % at ``steps``."""
    weight_decay: float = 1e-4
    holdout: int = 256
    """The last scenes with targets, held out for the logged validation loss."""
    seed: int = 0
    checkpoint_every: int = 250
    texture: float = 0.1
    """Weight of the texture-latent term (``DistillWeights.texture``)."""
    color: float = 0.0
    """Weight of the colour term (``color_term``): the texture field's colours under the corrected and the target
    texture latents, compared at fixed points of the object frame. 0: off (the fits before session 51)."""
    true_poses: bool = False
    """Fit the slots the search shows to the true poses of the objects they match, not to the search's
    (``prismonet.model.pose_targets``): supervised, the + 3D pose variant. Shapes, textures and the keep target stay the
    search's."""
    fill_hidden: bool = False
    """With ``true_poses``: the true objects no shown slot matches go to the hidden slots, which become targets
    (``pose_targets.with_true_poses``)."""
    recolor: bool = False
    """The refiner sees every training scene with new object colours (``prismonet.data.recolor.RecoloredScenes``,
    drawn once per scene from ``seed``), the encoder's cached decoding included, so that it cannot tell a seen model by
    its colour (EVALUATION.md, sessions 73-74). The targets' poses and shapes do not depend on colour; their texture
    latents do, so ``texture`` and ``color`` must be 0."""
    gray_share: float = 0.0
    """> 0: the refiner sees this share of the training scenes grey (``prismonet.data.gray.GrayScenes``, drawn once per
    scene from ``seed``), the encoder's cached decoding included, as a greyscale photo shows them; the targets stay the
    search's fits to the colour scenes. Their texture latents are colours a grey scene does not show, so ``texture``
    and ``color`` must be 0 (unless ``gray_targets``)."""
    reanchored: float = 0.0
    """> 0: the refiner is also fitted on the slots the model's re-anchoring adds (``reanchor_cache``: what its passes
    on them see), with this weight, against targets made by the whole model (``prismonet distill`` from the same
    model, so slot k of the targets is slot k of its output, re-anchored slots included, and none dropped: keep bars
    off). The encoder's rows of the slots it left empty are then not targets. Needs an anchored model with
    ``reanchor_steps`` and a refiner, whose current refiner makes the re-anchored slots (EVALUATION.md, "Session 96").
    0: off (the fits before session 96)."""
    second_pass: float = 0.0
    """> 0: the refiner is also fitted on what its second pass sees (``second_pass_cache``: the decoding after the
    model's first pass, the slots that pass dropped left out), with this weight, against the same targets, which must
    be in the model's slot order (made by the model, or by its encoder where refinement keeps the slots' order; for
    an anchored model that re-anchors, by the whole model as for ``reanchored``). The first pass's inputs are the encoder's decoding, the later passes' are the
    refiner's own output, which a fit on the encoder's rows alone never shows it. Needs a model with a refiner of two
    passes or more, whose current refiner makes the cache (EVALUATION.md, "Session 97"). 0: off."""
    second_pass_shape: bool = True
    """With ``second_pass`` and a refiner that corrects shapes: the second-pass term regresses the shape latent too.
    ``False``: its shape weight is 0, so the shape step is fitted on the encoder's rows alone."""
    keep_best: bool = False
    """Save the refiner at its lowest logged held-out loss (every ``checkpoint_every`` steps, the starting refiner
    included) rather than at the last step: early stopping on the held-out scenes (``part_fit.BestHeldOut``; session
    106's 4-object fine-tune was best at step 250 of 3,000). False: the last step's (the fits before session 107)."""
    gray_targets: bool = False
    """The targets were fitted on the grey scenes themselves (``prismonet distill --gray``, ``DistillTargets.gray``): slot
    k's target is what the grey decoding's slot k found, and its texture latent a grey fit. Needs ``gray_share`` 1;
    ``texture`` and ``color`` may then be used."""

    def __post_init__(self) -> None:
        if self.steps <= 0 or self.batch_size <= 0 or self.lr <= 0 or self.holdout < 0 or self.checkpoint_every <= 0:
            raise ValueError("refiner fit: steps, batch_size, lr and checkpoint_every must be positive and holdout >= 0, got "
                             f"{self.steps}, {self.batch_size}, {self.lr}, {self.checkpoint_every}, {self.holdout}")
        if self.fill_hidden and not self.true_poses:
            raise ValueError("refiner fit: fill_hidden needs true_poses (it gives hidden slots the true poses left over)")
        if self.recolor and (self.texture > 0 or self.color > 0):
            raise ValueError("refiner fit: recolor needs texture = 0 and color = 0 (the targets' texture latents are "
                             f"the scenes' own colours), got {self.texture}, {self.color}")
        if self.gray_targets and self.gray_share != 1:
            raise ValueError(f"refiner fit: targets fitted on grey scenes need gray_share 1 (every scene grey), got {self.gray_share}")
        if not 0 <= self.gray_share <= 1 or (self.gray_share > 0 and not self.gray_targets and (self.texture > 0 or self.color > 0)):
            raise ValueError("refiner fit: gray_share must be in [0, 1], and with it texture = 0 and color = 0 (a grey scene "
                             f"does not show the targets' colours), got {self.gray_share}, {self.texture}, {self.color}")
        for name in ("reanchored", "second_pass"):
            w = getattr(self, name)
            if w < 0 or (w > 0 and (self.true_poses or self.recolor or self.gray_share > 0)):
                raise ValueError(f"refiner fit: {name} must be >= 0, and cannot be used with true_poses, recolor or "
                                 f"gray_share, got {w}")
        if self.weight_decay < 0 or self.texture < 0 or self.color < 0:
            raise ValueError(f"refiner fit: weight_decay, texture and color must be >= 0, got {self.weight_decay}, {self.texture}, {self.color}")


def with_refiner(model, passes: int = 1, **fields):
    """A copy of a trained scene model with a fresh (identity) refiner of ``passes`` passes; the
    encoder, background encoder and texture field keep their weights. ``fields``: other ``ModelConfig``
    refiner settings (``refiner_glimpse``, ``refiner_coords``, ``refiner_channels``, ``refiner_fc``, ``refiner_shape``,
    ``refiner_shape_codes``, ``refiner_keep``); a refiner the model already has is replaced. With no passes the steps
    after refinement (``reanchor_steps``), which need them, are off too."""
    from prismonet.model.io import rebuilt

    bad = [k for k in fields if not k.startswith("refiner_")]
    if bad:
        raise ValueError(f"with_refiner: only refiner settings may change, got {bad}")
    steps = {} if passes else {"reanchor_steps": 0}
    return rebuilt(model, "refiner.", refine_passes=passes, **steps, **fields)


def with_shape_step(model):
    """A copy of a model whose refiner has no shape step (``refiner_shape`` off) with one added: every refiner weight as
    it was, and the head's new shape rows zero, so the copy decodes exactly as ``model`` until it is trained on (a
    refiner fine-tuned to correct shapes as well, e.g. on shape-trial search targets)."""
    from prismonet.model.io import rebuilt

    if not model.cfg.refine_passes or model.cfg.refiner_shape:
        raise ValueError("with_shape_step adds a shape step to a refiner without one: the model has "
                         + ("no refiner" if not model.cfg.refine_passes else "one already"))
    new = rebuilt(model, f"refiner.head.{len(model.refiner.head) - 1}.", refiner_shape=True)  # a fresh last layer: zero
    old, fresh = model.refiner.head[-1], new.refiner.head[-1]
    tex_end, sh = 5 + model.cfg.tex_dim, model.prior.latents.shape[1]
    with torch.no_grad():
        for w, w_old in ((fresh.weight, old.weight), (fresh.bias, old.bias)):
            w[:tex_end] = w_old[:tex_end]
            w[tex_end + sh:] = w_old[tex_end:]  # the keep logit, where there is one
    return new


LATENTS = ("z_sh", "z_tex", "position", "cos_sin", "scale")


def _append_decoding(rows: dict[str, list[torch.Tensor]], out) -> None:
    """Add a decoding ``out`` to a cache's ``rows``: composite colour (float16), instance ids, slot silhouettes, latents,
    and the slots' activity where it has one."""
    p = out.latents.params
    rows.setdefault("comp", []).append(out.composite.image.half())
    rows.setdefault("instance", []).append(out.composite.instance.to(torch.uint8))
    rows.setdefault("obj_mask", []).append(out.obj_mask)
    for k in LATENTS:
        rows.setdefault(k, []).append(getattr(p, k))
    if p.active is not None:
        rows.setdefault("active", []).append(p.active)


@torch.no_grad()
def _decoding_cache(model, ds, count: int, batch_size: int, progress: bool, desc: str, decode) -> dict[str, torch.Tensor]:
    """A cache of scenes ``0 .. count-1``, a batch at a time: ``decode(batch)`` gives a decoding and ``(B, N)`` bool, the
    slots a later pass acts on (``subjects``; ``None``: no such field), kept with ``_append_decoding``'s fields."""
    from tqdm import tqdm

    model.eval()
    rows: dict[str, list[torch.Tensor]] = {}
    for s in tqdm(range(0, count, batch_size), desc=desc, unit="batch", disable=not progress):
        out, subjects = decode(ds.batch(list(range(s, min(s + batch_size, count)))).to(model.pos_scale.device))
        _append_decoding(rows, out)
        if subjects is not None:
            rows.setdefault("subjects", []).append(subjects)
    return {k: torch.cat(v) for k, v in rows.items()}


def encoder_cache(model, ds, count: int, batch_size: int = 64, progress: bool = True) -> dict[str, torch.Tensor]:
    """The model's unrefined decoding of scenes ``0 .. count-1``: composite colour (float16), instance
    ids, slot silhouettes and latents (and ``active``, where the encoder leaves slots empty), on the model's device."""
    return _decoding_cache(model, ds, count, batch_size, progress, "encoder outputs",
                           lambda b: (model(b.rgb, b.K, b.T_world_cam, b.ground_z, refine=False), None))


def reanchor_cache(model, ds, count: int, batch_size: int = 64, progress: bool = True) -> dict[str, torch.Tensor]:
    """What the refiner's passes on re-anchored slots see, for scenes ``0 .. count-1``: the model decodes each scene,
    refines it (``refine_slots``) and re-anchors it (``reanchor_slots``), as at inference; the composite, instance ids,
    slot silhouettes and latents of that moment (``encoder_cache``'s fields) and ``subjects (S, N)``, the slots the
    re-anchoring put in (those the passes then act on). Needs an anchored model with ``reanchor_steps`` and a refiner."""
    if not (model.cfg.anchor and model.cfg.reanchor_steps and model.cfg.refine_passes):
        raise DistillError("reanchor_cache needs an anchored model with reanchor_steps and a refiner")

    def decode(b):
        out = model.refine_slots(model(b.rgb, b.K, b.T_world_cam, b.ground_z, refine=False), b.rgb, b.K, b.T_world_cam,
                                 b.ground_z)
        return model.reanchor_slots(out, b.rgb, b.K, b.T_world_cam, b.ground_z)

    return _decoding_cache(model, ds, count, batch_size, progress, "re-anchored slots", decode)


def second_pass_cache(model, ds, count: int, batch_size: int = 64, progress: bool = True) -> dict[str, torch.Tensor]:
    """What the refiner's second pass sees, for scenes ``0 .. count-1``: the model decodes each scene and takes its
    first refinement pass as at inference (its keep bar included); the composite, instance ids, slot silhouettes and
    latents after it (``encoder_cache``'s fields) and ``subjects (S, N)``, the slots still active, on which the second
    pass acts. Needs a refiner of two passes or more."""
    if model.cfg.refine_passes < 2:
        raise DistillError(f"second_pass_cache needs a refiner of two passes or more, the model has {model.cfg.refine_passes}")

    def decode(b):
        out = model.refine_pass(model(b.rgb, b.K, b.T_world_cam, b.ground_z, refine=False), b.rgb, b.K, b.T_world_cam, 0)
        p = out.latents.params
        return out, p.active if p.active is not None else torch.ones_like(p.scale, dtype=torch.bool)

    return _decoding_cache(model, ds, count, batch_size, progress, "first-pass outputs", decode)


def subjects_term(model, scache, ds, targets: DistillTargets, idx: torch.Tensor, weights: DistillWeights) -> torch.Tensor:
    """``()``: the refiner's loss on the subject slots of scenes ``idx`` in a cache of what a later pass sees
    (``reanchor_cache``, ``second_pass_cache``: ``scache``): the regression onto their targets over those the fit shows,
    plus ``KEEP_WEIGHT`` times the keep logits' binary cross-entropy over all of them, each a mean over a scene's
    subjects, then over the scenes that have targets and subjects (0 when none has)."""
    from prismonet.render import SceneParams

    idx = idx.to(scache["scale"].device)
    idx = idx[scache["subjects"][idx].any(1)]
    if not len(idx):
        return scache["scale"].new_zeros(())
    params = SceneParams(*(scache[k][idx] for k in LATENTS))
    delta, keep_logit = split_keep(model.refiner(*cached_refiner_inputs(model, scache, ds, idx, params)), model.cfg.refiner_keep)
    new = apply_correction(params, delta, model.pos_scale, model.cfg.scale_range)
    t, have = targets.lookup(idx)
    added = scache["subjects"][idx].to(new.scale.dtype)
    shown = seen_slots(t, added)
    # the regression over the shown subjects: ``distill_loss`` with the other slots marked hidden
    loss = distill_loss(new, t["bg_color"], {**t, VISIBLE: shown * added * MIN_VISIBLE}, have,
                        replace(weights, background=0.0))
    if keep_logit is not None:
        bce = torch.nn.functional.binary_cross_entropy_with_logits(keep_logit.reshape(added.shape), shown, reduction="none")
        per_scene = (bce * added).sum(1) / added.sum(1)
        loss = loss + KEEP_WEIGHT * (per_scene * have).sum() / have.sum().clamp_min(1.0)
    return loss


def cached_refiner_inputs(model, cache, ds, idx: torch.Tensor, params) -> tuple[torch.Tensor, torch.Tensor]:
    """The refiner's inputs for the cached decodings of scenes ``idx`` of ``ds`` (their latents ``params``)."""
    b = ds.batch(idx.tolist()).to(idx.device)
    return model.refiner_inputs(b.rgb, cache["comp"][idx].float(), cache["instance"][idx].long(), cache["obj_mask"][idx],
                                params, b.K, b.T_world_cam)


COLOR_POINTS = 64
"""Points of the object frame at which ``color_term`` compares colours: fixed, uniform in the shapes' box [-1, 1]^3."""


def color_points(n: int = COLOR_POINTS) -> torch.Tensor:
    """``(n, 3)``: the fixed comparison points (the same for every run: seed 0)."""
    return torch.rand(n, 3, generator=torch.Generator().manual_seed(0), device="cpu") * 2 - 1  # moved where it is used


def color_term(color_fn, z_tex: torch.Tensor, target_z_tex: torch.Tensor, targets: dict[str, torch.Tensor], mask: torch.Tensor,
               points: torch.Tensor) -> torch.Tensor:
    """``()``: the squared colour difference (RGB summed, mean over ``points (P, 3)``) of ``color_fn`` under ``z_tex (B, K, D)``
    and under ``target_z_tex``, the mean over each scene's slots that the fit shows (``seen_slots``; 0 if none), then
    over the scenes with targets (``mask``). What PSNR measures inside objects, where a squared distance of texture
    latents weighs every latent direction alike, whether it changes a colour or not."""
    B, K, D = z_tex.shape
    x = points.to(z_tex)[None, None].expand(B, K, -1, -1)
    got = color_fn(z_tex[:, :, None].expand(-1, -1, len(points), -1), x)
    with torch.no_grad():
        want = color_fn(target_z_tex[:, :, None].expand(-1, -1, len(points), -1), x)
    return shown_mean(((got - want) ** 2).sum(-1).mean(-1), targets, mask)


def shape_choice_term(logits: torch.Tensor, own: torch.Tensor, targets: dict[str, torch.Tensor], mask: torch.Tensor,
                      codes: torch.Tensor) -> torch.Tensor:
    """``()``: the cross-entropy of the shape logits ``(B, K, 1 + S)`` against the search's choice (``shape_labels`` of
    the targets' shapes, ``own (B, K, D_sh)`` the slots' latents before the refiner), the mean over each scene's slots
    that the fit shows (``seen_slots``; 0 if none), then over the scenes with targets (``mask``)."""
    labels = shape_labels(own, targets[SHAPE], codes)
    ce = torch.nn.functional.cross_entropy(logits.flatten(0, 1), labels.flatten(), reduction="none").reshape(labels.shape)
    return shown_mean(ce, targets, mask)


def _loss(model, cache, ds, targets: DistillTargets, idx: torch.Tensor, weights: DistillWeights, color: float = 0.0,
          later: tuple[tuple[dict[str, torch.Tensor], float, bool], ...] = ()) -> torch.Tensor:
    """The fit's loss on scenes ``idx``: the refiner on the encoder's rows (``cache``), plus ``weight *
    subjects_term`` for each ``(cache, weight, shape)`` of ``later``, caches of what later passes see (``shape``
    ``False``: without the shape latent's regression), made with targets of the whole model: a slot the encoder left
    empty is then no target of the encoder's rows."""
    from prismonet.render import SceneParams

    idx = idx.to(cache["scale"].device)  # the batch, the cache and the targets go where the model is
    params = SceneParams(*(cache[k][idx] for k in LATENTS))
    delta, keep_logit = split_keep(model.refiner(*cached_refiner_inputs(model, cache, ds, idx, params)), model.cfg.refiner_keep)
    codes = model.shape_codes()
    new = apply_correction(params, delta, model.pos_scale, model.cfg.scale_range, codes=codes)  # every slot moves: the regression sees all
    t, have = targets.lookup(idx)
    if later and "active" in cache:  # targets of the whole model: a slot the encoder left empty is not its
        t = {**t, VISIBLE: torch.where(cache["active"][idx], t[VISIBLE], torch.zeros_like(t[VISIBLE]))}
    if codes is not None:  # the shape is a choice, fitted by its own term, not regressed
        weights = replace(weights, shape=0.0)
    loss = distill_loss(new, t["bg_color"], t, have, weights)
    if codes is not None:
        tex_end = 5 + params.z_tex.shape[-1]
        logits = delta.reshape(len(idx), params.scale.shape[1], -1)[..., tex_end:]
        loss = loss + SHAPE_CODE_WEIGHT * shape_choice_term(logits, params.z_sh, t, have, codes)
    if color:
        loss = loss + color * color_term(model.color_fn, new.z_tex, t["z_tex"], t, have, color_points())
    if keep_logit is not None:
        loss = loss + KEEP_WEIGHT * keep_loss(keep_logit.reshape(len(idx), -1), t, have)
    for scache, w, shape in later:
        loss = loss + w * subjects_term(model, scache, ds, targets, idx, weights if shape else replace(weights, shape=0.0))
    return loss


def _held_out_loss(model, cache, ds, targets, idx: torch.Tensor, weights, batch: int = 128, color: float = 0.0,
                   later: tuple[tuple[dict[str, torch.Tensor], float, bool], ...] = ()) -> float:
    model.refiner.eval()
    with torch.no_grad():
        parts = [(_loss(model, cache, ds, targets, idx[i:i + batch], weights, color, later),
                  len(idx[i:i + batch])) for i in range(0, len(idx), batch)]
    model.refiner.train()
    return float(sum(l * n for l, n in parts) / max(1, sum(n for _, n in parts)))


def refiner_record(model) -> dict:
    """The model's refiner settings that differ from ``ModelConfig``'s defaults (empty for the session-43 design)."""
    from prismonet.model.config import ModelConfig

    default = ModelConfig()
    names = ("refiner_glimpse", "refiner_coords", "refiner_channels", "refiner_fc", "refiner_shape", "refiner_shape_codes",
             "refiner_keep")
    return {n.removeprefix("refiner_"): getattr(model.cfg, n) for n in names if getattr(model.cfg, n) != getattr(default, n)}


def _later_caches(model, ds, count: int, cfg: RefinerFitConfig, targets: DistillTargets, cache, progress: bool
                  ) -> tuple[tuple[dict[str, torch.Tensor], float, bool], ...]:
    """The ``(cache, weight, shape)`` of each later-pass term the fit has on (``reanchored``, ``second_pass``), made by
    the refiner the fit starts from, before a resumed run loads its later weights."""
    makers = [(w, make, shape) for w, make, shape in ((cfg.reanchored, reanchor_cache, True),
                                                      (cfg.second_pass, second_pass_cache, cfg.second_pass_shape)) if w]
    if not makers:
        return ()
    if model.cfg.refiner_shape_codes or VISIBLE not in targets.t:
        raise DistillError("reanchored, second_pass: need targets that say which slots the fit shows, and a refiner "
                           "without shape codes")
    if cache is not None and "active" not in cache:
        raise DistillError("reanchored, second_pass: the encoder cache must hold the encoder's active slots "
                           "(encoder_cache makes it)")
    return tuple((make(model, ds, count, progress=progress), w, shape) for w, make, shape in makers)


def fit_refiner(model, ds, targets_dir: str | Path, out_dir: str | Path, cfg: RefinerFitConfig = RefinerFitConfig(),
                info: dict | None = None, progress: bool = True, cache: dict[str, torch.Tensor] | None = None,
                device: torch.device | str = "cpu") -> dict:
    """Train ``model``'s refiner (``model.cfg.refine_passes`` >= 1; see ``with_refiner``) on the targets in
    ``targets_dir`` for the scenes of ``ds`` (the split they were made on), then save the whole model in
    ``out_dir``. ``info``: the base model's record (its training config is kept). ``cache``: ``encoder_cache``'s
    output for these scenes, when several refiners are fitted on one encoder (else it is computed here).
    ``device``: where the model, the cache and each batch go (the checkpoints and the model are saved from the CPU, so a
    run may resume on another device). Returns a summary."""
    from prismonet.checkpoint import resume_part, save_part
    from prismonet.model.part_fit import BestHeldOut, append_row, batch_indices, fit_steps, read_rows
    from prismonet.model.io import save_model

    if not model.cfg.refine_passes:
        raise DistillError("the model has no refiner (refine_passes 0): start from with_refiner(model)")
    targets = DistillTargets(targets_dir, model.cfg.num_slots)
    if targets.gray != cfg.gray_targets:
        raise DistillError(f"{targets_dir}: targets fitted on {'grey' if targets.gray else 'colour'} scenes, but the fit "
                           f"was set up for {'grey' if cfg.gray_targets else 'colour'} ones (RefinerFitConfig.gray_targets)")
    if model.cfg.refiner_keep and VISIBLE not in targets.t:
        raise DistillError(f"{targets_dir}: these targets do not say which slots the fit shows, so a refiner that keeps "
                           "or drops slots has nothing to learn it from; make them again with `prismonet distill`")
    if model.cfg.refiner_shape and SHAPE not in targets.t:
        raise DistillError(f"{targets_dir}: no shape latents in these targets, so a refiner that corrects shapes has nothing "
                           "to learn them from; make targets with --search-shapes N, or leave the shape out")
    count = min(targets.count, len(ds))
    if count <= cfg.holdout:
        raise DistillError(f"{targets_dir}: {targets.count} scenes with targets, need more than the {cfg.holdout} held out")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    # ``steps`` may change when a run resumes (to train longer); nothing else may
    # the options added later are recorded only when on, so runs made before them resume
    fit = {k: v for k, v in asdict(cfg).items()
           if k != "steps" and not (k in ("color", "true_poses", "fill_hidden", "recolor", "gray_share", "gray_targets",
                                          "reanchored", "second_pass", "keep_best") and not v)
           and not (k == "second_pass_shape" and (v or not cfg.second_pass))}
    record = {"fit": fit, "targets": str(targets_dir), "target_scenes": count}
    if refiner_record(model):  # recorded when not the default, so older runs still resume
        record["refiner"] = refiner_record(model)
    if cfg.true_poses:
        from prismonet.model.pose_targets import true_poses_for

        targets.t, record["true_poses"] = true_poses_for(targets.t, ds, count, cfg.fill_hidden)
        targets.count = count
    if cfg.recolor:
        from prismonet.data.recolor import RecoloredScenes

        if cache is not None:
            raise DistillError("recolor: the encoder's cache must be made from the recoloured scenes, so it is made here")

        ds = RecoloredScenes(ds, model.cfg.far_depth, seed=cfg.seed)
    if cfg.gray_share > 0:
        from prismonet.data.gray import GrayScenes

        if cache is not None:
            raise DistillError("gray_share: the encoder's cache must be made from the grey scenes, so it is made here")
        ds = GrayScenes(ds, cfg.gray_share, seed=cfg.seed)
    ckpt = out / "checkpoint.safetensors"
    model.to(device)
    weights = DistillWeights(background=0.0, texture=cfg.texture)
    later = _later_caches(model, ds, count, cfg, targets, cache, progress)
    opt = torch.optim.AdamW(model.refiner.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    step = resume_part(ckpt, "refiner.", model.refiner, opt, record, DistillError)
    if 0 < cfg.steps <= step:  # a finished run resumed: no step left to take, so no cache to make (minutes of decoding)
        cache = None
    elif cache is None:
        cache = encoder_cache(model, ds, count, progress=progress)
    elif len(cache["scale"]) < count:
        raise DistillError(f"the encoder cache holds {len(cache['scale'])} scenes, the targets {count}")
    else:
        cache = {k: v.to(device) for k, v in cache.items()}
    train_n = count - cfg.holdout
    held = torch.arange(train_n, count)
    log = out / "log.jsonl"
    later = tuple(({k: v.to(device) for k, v in c.items()}, w, shape) for c, w, shape in later)
    held_out = lambda: _held_out_loss(model, cache, ds, targets, held, weights, color=cfg.color, later=later)  # noqa: E731
    best = BestHeldOut(out / "best_refiner.safetensors", "refiner.", record, DistillError) if cfg.keep_best else None
    if step == 0:
        log.write_text("")
        start = held_out()
        append_row(log, {"step": 0, "held_out": start})  # the refiner as it starts (no correction when fresh)
        if best is not None:
            best.offer(0, start, model.refiner)

    def loss_at(at: int) -> torch.Tensor:
        return _loss(model, cache, ds, targets, batch_indices(cfg.seed, at, train_n, cfg.batch_size), weights, cfg.color,
                     later)

    def report(at: int, train: float) -> str:
        row = {"step": at, "train": train, "held_out": held_out()}
        append_row(log, row)
        if best is not None:
            best.offer(at, row["held_out"], model.refiner)
        return f"held_out={row['held_out']:.4f}"

    model.refiner.train()
    t0 = time.perf_counter()
    step = fit_steps(step, cfg.steps, opt, lambda at: cfg.lr * (0.01 + 0.99 * 0.5 * (1 + math.cos(math.pi * at / cfg.steps))),
                     loss_at, cfg.checkpoint_every, report, lambda at: save_part(ckpt, "refiner.", model.refiner, opt, at, record),
                     "refiner", progress)
    model.eval()
    model.to("cpu")
    saved = record
    if best is not None:
        best.restore(model.refiner)
        saved = {**record, "best": {"step": best.step, "held_out": best.loss}}
    save_model(model, out / "model", {**(info or {}), "refiner_fit": saved})
    rows = read_rows(log)
    summary = {"steps": step, "held_out_start": rows[0]["held_out"], "held_out_end": rows[-1]["held_out"],
               "seconds": time.perf_counter() - t0}
    return summary if best is None else {**summary, "best_step": best.step, "held_out_best": best.loss}
