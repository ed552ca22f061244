"""Editing a latent scene: move, swap, remove or add objects, swap shape or texture latents.

Every edit returns a new ``LatentScene`` and leaves its input untouched. The paper's intersection
loss L_int (Eq. 12) scores a scene: for each pair of objects, the mean over points evenly spaced
between their centres of ``max(-(phi_i + phi_j), 0)``, with ``phi`` the world-unit SDFs. It is zero
when the objects keep apart and positive when they overlap. ``checked`` rejects an edit whose
objects intersect.
"""

from __future__ import annotations

import math
from dataclasses import replace

import torch

from prismonet.scene.latent_scene import LatentScene, LatentSceneError

INTERSECTION_POINTS = 16
"""Sample points per pair for L_int (the paper's K)."""
INTERSECTION_TOL = 1e-3
"""L_int above this (world units) counts as an intersection: the learned SDFs are not exact, so
touching objects may score a few 1e-4."""


class EditRejected(LatentSceneError):
    """An edit whose objects would intersect (L_int above the tolerance)."""


def _index(scene: LatentScene, k: int) -> int:
    if not 0 <= k < scene.num_objects:
        raise LatentSceneError(f"object {k}: the scene has objects 0..{scene.num_objects - 1}")
    return k


def _set(t: torch.Tensor, k: int, value) -> torch.Tensor:
    t = t.clone()
    t[k] = torch.as_tensor(value, dtype=t.dtype)
    return t


def move(scene: LatentScene, k: int, position=None, delta=None, yaw_deg: float | None = None, scale: float | None = None) -> LatentScene:
    """Object ``k`` placed at ``position`` (or shifted by ``delta``), turned to ``yaw_deg``, resized."""
    k = _index(scene, k)
    if position is not None and delta is not None:
        raise LatentSceneError("move: give position or delta, not both")
    pos = scene.position
    if position is not None:
        pos = _set(pos, k, position)
    if delta is not None:
        pos = _set(pos, k, pos[k] + torch.as_tensor(delta, dtype=pos.dtype))
    cs = scene.cos_sin
    if yaw_deg is not None:
        a = math.radians(yaw_deg)
        cs = _set(cs, k, [math.cos(a), math.sin(a)])
    sc = scene.scale
    if scale is not None:
        if not scale > 0:
            raise LatentSceneError(f"move: scale must be positive, got {scale}")
        sc = _set(sc, k, scale)
    return replace(scene, position=pos, cos_sin=cs, scale=sc)


def swap_places(scene: LatentScene, i: int, j: int) -> LatentScene:
    """Objects ``i`` and ``j`` trade positions (each keeps its shape, texture, yaw and scale)."""
    i, j = _index(scene, i), _index(scene, j)
    perm = list(range(scene.num_objects))
    perm[i], perm[j] = j, i
    return replace(scene, position=scene.position[perm])


def swap_latents(scene: LatentScene, i: int, j: int, which: str = "shape") -> LatentScene:
    """Objects ``i`` and ``j`` trade their ``"shape"`` latents, ``"texture"`` latents, or ``"both"``."""
    if which not in ("shape", "texture", "both"):
        raise LatentSceneError(f"swap_latents: which must be shape, texture or both, got {which!r}")
    i, j = _index(scene, i), _index(scene, j)
    perm = list(range(scene.num_objects))
    perm[i], perm[j] = j, i
    z_sh = scene.z_sh[perm] if which in ("shape", "both") else scene.z_sh
    z_tex = scene.z_tex[perm] if which in ("texture", "both") else scene.z_tex
    return replace(scene, z_sh=z_sh, z_tex=z_tex)


def remove(scene: LatentScene, k: int) -> LatentScene:
    """The scene without object ``k``."""
    k = _index(scene, k)
    if scene.num_objects == 1:
        raise LatentSceneError("remove: cannot remove the only object of a scene")
    return scene.select([i for i in range(scene.num_objects) if i != k])


def add(scene: LatentScene, source: LatentScene, k: int, position=None) -> LatentScene:
    """The scene plus object ``k`` of ``source`` (optionally placed at ``position``)."""
    k = _index(source, k)
    if source.z_sh.shape[1] != scene.z_sh.shape[1] or source.z_tex.shape[1] != scene.z_tex.shape[1]:
        raise LatentSceneError("add: the two scenes have different latent sizes")
    if source.prior_fingerprint and scene.prior_fingerprint and source.prior_fingerprint != scene.prior_fingerprint:
        raise LatentSceneError("add: the two scenes belong to different shape priors")
    obj = source.select([k])
    if position is not None:
        obj = move(obj, 0, position=position)
    cat = lambda name: torch.cat([getattr(scene, name), getattr(obj, name)])
    return replace(scene, z_sh=cat("z_sh"), z_tex=cat("z_tex"), position=cat("position"), cos_sin=cat("cos_sin"), scale=cat("scale"))


@torch.no_grad()
def intersection_pairs(model, scene: LatentScene, points: int = INTERSECTION_POINTS) -> dict[tuple[int, int], float]:
    """L_int of every pair ``(i, j)``, ``j < i``."""
    from prismonet.model.losses import intersection_loss

    scene.check_model(model)
    out = {}
    for i in range(scene.num_objects):
        for j in range(i):
            out[(i, j)] = float(intersection_loss(model, scene.select([j, i]).params(), points)[0])
    return out


def intersection_score(model, scene: LatentScene, points: int = INTERSECTION_POINTS) -> float:
    """The paper's L_int of the whole scene (sum over pairs)."""
    return float(sum(intersection_pairs(model, scene, points).values()))


def checked(model, scene: LatentScene, tol: float = INTERSECTION_TOL) -> LatentScene:
    """``scene`` if no two objects intersect, else ``EditRejected`` naming the pairs."""
    bad = {p: v for p, v in intersection_pairs(model, scene).items() if v > tol}
    if bad:
        pairs = ", ".join(f"{i}-{j} (L_int {v:.4f})" for (i, j), v in sorted(bad.items()))
        raise EditRejected(f"objects intersect: {pairs}; tolerance {tol}")
    return scene
