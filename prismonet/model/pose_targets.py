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
"""

from __future__ import annotations

import numpy as np
import torch

from prismonet.model.distill import MIN_VISIBLE, VISIBLE


def nearest_turn(yaw: torch.Tensor, true_yaw: torch.Tensor, period: torch.Tensor) -> torch.Tensor:
    """The yaw that the true yaw's shape cannot be told from, nearest to ``yaw``: ``true_yaw + n * period`` for the
    integer ``n`` that brings it closest (``period`` 2 pi: the true yaw itself, up to whole turns); ``yaw`` itself
    where the shape is round (``period`` 0). All ``(N,)``."""
    p = torch.where(period > 0, period, torch.ones_like(period))
    turned = true_yaw + p * torch.round((yaw - true_yaw) / p)
    return torch.where(period > 0, turned, yaw)


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
    from scipy.optimize import linear_sum_assignment

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
        if len(slots) == 0 or len(objects) == 0:
            return slots[:0], objects[:0]
        cost = torch.cdist(targets["position"][i, slots].double(), obj_position[i, objects].double())
        rows, cols = linear_sum_assignment(cost.numpy())
        slot, obj = slots[torch.as_tensor(rows, dtype=torch.long)], objects[torch.as_tensor(cols, dtype=torch.long)]
        shape = obj_shape[i, obj]
        if int(shape.min()) < 0 or int(shape.max()) >= len(periods):
            raise ValueError(f"with_true_poses: scene {i} has shape ids {shape.tolist()}, the yaw periods cover {len(periods)}")
        out["position"][i, slot] = obj_position[i, obj].to(out["position"].dtype)
        out["scale"][i, slot] = obj_scale[i, obj].to(out["scale"].dtype)
        new_yaw = nearest_turn(yaw[i, slot], obj_yaw[i, obj].float(), periods[shape])
        out["cos_sin"][i, slot] = torch.stack([torch.cos(new_yaw), torch.sin(new_yaw)], -1).to(out["cos_sin"].dtype)
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
    from prismonet.evaluation.evaluate import dataset_shapes, shape_periods

    specs, clevr_ids = dataset_shapes(ds)
    periods = shape_periods(ds, specs, clevr_ids)
    if periods is None:
        raise ValueError(f"{ds.path}: its shape library is not here, so the shapes' symmetries (and the true yaws that "
                         "matter) are unknown; import it first (`prismonet shapes import-furniture ...`)")
    truth = {k: torch.from_numpy(np.array(ds.arrays[k][:count])) for k in ("obj_count", "obj_shape", "obj_position", "obj_yaw", "obj_scale")}
    head = {k: v[:count] for k, v in targets.items()}
    return with_true_poses(head, truth["obj_count"].long(), truth["obj_shape"].long(), truth["obj_position"].float(),
                           truth["obj_yaw"].float(), truth["obj_scale"].float(), periods, fill_hidden)
