"""Quality of a shape prior on its training shapes: Chamfer-L1, volumetric IoU, interpolation."""

from __future__ import annotations

import numpy as np

from prismonet.shapes.mesh import EmptyMeshError, extract_mesh
from prismonet.shapes.metrics import (
    CHAMFER_POINTS,
    IOU_RESOLUTION,
    decoder_occupancy,
    grid_points,
    mesh_chamfer_l1,
    mesh_occupancy,
    volumetric_iou,
)

INTERPOLATION_STEPS = (0.25, 0.5, 0.75)


def evaluate_prior(prior, shape_set="clevr", resolution: int = 64, iou_resolution: int = IOU_RESOLUTION,
                   chamfer_points: int = CHAMFER_POINTS, interpolation_pairs: int = 10, progress: bool = True) -> dict:
    """Per-shape Chamfer-L1 (marching cubes at ``resolution``) and IoU, plus an interpolation check.

    Returns a dict with ``per_shape`` rows, means, and ``interpolation_nonempty`` (the share of
    meshes along ``interpolation_pairs`` random latent pairs that are non-empty).
    """
    import trimesh
    from tqdm import tqdm

    from prismonet.shapes.pretrain import load_shape_set

    shapes = load_shape_set(shape_set) if isinstance(shape_set, str) else shape_set
    meshes, names = shapes.meshes, shapes.names
    if len(meshes) != len(prior.latents):
        raise ValueError(f"prior has {len(prior.latents)} latents but shape set {shape_set!r} has {len(meshes)} shapes")
    grid = grid_points(iou_resolution)
    rows = []
    for i, ((v, f), name) in enumerate(tqdm(list(zip(meshes, names)), desc="evaluate", disable=not progress)):
        gt = trimesh.Trimesh(v, f, process=False)
        try:
            rec = extract_mesh(prior.decoder, prior.latents[i], resolution)
            cd = mesh_chamfer_l1(rec, gt, chamfer_points, seed=i)
        except EmptyMeshError:
            cd = float("inf")
        iou = volumetric_iou(mesh_occupancy(v, f, grid), decoder_occupancy(prior.decoder, prior.latents[i], grid))
        rows.append({"shape": name, "chamfer_l1": cd, "iou": iou})
    rng = np.random.default_rng(0)
    nonempty, total = 0, 0
    for _ in range(interpolation_pairs):
        i, j = rng.choice(len(prior.latents), 2, replace=False)
        for t in INTERPOLATION_STEPS:
            z = (1 - t) * prior.latents[i] + t * prior.latents[j]
            total += 1
            try:
                nonempty += len(extract_mesh(prior.decoder, z, 32).faces) > 0
            except EmptyMeshError:
                pass
    return {
        "resolution": resolution,
        "iou_resolution": iou_resolution,
        "per_shape": rows,
        "mean_chamfer_l1": float(np.mean([r["chamfer_l1"] for r in rows])),
        "max_chamfer_l1": float(np.max([r["chamfer_l1"] for r in rows])),
        "mean_iou": float(np.mean([r["iou"] for r in rows])),
        "min_iou": float(np.min([r["iou"] for r in rows])),
        "interpolation_nonempty": nonempty / max(total, 1),
    }
