"""Self-distillation targets with the true poses (the + 3D pose variant, supervised).

The search's fitted poses (``prismonet distill``) are near the truth but not on it: on 1,024 tableware training
scenes the fitted slots sit a median 0.07 (90 %: 0.21) from the true object centres, for objects of scale about 0.5.
Where the training data may give poses, as the paper's "+ 3D pose" rows do (L_pose), a refiner can be fitted to the
true poses instead. ``with_true_poses`` matches each slot the fit shows to a true object, as L_pose does (Hungarian
on position distance, every true object of the scene a candidate: no mask is read), and replaces that slot's position
and scale by the object's, and its yaw by the object's up to the shape's symmetry. What the pose does not say stays
the search's: the shape and texture latents, which slots are shown (the keep target), the background colour, and the
yaw of a round shape (``prismonet.shapes.symmetry.ANY``; the texture is drawn in the object frame, so only the fit's
yaw matches its colours).

Those shapes and textures were fitted at the search's poses, though: a chair's search pairs a wrong yaw with a shape
code that makes up for it, and at the true yaw that code draws another chair. ``start_at_truth`` therefore moves the
search's *start* instead (``prismonet distill --true-poses``): the encoder's slots are put on the true poses first
(``posed_at_truth``), and the search, its pose trials off, fits only the shapes and the colours there. On tableware
and chairs training scenes this covers 99 % and 97 % of the visible objects with a target slot (the search: 92 % and
47 %) and picks each object's own shape code 84 % and 67 % of the time (37 % and 6 %; EVALUATION.md, session 64).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import torch

from prismonet.model.distill import MIN_VISIBLE, VISIBLE
from prismonet.model.prismonet import ModelOutput
from prismonet.render import SceneParams


def nearest_turn(yaw: torch.Tensor, true_yaw: torch.Tensor, period: torch.Tensor) -> torch.Tensor:
    """The yaw that the true yaw's shape cannot be told from, nearest to ``yaw``: ``true_yaw + n * period`` for the
    integer ``n`` that brings it closest (``period`` 2 pi: the true yaw itself, up to whole turns); ``yaw`` itself
    where the shape is round (``period`` 0). All ``(N,)``."""
    p = torch.where(period > 0, period, torch.ones_like(period))
    turned = true_yaw + p * torch.round((yaw - true_yaw) / p)
    return torch.where(period > 0, turned, yaw)


def match_slots(slot_position: torch.Tensor, obj_position: torch.Tensor, slots: torch.Tensor,
                objects: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """One scene's pairs ``(slot, object)`` among ``slots`` and ``objects`` (index tensors into ``slot_position (K, 3)``
    and ``obj_position (M, 3)``), as L_pose pairs them: Hungarian on position distance. ``min(len(slots),
    len(objects))`` pairs."""
    from scipy.optimize import linear_sum_assignment

    if len(slots) == 0 or len(objects) == 0:
        return slots[:0], objects[:0]
    cost = torch.cdist(slot_position[slots].double(), obj_position[objects].double())
    rows, cols = linear_sum_assignment(cost.numpy())
    return slots[torch.as_tensor(rows, dtype=torch.long)], objects[torch.as_tensor(cols, dtype=torch.long)]


def true_cos_sin(yaw: torch.Tensor, true_yaw: torch.Tensor, shape: torch.Tensor, periods: torch.Tensor,
                 where: str) -> torch.Tensor:
    """``(N, 2)`` cos and sin of the true yaws as a slot should take them: ``nearest_turn`` to the slot's ``yaw`` by
    each object's shape's period (``periods`` indexed by ``shape`` ids; ``where`` names the caller in the error)."""
    if int(shape.min()) < 0 or int(shape.max()) >= len(periods):
        raise ValueError(f"{where} has shape ids {shape.tolist()}, the yaw periods cover {len(periods)}")
    new_yaw = nearest_turn(yaw.float(), true_yaw.float(), periods[shape])
    return torch.stack([torch.cos(new_yaw), torch.sin(new_yaw)], -1)


def with_true_poses(targets: dict[str, torch.Tensor], obj_count: torch.Tensor, obj_shape: torch.Tensor,
                    obj_position: torch.Tensor, obj_yaw: torch.Tensor, obj_scale: torch.Tensor,
                    yaw_periods: list[float], fill_hidden: bool = False) -> tuple[dict[str, torch.Tensor], dict[str, int]]:
    """A copy of distillation ``targets`` (``DistillTargets.t``; scenes first, ``(N, K, ...)``) with the true poses of
    the scenes' objects (``SceneBatch`` fields of the same N scenes) on the slots the fit shows.

    ``fill_hidden``: the true objects no shown slot was matched to (the search left them uncovered) go to the slots the
    fit hides, matched the same way: such a slot becomes a target (shown, so the keep output learns to keep it) with the
    object's pose; its shape and texture targets stay the fit's, which did not move a hidden slot's. Measured on
    tableware + 3D pose (EVALUATION.md, session 63) it costs precision (val AP0.5 0.914 -> 0.896 at 3,000 steps), so it is off
    by default.

    Returns the new targets and counts: ``slots`` shown, ``matched`` (replaced), ``objects`` (true objects in all),
    ``filled`` (hidden slots given an object), ``unmatched_objects`` (true objects left without a slot)."""
    if VISIBLE not in targets:
        raise ValueError("with_true_poses: these targets do not say which slots the fit shows; make them again with `prismonet distill`")
    n, _ = targets["scale"].shape
    if len(obj_count) != n:
        raise ValueError(f"with_true_poses: targets for {n} scenes, true poses for {len(obj_count)}")
    periods = torch.tensor(yaw_periods, dtype=torch.float32)
    out = {k: v.clone() for k, v in targets.items()}
    shown_all = targets[VISIBLE] >= MIN_VISIBLE
    yaw = torch.atan2(targets["cos_sin"][..., 1], targets["cos_sin"][..., 0])
    stats = {"slots": int(shown_all.sum()), "matched": 0, "objects": int(obj_count.sum()), "filled": 0, "unmatched_objects": 0}

    def match(i: int, slots: torch.Tensor, objects: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Put the true poses of ``objects`` on ``slots`` of scene ``i`` (Hungarian on position); the pairs made."""
        slot, obj = match_slots(targets["position"][i], obj_position[i], slots, objects)
        if len(slot):
            cos_sin = true_cos_sin(yaw[i, slot], obj_yaw[i, obj], obj_shape[i, obj], periods, f"with_true_poses: scene {i}")
            out["position"][i, slot] = obj_position[i, obj].to(out["position"].dtype)
            out["scale"][i, slot] = obj_scale[i, obj].to(out["scale"].dtype)
            out["cos_sin"][i, slot] = cos_sin.to(out["cos_sin"].dtype)
        return slot, obj

    for i in range(n):
        objects = torch.arange(int(obj_count[i]))
        slot, obj = match(i, torch.nonzero(shown_all[i]).flatten(), objects)
        stats["matched"] += len(slot)
        left = objects[~torch.isin(objects, obj)]
        if fill_hidden:
            slot, obj = match(i, torch.nonzero(~shown_all[i]).flatten(), left)
            out[VISIBLE][i, slot] = float(MIN_VISIBLE)
            stats["filled"] += len(slot)
            left = left[~torch.isin(left, obj)]
        stats["unmatched_objects"] += len(left)
    return out, stats


def true_poses_for(targets: dict[str, torch.Tensor], ds, count: int, fill_hidden: bool = False) -> tuple[dict[str, torch.Tensor], dict[str, int]]:
    """``with_true_poses`` for the first ``count`` scenes of dataset ``ds`` (the split the targets were made on), the yaw
    periods found from its shape library's meshes (``prismonet.evaluation.evaluate.shape_periods``)."""
    periods = yaw_periods_of(ds)
    truth = {k: torch.from_numpy(np.array(ds.arrays[k][:count])) for k in ("obj_count", "obj_shape", "obj_position", "obj_yaw", "obj_scale")}
    head = {k: v[:count] for k, v in targets.items()}
    return with_true_poses(head, truth["obj_count"].long(), truth["obj_shape"].long(), truth["obj_position"].float(),
                           truth["obj_yaw"].float(), truth["obj_scale"].float(), periods, fill_hidden)


def yaw_periods_of(ds) -> list[float]:
    """Each shape's period of symmetry about z, by dataset ``ds``'s ``obj_shape`` ids (its shape library's meshes,
    ``prismonet.evaluation.evaluate.shape_periods``); refused in one line when the library is not here."""
    from prismonet.evaluation.evaluate import dataset_shapes, shape_periods

    specs, clevr_ids = dataset_shapes(ds)
    periods = shape_periods(ds, specs, clevr_ids)
    if periods is None:
        raise ValueError(f"{ds.path}: its shape library is not here, so the shapes' symmetries (and the true yaws that "
                         "matter) are unknown; import it first (`prismonet shapes import-furniture ...`)")
    return periods


def posed_at_truth(params: SceneParams, batch, yaw_periods: list[float]) -> tuple[SceneParams, dict[str, int]]:
    """A copy of slots ``params`` with each true object of ``batch`` (a ``SceneBatch``: its poses are read, nothing
    else) on the slot nearest it, as L_pose pairs them (Hungarian on position, every active slot a candidate): that
    slot takes the object's position and scale, and its yaw up to the shape's symmetry (``true_cos_sin``: a round
    shape keeps the slot's yaw). The slots no object takes are made inactive, so they render nothing. Shape and
    texture latents stay the slots' own.

    Where the + 3D pose variant may read poses, the test-time search can then start at the truth and fit only what the
    pose does not say (shape trials, colours): ``prismonet distill --true-poses``. Returns the new slots and counts:
    ``objects``, ``matched`` and ``unmatched_objects`` (more objects than slots)."""
    periods = torch.tensor(yaw_periods, dtype=torch.float32)
    B, K = params.scale.shape
    active = torch.ones(B, K, dtype=torch.bool) if params.active is None else params.active.cpu()
    position, scale, cos_sin = params.position.clone(), params.scale.clone(), params.cos_sin.clone()
    yaw = torch.atan2(cos_sin[..., 1], cos_sin[..., 0])
    taken = torch.zeros(B, K, dtype=torch.bool)
    count = batch.obj_count.long()
    for i in range(B):
        objects = torch.arange(int(count[i]))
        slot, obj = match_slots(params.position[i].detach().cpu(), batch.obj_position[i], torch.nonzero(active[i]).flatten(),
                                objects)
        if len(slot):
            cs = true_cos_sin(yaw[i, slot].cpu(), batch.obj_yaw[i, obj], batch.obj_shape[i, obj].long(), periods,
                              f"posed_at_truth: scene {i}")
            position[i, slot] = batch.obj_position[i, obj].to(position)
            scale[i, slot] = batch.obj_scale[i, obj].to(scale)
            cos_sin[i, slot] = cs.to(cos_sin)
            taken[i, slot] = True
    matched = int(taken.sum())
    new = SceneParams(params.z_sh, params.z_tex, position, cos_sin, scale, params.axis, taken.to(params.scale.device))
    return new, {"objects": int(count.sum()), "matched": matched, "unmatched_objects": int(count.sum()) - matched}


def start_at_truth(model, out: ModelOutput, batch, yaw_periods: list[float]) -> ModelOutput:
    """``out`` (the model's decoding of ``batch``) with its slots ``posed_at_truth`` and rendered again: where the
    test-time steps start when the poses are given (``infer(..., start=...)``)."""
    from prismonet.model.refine import render_latents

    params, _ = posed_at_truth(out.latents.params, batch, yaw_periods)
    H, W = batch.rgb.shape[-2:]
    with torch.no_grad():
        new = render_latents(model, params, out.latents.bg_color, batch.K, batch.T_world_cam, batch.ground_z, H, W)
    return replace(new, slot_steps=out.slot_steps)
