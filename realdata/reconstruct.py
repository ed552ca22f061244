"""Reconstruct real photos: prepare them, run a trained model, and write per photo a figure, the
latent scene, a mesh of the objects found on their ground, and the object count.

The camera: with a calibration that has a ground pose (``prismonet calibrate ground``), the photo's
own camera and table plane. Without one, the photo is cropped and resized to the model's input
size and taken to be seen by the model's training camera, as the paper did with its real photos.
An object is "found" when at least ``min_pixels`` pixels of it are visible in the composed render
(the evaluation's 25-pixel rule). ``inference`` gives the test-time steps after the encoder
(``prismonet.model.inference``: extra slots, pose search, refinement, colour fit), each run against
the photo's colour alone (a photo has no depth); the summary records the render's PSNR against the
prepared photo after each step that ran.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch

from prismonet.assets import PHOTO_NAME, model_name
from prismonet.files import write_atomic
from realdata.color import HIGHLIGHT_PERCENTILE

MIN_PIXELS = 25
"""Visible pixels for a slot to count as a found object (the paper's 25-pixel rule)."""
BATCH = 16
"""Prepared views (photos or tiles) decoded together."""


def found_objects(instance: torch.Tensor, num_slots: int, min_pixels: int = MIN_PIXELS) -> list[int]:
    """Slots with at least ``min_pixels`` visible pixels in an instance image ``(H, W)`` (1-based)."""
    counts = torch.bincount(instance.reshape(-1), minlength=num_slots + 1)[1:]
    return [k for k in range(num_slots) if int(counts[k]) >= min_pixels]


def reconstruct_photos(photos: list[str | Path], out: str | Path, model: str | Path = PHOTO_NAME,
                       calibration: str | Path | None = None,
                       box: tuple[int, int, int, int] | None = None, normalize: str = "auto", gain=None,
                       objects: int | None = None, min_pixels: int = MIN_PIXELS, mesh_format: str = "ply",
                       resolution: int = 40, inference=None, progress: bool = True,
                       metres_per_unit: float | None = None, elevation: float | dict[str, float] | None = None,
                       elevation_hints: dict[str, float] | None = None, tiling=None, meshes: bool = True,
                       highlights: float | None = HIGHLIGHT_PERCENTILE, gray_tint: str = "off", gray_inference=None,
                       prepared_dir: str = "prepared") -> list[dict]:
    """Run the whole real-photo path; returns one record per photo (also in ``out/summary.json``), each with its
    ``detections``: the found objects' boxes in photo pixels and their scores (visible pixels).

    The prepared views (photos, or tiles) are decoded ``BATCH`` at a time. ``meshes``: write each view's mesh of
    the objects found (``real evaluate`` does not).

    ``tiling`` (``realdata.tiles.TileConfig``, uncalibrated photos): each photo is read as overlapping tiles
    (``tiling.tiles`` along the table region's shorter side), every tile decoded as its own photo (its figure, latent
    scene and mesh under ``out/tiles/``), and the tiles' detections merged; the photo's record lists its tiles.

    ``elevation``: degrees, for all photos or ``{photo stem: degrees}``: an uncalibrated photo is seen by the
    model's training camera moved to that elevation about the table point it looks at (``orbit_elevation``),
    e.g. about 80 for a photo taken from above. Only for models that take the camera as an input
    (``pose_frame = "camera"``); the others know one camera. ``elevation_hints`` (``{photo stem: degrees}``,
    e.g. the labels' ``elevation_deg``): used as ``elevation`` when that is not given and the model takes
    the camera as an input, ignored otherwise.

    ``gray_tint`` (``realdata.gray_tint``): a hue for greyscale photos. ``gray_inference``: the ``InferenceConfig`` for the
    views that tint changed (None: ``inference`` for every view), e.g. no test-time steps for greyscale photos while colour
    ones take them (EVALUATION.md, session 85); each group is decoded in batches of its own. ``prepared_dir``: the folder
    under ``out`` for the prepared views (a reading that reads some photos again in tiles or zoomed out keeps each
    group's views in a folder of its own)."""
    if tiling is not None and tiling.reads_whole_first:
        return _tiled_where_small(photos, out, tiling, model=model, calibration=calibration, box=box, normalize=normalize, gain=gain,
                                  objects=objects, min_pixels=min_pixels, mesh_format=mesh_format, resolution=resolution,
                                  inference=inference, progress=progress, metres_per_unit=metres_per_unit, elevation=elevation,
                                  elevation_hints=elevation_hints, meshes=meshes, highlights=highlights,
                                  gray_tint=gray_tint, gray_inference=gray_inference)
    from tqdm import tqdm

    from prismonet.data.dataset import SceneDataset
    from prismonet.evaluation.metrics import image_metrics
    from prismonet.geometry.camera import orbit_elevation
    from prismonet.model.inference import InferenceConfig, infer
    from prismonet.model.io import load_model, prior_fingerprint, training_camera, training_loss_config
    from realdata.pipeline import prepare_photos

    cfg = (inference or InferenceConfig()).without_depth()  # a photo has no depth
    gray_cfg = None if gray_inference is None else gray_inference.without_depth()
    out = Path(out)
    net, info = load_model(model, num_slots=objects)
    prepared = out / prepared_dir
    train_cam, train_ground = training_camera(net, info)
    own = net.cfg.pose_frame == "camera"  # a camera-frame model takes the calibrated photo camera as it is
    asked = elevation  # given by the user, not a label's hint: say so when a calibrated camera overrides it
    if elevation is None and own:
        elevation = elevation_hints
    if elevation is not None and not own:
        raise ValueError("an elevation needs a model that takes the camera as an input (pose_frame camera, e.g. a "
                         "tabletop model); this one was trained from one camera")
    if (prepared / "dataset.json").is_file():  # an earlier run's prepared views would be read with these
        import shutil

        shutil.rmtree(prepared)
    recs = prepare_photos(photos, prepared, net.cfg.image_size, calibration, box, normalize, gain,
                          view=(train_cam, train_ground), metres_per_unit=metres_per_unit, own_camera=own,
                          tiling=tiling, highlights=highlights, gray_tint=gray_tint)
    tiles = 1 if tiling is None else tiling.tiles
    ds = SceneDataset(prepared)
    by_name = {r["name"]: r for r in recs}
    per_view = out / "tiles" if tiles > 1 else out
    per_view.mkdir(parents=True, exist_ok=True)
    fp = prior_fingerprint(net.prior)
    loss_cfg = training_loss_config(info)
    by_index, shown = {}, {}  # shown: each photo as uint8, loaded once for all its views' figures
    bar = tqdm(total=len(ds), desc="reconstruct", unit="photo" if tiles <= 1 else "tile", disable=not progress)
    tinted = [gray_cfg is not None and "gray_tint" in by_name[name] for name in ds.names]
    groups = [(cfg, [i for i in range(len(ds)) if not tinted[i]]), (gray_cfg, [i for i in range(len(ds)) if tinted[i]])]
    for view_cfg, rows in ((c, idx[s : s + BATCH]) for c, idx in groups for s in range(0, len(idx), BATCH)):
        b = ds.batch(rows)  # seen by the training camera: rectified to it, or assumed (as the paper's real photos)
        recs_b, elevs = [by_name[ds.names[i]] for i in rows], []
        for j, rec in enumerate(recs_b):
            elev = _for_photo(elevation, Path(rec["photo"]).stem)
            elevs.append(elev)
            if not rec.get("own_camera", False):
                b.K[j] = train_cam.K
                b.T_world_cam[j] = train_cam.T_world_cam if elev is None else orbit_elevation(train_cam.T_world_cam, train_ground, elev)
        b.ground_z[:] = train_ground
        psnr = [{} for _ in rows]

        def score(step, o, b=b, psnr=psnr):
            for j in range(len(psnr)):
                psnr[j][step] = image_metrics(o.composite.image[j : j + 1].numpy(), b.rgb[j : j + 1].numpy())["PSNR"]

        o = infer(net, b, view_cfg, loss_cfg, on_step=score)
        for j, (i, rec, elev) in enumerate(zip(rows, recs_b, elevs)):
            by_index[i] = _view_record(net, o, b, j, ds.names[i], rec, _photo_u8(rec["photo"], shown), elev, psnr[j], per_view, fp,
                                       view_cfg, min_pixels, mesh_format, resolution if meshes else None, asked)
        bar.update(len(rows))
    bar.close()
    results = [by_index[i] for i in range(len(ds))]
    if tiles > 1:
        results = [_merged(photo, _photo_u8(photo, shown), [r for r in results if r["photo"] == photo], out, net,
                           resolution if meshes else None, mesh_format) for photo in dict.fromkeys(r["photo"] for r in results)]
    results = [{**r, "model": model_name(model)} for r in results]  # which model read it, in every record
    write_atomic(out / "summary.json", json.dumps(results, indent=1))
    return results


def _photo_u8(path: str, cache: dict) -> np.ndarray:
    """The photo at ``path`` as ``(H, W, 3)`` uint8 RGB for figures, loaded once per ``cache``."""
    if path not in cache:
        from realdata.io import load_photo

        cache[path] = (np.clip(load_photo(path), 0, 1) * 255).round().astype(np.uint8)
    return cache[path]


def _view_record(net, o, b, j, name, rec, photo, elev, psnr, per_view, fp, cfg, min_pixels, mesh_format, resolution, asked) -> dict:
    """Write one prepared view's outputs (row ``j`` of the batch ``b`` and its output ``o``; ``photo`` the uint8 photo
    it was read from): figure, latent scene, instance image and (with a ``resolution``) the mesh of the objects found;
    return its record."""
    from prismonet.files import write_image
    from prismonet.scene import LatentScene
    from prismonet.scene.export import scene_mesh, write_mesh
    from prismonet.viz.decomposition import decomposition_figure

    stem = Path(rec["photo"]).stem
    own_cam = rec.get("own_camera", False)
    warnings = list(rec.get("warnings", []))
    if own_cam and _for_photo(asked, stem) is not None:
        warnings.append(f"elevation {_for_photo(asked, stem):g} deg ignored: this photo's calibrated camera is used as it is")
    keep = found_objects(o.composite.instance[j], o.obj_depth.shape[1], min_pixels)
    title = f"{Path(rec['photo']).name}: {len(keep)} objects found (>= {min_pixels} px), PSNR " + " -> ".join(f"{v:.1f}" for v in psnr.values()) + " dB"
    fig = decomposition_figure(b.rgb, o, j, per_view / f"{name}.png", photo=photo,
                               photo_outline=rec.get("outline"), title=title, min_pixels=min_pixels)
    p = o.latents.params
    scene_slots = list(range(p.z_sh.shape[1])) if p.active is None else torch.nonzero(p.active[j]).flatten().tolist()
    scene_path = None  # a scene file holds at least one object (LatentScene.load): none where every slot was dropped
    if scene_slots:
        scene_path = LatentScene.from_output(o, b, j, fp, slots=scene_slots).save(per_view / f"{name}.json")
    instance = o.composite.instance[j].numpy().astype(np.uint8)
    write_image(per_view / f"{name}_instance.png", instance)
    mesh_path = None
    if keep and resolution is not None:
        mesh_path = write_mesh(scene_mesh(net, LatentScene.from_output(o, b, j, fp, slots=keep), resolution), per_view / f"{name}.{mesh_format}")
    finite = all(bool(torch.isfinite(t[j]).all()) for t in (o.composite.image, o.composite.depth, o.latents.bg_color,
                                                           o.latents.params.position, o.latents.params.z_sh))
    return {"photo": rec["photo"], "objects_found": len(keep), "found_slots": keep, "scene_slots": scene_slots,
            "objects": _objects(o, j, keep, rec.get("world")),
            "detections": view_detections(instance, rec["outline"], min_pixels, tuple(rec.get("inner_edges", (False,) * 4)),
                                          rec.get("zoom_out", 1.0) ** 2),
            "outlines": [rec["outline"]],
            "figure": str(fig), "scene": None if scene_path is None else str(scene_path), "instance": str(per_view / f"{name}_instance.png"),
            "mesh": None if mesh_path is None else str(mesh_path),
            "camera": "the photo's own calibrated camera" if own_cam else
            "rectified to the training view (calibrated ground pose)" if rec.get("rectified")
            else "model's training camera (assumed)" if elev is None
            else f"model's training camera moved to {elev:g} deg elevation (assumed)", "warnings": warnings,
            "finite": finite, "psnr": psnr, "inference": cfg.record(), "prepare": rec}


def _tiled_where_small(photos, out, tiling, **kw) -> list[dict]:
    """``TileConfig.below_px``, ``target_px`` or ``zoom_out``: read every photo whole first (into ``out/whole``), then in
    tiles those whose objects are small (or none found, or read poorly), as many as ``TileConfig.tiles_after`` asks, and
    zoomed out those whose objects are large; each record says which reading it is (``reading``: whole, tiles or zoomed
    out; ``tiles_across``, under 1 when zoomed out) and the whole reading's median object size and PSNR."""
    from dataclasses import replace

    out = Path(out)
    whole = reconstruct_photos(photos, out / "whole", tiling=None, **kw)
    size = {r["photo"]: float(np.median(r["detections"]["scores"])) if r["detections"]["scores"] else 0.0 for r in whole}
    psnr = {r["photo"]: (r.get("psnr") or {}).get("encoder") for r in whole}
    count = {r["photo"]: tiling.tiles_after(size[r["photo"]], len(r["detections"]["scores"]), psnr[r["photo"]]) for r in whole}
    tiled = {}
    for n in sorted({c for c in count.values() if c != 1}):
        group = [str(p) for p in photos if count[str(p)] == n]
        plain = replace(tiling, tiles=n, below_px=None, target_px=None, below_psnr=None, fine_tiles=None, fine_below_px=None,
                        zoom_out=None, zoom_out_above_px=None)
        folder = f"prepared_tiles{n:g}" if n > 1 else f"prepared_zoom{1 / n:g}"
        tiled.update({r["photo"]: r for r in reconstruct_photos(group, out, tiling=plain, prepared_dir=folder, **kw)})
    results = []
    for r in whole:
        rec, n = tiled.get(r["photo"], r), count[r["photo"]]
        reading = "whole" if r["photo"] not in tiled else "tiles" if n > 1 else "zoomed out"
        results.append({**rec, "reading": reading, "tiles_across": n, "whole_median_px": size[r["photo"]], "whole_psnr": psnr[r["photo"]]})
    write_atomic(out / "summary.json", json.dumps(results, indent=1))
    return results


RENDER_SIDE = 192
"""Pixels across the view when an assembled scene is rendered for the tiled photo's figure."""


def _render_over_photo(net, scene, view, photo_shape) -> np.ndarray:
    """``(h, w, 3)`` uint8: the scene rendered from its camera over the square ``view`` of the photo, mapped onto the
    photo's pixels (outside the view: white)."""
    import cv2

    with torch.no_grad():
        comp = scene.render(net, scene.camera.resized(RENDER_SIDE, RENDER_SIDE))[0]
    img = (comp.image[0].clamp(0, 1).permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)
    vx, vy, vs, _ = view
    f = RENDER_SIDE / vs  # photo pixel x -> render pixel (x + 0.5 - vx) f - 0.5
    A = np.float32([[f, 0, (0.5 - vx) * f - 0.5], [0, f, (0.5 - vy) * f - 0.5]])
    h, w = photo_shape
    return cv2.warpAffine(img, A, (w, h), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP, borderValue=(255, 255, 255))


def view_detections(instance: np.ndarray, outline, min_pixels: int = MIN_PIXELS, inner=(False, False, False, False),
                    score_scale: float = 1.0) -> dict:
    """The found objects of one view (``instance (S, S)``, 0 = background): their boxes in photo pixels (every mask
    pixel's corners through the view-to-photo map of ``outline``), scores (visible pixels, times ``score_scale``: a
    zoomed-out view's ``zoom ** 2``, so that its objects score in the whole view's pixels, as a whole reading of the
    photo would), slots, and whether each is cut: its mask touches one of the view's ``inner`` edges (left, top, right,
    bottom; a tile's, ``realdata.tiles``)."""
    from realdata.boxes import mask_box, view_to_photo
    from realdata.tiles import mask_cut

    H = view_to_photo(outline, instance.shape[0])
    ids, counts = np.unique(instance[instance > 0], return_counts=True)
    found = [(int(k), int(c)) for k, c in zip(ids, counts) if c >= min_pixels]
    masks = [instance == k for k, _ in found]
    return {"boxes": [list(mask_box(m, H)) for m in masks], "scores": [float(c) * score_scale for _, c in found], "slots": [k - 1 for k, _ in found],
            "cut": [mask_cut(m, inner) for m in masks]}


def _merged(photo: str, img: np.ndarray, views: list[dict], out: Path, net=None, resolution: int | None = None,
            mesh_format: str = "ply") -> dict:
    """One photo's record from its tiles' records: their detections merged (``realdata.tiles``), assembled into one
    scene (``realdata.assemble``), and a figure (``img``: the photo as uint8)."""
    from prismonet.scene import LatentScene
    from prismonet.viz.tiled_photo import tiled_photo_figure
    from realdata.assemble import assemble_scene, view_box
    from realdata.tiles import merge_detections

    boxes, scores, cut, picks = [], [], [], []
    for t, v in enumerate(views):
        d = v["detections"]
        boxes += d["boxes"]
        scores += d["scores"]
        cut += d["cut"]
        picks += [(t, v["scene_slots"].index(k)) for k in d["slots"]]
    boxes_a = np.array(boxes, np.float64).reshape(-1, 4)
    kept = merge_detections(boxes_a, np.array(scores), np.array(cut, bool))
    stem = Path(photo).stem
    tile_boxes = [tuple(v["prepare"]["crop_box"]) for v in views]
    chosen = [picks[k] for k in kept]
    scene = scene_path = rendered = None
    if chosen:  # (a tile whose slots were all dropped has no scene file, and no detection)
        view = view_box(views[0]["prepare"]["region"])
        scene = assemble_scene({t: LatentScene.load(views[t]["scene"]) for t in sorted({t for t, _ in chosen})}, tile_boxes, chosen, view)
        scene_path = scene.save(out / f"{stem}.json")
        rendered = _render_over_photo(net, scene, view, img.shape[:2]) if net is not None else None
    fig = tiled_photo_figure(img, [v["prepare"]["outline"] for v in views], boxes_a, np.array(cut, bool), kept, out / f"{stem}.png",
                             rendered=rendered)
    mesh_path = None
    if resolution is not None and net is not None and scene is not None:
        from prismonet.scene.export import scene_mesh, write_mesh

        mesh_path = write_mesh(scene_mesh(net, scene, resolution), out / f"{stem}.{mesh_format}")
    steps = list(views[0]["psnr"])
    return {"photo": photo, "objects_found": len(kept), "tiles": views, "objects": [], "scene": None if scene_path is None else str(scene_path),
            "mesh": None if mesh_path is None else str(mesh_path),
            "detections": {"boxes": [boxes[k] for k in kept], "scores": [scores[k] for k in kept]},
            "outlines": [v["prepare"]["outline"] for v in views], "figure": str(fig),
            "camera": views[0]["camera"] + f", per tile ({len(views)} tiles)", "warnings": sorted({w for v in views for w in v["warnings"]}),
            "finite": all(v["finite"] for v in views), "psnr": {k: float(np.mean([v["psnr"][k] for v in views])) for k in steps},
            "inference": views[0]["inference"]}


def _for_photo(value: float | dict[str, float] | None, name: str) -> float | None:
    """An elevation given for all photos, or per photo stem (``None`` where a photo has none)."""
    return value.get(name) if isinstance(value, dict) else value


def _objects(o, j: int, keep: list[int], world: dict | None) -> list[dict]:
    """Each found object's slot, scale and position in model units, and with a world map its
    position and size on the calibrated table (metres, the table's frame)."""
    p = o.latents.params
    rows = []
    for k in keep:
        pos = p.position[j, k].double().numpy()
        row = {"slot": k, "position": pos.tolist(), "scale": float(p.scale[j, k])}
        if world is not None:
            from realdata.world import WorldMapping

            row["position_table_m"] = WorldMapping.from_dict(world).to_table(pos[None])[0].tolist()
            row["scale_m"] = row["scale"] * world["metres_per_unit"]
        rows.append(row)
    return rows
