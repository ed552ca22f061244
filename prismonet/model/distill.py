"""Self-distillation (beyond the paper, still weakly supervised): the encoder learns to output in one
pass what the test-time pose search and colour fit reach.

1. ``fit_targets`` (``prismonet.model.distill_fit``): run the trained model on *training* scenes, then the pose search (against their
   RGB-D) and the colour fit (against their RGB), exactly as ``evaluate --search R --fit-color K``
   does on test scenes. Only the input RGB-D enters; no pose, mask or instance label is read.
   The fitted scale, position, yaw, texture latents and background colour of every slot are the
   targets, and its shape latent when the search tried the prior's shapes (``SearchConfig.shape_nearest``).
   Slots keep their order (slot k is encoder step k), so step k learns step k's fit.
2. ``distill_loss``: a regression of the encoder's decoded slots onto those targets, added to the
   paper's losses with weight ``LossConfig.w_distill`` (``TrainConfig.distill`` names the targets).

Targets are written in chunks of ``CHUNK`` scenes, each atomically (``chunk_NNNNN.safetensors``), so
an interrupted run resumes at the first missing chunk and the files of a finished chunk never change.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import torch

CHUNK = 256
"""Scenes per target file."""

FIELDS = ("scale", "position", "cos_sin", "z_tex", "bg_color")
VISIBLE = "visible"
"""An optional field: ``(K,)`` pixels of the fitted render each slot wins (targets made before it existed
lack it; then every slot is a target)."""
SHAPE = "z_sh"
"""An optional field: ``(K, D_sh)`` fitted shape latents, saved only when the fit could change them (a
search with shape trials); without it the shapes are not distilled."""
MIN_VISIBLE = 25
"""A slot is a target only where the fit shows at least this many of its pixels (the metrics' visibility
rule): a hidden slot's fitted pose is arbitrary, and regressing onto it pulls the encoder off the objects."""


class DistillError(ValueError):
    """Targets that are missing, malformed or made for another model or dataset."""


@dataclass(frozen=True)
class DistillWeights:
    """Weights of the distillation terms inside ``distill_loss`` (each a mean over slots)."""

    position: float = 1.0
    """L1 of world positions (x, y, z summed)."""
    scale: float = 1.0
    """L1 of scales."""
    rotation: float = 0.5
    """1 - cos of the yaw difference."""
    texture: float = 0.1
    """Squared L2 of texture latents."""
    background: float = 1.0
    """L1 of the background colour (RGB summed)."""
    shape: float = 1.0
    """Squared L2 of shape latents (only with targets that have them, ``SHAPE``)."""


class DistillTargets:
    """Targets of scenes ``0 .. count-1`` (``fit_targets``'s folder), looked up by scene index."""

    def __init__(self, path: str | Path, num_slots: int) -> None:
        from prismonet.checkpoint import load_checkpoint

        root = Path(path)
        info_path = root / "targets.json"
        if not info_path.is_file():
            raise DistillError(f"{root}: no distillation targets here (targets.json); make them with `prismonet distill`")
        info = json.loads(info_path.read_text())
        if info.get("num_slots") != num_slots:
            raise DistillError(f"{root}: targets for {info.get('num_slots')} slots, the model has {num_slots}")
        parts: dict[str, list[torch.Tensor]] = {k: [] for k in (*FIELDS, VISIBLE, SHAPE)}
        for i in range(0, info["count"], info["chunk"]):
            f = root / f"chunk_{i // info['chunk']:05d}.safetensors"
            if not f.is_file():
                break  # an unfinished run: use the chunks that are complete
            tensors, _ = load_checkpoint(f)
            for k in FIELDS:
                parts[k].append(tensors[k])
            for k in (VISIBLE, SHAPE):
                if k in tensors:
                    parts[k].append(tensors[k])
        if not parts["scale"]:
            raise DistillError(f"{root}: no finished chunk of targets yet")
        for k in (VISIBLE, SHAPE):  # none, or older chunks without it: every slot a target / shapes not distilled
            if len(parts[k]) != len(parts["scale"]):
                del parts[k]
        self.t = {k: torch.cat(v) for k, v in parts.items()}
        self.count = len(self.t["scale"])
        self.gray = bool(info.get("gray", False))
        """Fitted on the scenes' grey images (``prismonet distill --gray``)."""

    def lookup(self, indices: torch.Tensor) -> tuple[dict[str, torch.Tensor], torch.Tensor]:
        """Targets of scenes ``indices`` (zeros where there are none) and a ``(B,)`` float mask of those that have them."""
        have = indices < self.count
        safe = torch.where(have, indices, torch.zeros_like(indices)).cpu()
        return {k: v[safe].to(indices.device) for k, v in self.t.items()}, have.float()


def distill_terms(params, targets: dict[str, torch.Tensor], w: DistillWeights = DistillWeights()) -> dict[str, torch.Tensor]:
    """The weighted slot terms of ``distill_loss``, each ``(B, K)``: position, scale, rotation, texture, and shape
    when the targets have shape latents."""
    cs = params.cos_sin / params.cos_sin.norm(dim=-1, keepdim=True).clamp_min(1e-6)
    ct = targets["cos_sin"] / targets["cos_sin"].norm(dim=-1, keepdim=True).clamp_min(1e-6)
    terms = {
        "position": w.position * (params.position - targets["position"]).abs().sum(-1),
        "scale": w.scale * (params.scale - targets["scale"]).abs(),
        "rotation": w.rotation * (1 - (cs * ct).sum(-1)),
        "texture": w.texture * ((params.z_tex - targets["z_tex"]) ** 2).sum(-1),
    }
    if SHAPE in targets:
        terms["shape"] = w.shape * ((params.z_sh - targets[SHAPE]) ** 2).sum(-1)
    return terms


def seen_slots(targets: dict[str, torch.Tensor], like: torch.Tensor) -> torch.Tensor:
    """``(B, K)`` float: 1 for the slots that are targets (those the fit shows, with ``targets["visible"]``; else all)."""
    if VISIBLE in targets:
        return (targets[VISIBLE] >= MIN_VISIBLE).to(like.dtype)
    return torch.ones_like(like)


def shown_mean(per_slot: torch.Tensor, targets: dict[str, torch.Tensor], mask: torch.Tensor) -> torch.Tensor:
    """``()``: ``per_slot (B, K)`` averaged over each scene's slots that the fit shows (``seen_slots``; 0 if none), then
    over the scenes that have targets (``mask``; 0 when none has)."""
    shown = seen_slots(targets, per_slot)
    per_scene = (per_slot * shown).sum(1) / shown.sum(1).clamp_min(1.0)
    return (per_scene * mask).sum() / mask.sum().clamp_min(1.0)


def keep_loss(keep_logit: torch.Tensor, targets: dict[str, torch.Tensor], mask: torch.Tensor) -> torch.Tensor:
    """``()``: the binary cross-entropy of ``keep_logit (B, K)`` (a refiner's keep output) against whether the fit shows
    each slot (``seen_slots``), the mean over each scene's slots, hidden ones included, then over the scenes that have
    targets (``mask``). Needs targets with ``visible``."""
    if VISIBLE not in targets:
        raise DistillError("these targets do not say which slots the fit shows; a keep term has nothing to learn from")
    shown = seen_slots(targets, keep_logit)
    per_scene = torch.nn.functional.binary_cross_entropy_with_logits(keep_logit, shown, reduction="none").mean(1)
    return (per_scene * mask).sum() / mask.sum().clamp_min(1.0)


def distill_loss(params, bg_color: torch.Tensor, targets: dict[str, torch.Tensor], mask: torch.Tensor,
                 w: DistillWeights = DistillWeights()) -> torch.Tensor:
    """``()``: the weighted regression of the decoded slots onto their targets, mean over the scenes
    that have targets (``mask``); 0 when none has. With ``targets["visible"]``, each scene's slot terms
    are the mean over its slots that the fit shows (``MIN_VISIBLE`` pixels or more), 0 if it shows none."""
    per_slot = sum(distill_terms(params, targets, w).values())  # (B, K)
    seen = seen_slots(targets, per_slot)
    slots = (per_slot * seen).sum(1) / seen.sum(1).clamp_min(1.0)
    per_scene = slots + w.background * (bg_color - targets["bg_color"]).abs().sum(-1)
    return (per_scene * mask).sum() / mask.sum().clamp_min(1.0)
