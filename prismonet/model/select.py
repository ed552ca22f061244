"""Over-complete decoding (beyond the paper): run the recurrent encoder for a few extra steps and
keep the ``N`` slots whose composition best explains the input.

The encoder finds objects one after another, and its later steps are its weakest. Every ``N``-subset
of the ``N + extra`` slots is composed by z-buffering (no re-rendering: the per-object renders are
reused) and scored on the input with the unblurred image and depth terms of the training loss; the
best subset is kept, in encoder order. The first ``N`` steps are one candidate, so the kept slots never
score worse than them. On the shipped model this mostly drops a wrong slot for the extra step's
(EVALUATION.md: AP0.5 0.886 -> 0.895 with one extra step); with long refinement afterwards (K = 50) it
does worse than the plain slots, which refinement would have repaired, so it is off by default.
"""

from __future__ import annotations

import itertools

import torch

from prismonet.model.fit_score import fit_score
from prismonet.model.prismonet import ModelOutput, SceneLatents
from prismonet.render import SceneParams, composite


def check_extra_slots(extra: int) -> None:
    """Raise ``ValueError`` unless ``extra`` is a valid number of extra encoder steps (callers check
    up front, before loading data or running anything)."""
    if extra < 0:
        raise ValueError(f"extra slots must be non-negative, got {extra}")


def gather_slots(out: ModelOutput, idx: torch.Tensor) -> ModelOutput:
    """The slots ``idx (B, N)`` (indices into ``out``'s slots, per scene) of ``out``, composed anew."""
    if idx.dim() != 2 or idx.shape[0] != out.obj_depth.shape[0]:
        raise ValueError(f"idx: expected shape (B, N) with B={out.obj_depth.shape[0]}, got {tuple(idx.shape)}")

    def take(t: torch.Tensor | None) -> torch.Tensor | None:
        if t is None:
            return None
        i = idx.view(*idx.shape, *([1] * (t.dim() - 2))).expand(-1, -1, *t.shape[2:])
        return torch.gather(t, 1, i)

    p = out.latents.params
    params = SceneParams(take(p.z_sh), take(p.z_tex), take(p.position), take(p.cos_sin), take(p.scale), take(p.axis), take(p.active))
    depth, mask, color = take(out.obj_depth), take(out.obj_mask), take(out.obj_color)
    comp = composite(depth, mask, color, out.latents.bg_color, out.bg_depth)
    steps = torch.gather(out.encoder_steps(), 1, idx)
    return ModelOutput(SceneLatents(params, out.latents.bg_color), comp, depth, mask, color, out.bg_depth,
                       take(out.obj_soft_mask), slot_steps=steps)


def subset_scores(out: ModelOutput, rgb: torch.Tensor, depth: torch.Tensor | None, num_objects: int,
                  w_image: float = 1.0, w_depth: float = 0.1) -> tuple[torch.Tensor, torch.Tensor]:
    """Scores ``(B, S)`` of all ``S = C(M, num_objects)`` subsets of the ``M`` slots (lower is better),
    and the subsets ``(S, num_objects)``: ``w_image`` x mean squared colour error (summed over
    channels) + ``w_depth`` x mean absolute depth error (the latter only when ``depth`` is given)."""
    M = out.obj_depth.shape[1]
    if not 0 < num_objects <= M:
        raise ValueError(f"num_objects must be in [1, {M}] (the slots decoded), got {num_objects}")
    subsets = torch.tensor(list(itertools.combinations(range(M), num_objects)), dtype=torch.long)
    scores = []
    for sub in subsets:
        c = composite(out.obj_depth[:, sub], out.obj_mask[:, sub], out.obj_color[:, sub], out.latents.bg_color, out.bg_depth)
        scores.append(fit_score(c.image, c.depth, rgb, depth, w_image, w_depth))
    return torch.stack(scores, 1), subsets


@torch.no_grad()
def select_slots(out: ModelOutput, rgb: torch.Tensor, depth: torch.Tensor | None, num_objects: int,
                 w_image: float = 1.0, w_depth: float = 0.1) -> ModelOutput:
    """Keep, per scene, the ``num_objects`` slots of ``out`` whose composition best explains ``rgb``
    ``(B, 3, H, W)`` and ``depth`` ``(B, 1, H, W)`` (or ``None``: colour only). Ties go to the
    earliest subset, so with no extra slots the output is ``out``'s slots unchanged."""
    scores, subsets = subset_scores(out, rgb, depth, num_objects, w_image, w_depth)
    best = scores.argmin(1)  # first minimum on ties
    return gather_slots(out, subsets[best])


def decode_overcomplete(model, batch, num_objects: int | None = None, extra: int = 0, use_depth: bool = True,
                        w_image: float = 1.0, w_depth: float = 0.1, stop=None) -> ModelOutput:
    """``model``'s output on ``batch`` with ``num_objects`` slots (default: the model's), chosen among
    ``num_objects + extra`` encoder steps by ``select_slots`` (against depth too, if ``use_depth``); a model
    with ``refine_passes`` refines the chosen slots, after the choice.
    ``stop``: a ``StopRule`` that ends the encoder early per scene (``prismonet.model.stopping``)."""
    check_extra_slots(extra)
    N = model.cfg.num_slots if num_objects is None else num_objects
    bound = None if stop is None else stop.bind(batch.rgb, batch.depth if use_depth else None)
    out = model(batch.rgb, batch.K, batch.T_world_cam, batch.ground_z, num_slots=N + extra, stop=bound, refine=extra == 0)
    if extra == 0:
        return out
    # the choice is among the encoder's slots; a model's refinement passes then correct the chosen ones
    out = select_slots(out, batch.rgb, batch.depth if use_depth else None, N, w_image, w_depth)
    return model.refine_slots(out, batch.rgb, batch.K, batch.T_world_cam, batch.ground_z)

