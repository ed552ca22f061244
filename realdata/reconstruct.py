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

MIN_PIXELS = 25
"""Visible pixels for a slot to count as a found object (the paper's 25-pixel rule)."""


def found_objects(instance: torch.Tensor, num_slots: int, min_pixels: int = MIN_PIXELS) -> list[int]:
    """Slots with at least ``min_pixels`` visible pixels in an instance image ``(H, W)`` (1-based)."""
    counts = torch.bincount(instance.reshape(-1), minlength=num_slots + 1)[1:]
    return [k for k in range(num_slots) if int(counts[k]) >= min_pixels]


def reconstruct_photos(photos: list[str | Path], out: str | Path, model: str | Path = "shipped", calibration: str | Path | None = None,
                       box: tuple[int, int, int, int] | None = None, normalize: str = "auto", gain=None,
                       objects: int | None = None, min_pixels: int = MIN_PIXELS, mesh_format: str = "ply",
                       resolution: int = 40, inference=None, progress: bool = True,
                       metres_per_unit: float | None = None, elevation: float | dict[str, float] | None = None,
                       elevation_hints: dict[str, float] | None = None) -> list[dict]:
    """Run the whole real-photo path; returns one record per photo (also in ``out/summary.json``).

    ``elevation``: degrees, for all photos or ``{photo stem: degrees}``: an uncalibrated photo is seen by the
    model's training camera moved to that elevation about the table point it looks at (``orbit_elevation``),
    e.g. about 80 for a photo taken from above. Only for models that take the camera as an input
    (``pose_frame = "camera"``); the others know one camera. ``elevation_hints`` (``{photo stem: degrees}``,
    e.g. the labels' ``elevation_deg``): used as ``elevation`` when that is not given and the model takes
    the camera as an input, ignored otherwise."""
    from tqdm import tqdm

    from prismonet.data.dataset import SceneDataset
    from prismonet.evaluation.metrics import image_metrics
    from prismonet.geometry.camera import orbit_elevation
    from prismonet.model.inference import InferenceConfig, infer
    from prismonet.model.io import load_model, prior_fingerprint, training_camera, training_loss_config
    from prismonet.files import write_image
    from prismonet.scene import LatentScene
    from prismonet.scene.export import scene_mesh, write_mesh
    from prismonet.viz.decomposition import decomposition_figure
    from realdata.io import load_photo
    from realdata.pipeline import prepare_photos

    cfg = (inference or InferenceConfig()).without_depth()  # a photo has no depth
    out = Path(out)
    net, info = load_model(model, num_slots=objects)
    prepared = out / "prepared"
    train_cam, train_ground = training_camera(net, info)
    own = net.cfg.pose_frame == "camera"  # a camera-frame model takes the calibrated photo camera as it is
    asked = elevation  # given by the user, not a label's hint: say so when a calibrated camera overrides it
    if elevation is None and own:
        elevation = elevation_hints
    if elevation is not None and not own:
        raise ValueError("an elevation needs a model that takes the camera as an input (pose_frame camera, e.g. a "
                         "tabletop model); this one was trained from one camera")
    recs = prepare_photos(photos, prepared, net.cfg.image_size, calibration, box, normalize, gain,
                          view=(train_cam, train_ground), metres_per_unit=metres_per_unit, own_camera=own)
    ds = SceneDataset(prepared)
    by_name = {Path(r["photo"]).stem: r for r in recs}
    fp = prior_fingerprint(net.prior)
    loss_cfg = training_loss_config(info)
    results = []
    for i in tqdm(range(len(ds)), desc="reconstruct", unit="photo", disable=not progress):
        b = ds.batch([i])  # seen by the training camera: rectified to it, or assumed (as the paper's real photos)
        own_cam = by_name[ds.names[i]].get("own_camera", False)
        elev = _for_photo(elevation, ds.names[i])
        if not own_cam:
            b.K[:] = train_cam.K
            b.T_world_cam[:] = train_cam.T_world_cam if elev is None else orbit_elevation(train_cam.T_world_cam, train_ground, elev)
        b.ground_z[:] = train_ground
        warnings = list(by_name[ds.names[i]].get("warnings", []))
        if own_cam and _for_photo(asked, ds.names[i]) is not None:
            warnings.append(f"elevation {_for_photo(asked, ds.names[i]):g} deg ignored: this photo's calibrated camera is used as it is")
        psnr = {}

        def score(step, o, b=b):
            psnr[step] = image_metrics(o.composite.image.numpy(), b.rgb.numpy())["PSNR"]

        o = infer(net, b, cfg, loss_cfg, on_step=score)
        name = ds.names[i]
        rec = by_name[name]
        photo = load_photo(rec["photo"])
        keep = found_objects(o.composite.instance[0], o.obj_depth.shape[1], min_pixels)
        title = f"{Path(rec['photo']).name}: {len(keep)} objects found (>= {min_pixels} px), PSNR " + " -> ".join(f"{v:.1f}" for v in psnr.values()) + " dB"
        fig = decomposition_figure(b.rgb, o, 0, out / f"{name}.png", photo=(np.clip(photo, 0, 1) * 255).round().astype(np.uint8),
                                   photo_outline=rec.get("outline"), title=title, min_pixels=min_pixels)
        scene = LatentScene.from_output(o, b, 0, fp)
        scene.save(out / f"{name}.json")
        write_image(out / f"{name}_instance.png", o.composite.instance[0].numpy().astype(np.uint8))
        mesh_path = None
        if keep:
            mesh_path = write_mesh(scene_mesh(net, LatentScene.from_output(o, b, 0, fp, slots=keep), resolution),
                                   out / f"{name}.{mesh_format}")
        finite = all(bool(torch.isfinite(t).all()) for t in (o.composite.image, o.composite.depth, o.latents.bg_color,
                                                               o.latents.params.position, o.latents.params.z_sh))
        results.append({"photo": rec["photo"], "objects_found": len(keep), "found_slots": keep,
                        "objects": _objects(o, keep, rec.get("world")),
                        "figure": str(fig), "scene": str(out / f"{name}.json"), "instance": str(out / f"{name}_instance.png"), "mesh": None if mesh_path is None else str(mesh_path),
                        "camera": "the photo's own calibrated camera" if own_cam else
                        "rectified to the training view (calibrated ground pose)" if rec.get("rectified")
                        else "model's training camera (assumed)" if elev is None
                        else f"model's training camera moved to {elev:g} deg elevation (assumed)", "warnings": warnings,
                        "finite": finite, "psnr": psnr, "inference": cfg.record(), "prepare": rec})
    (out / "summary.json").write_text(json.dumps(results, indent=1))
    return results


def _for_photo(value: float | dict[str, float] | None, name: str) -> float | None:
    """An elevation given for all photos, or per photo stem (``None`` where a photo has none)."""
    return value.get(name) if isinstance(value, dict) else value


def _objects(o, keep: list[int], world: dict | None) -> list[dict]:
    """Each found object's slot, scale and position in model units, and with a world map its
    position and size on the calibrated table (metres, the table's frame)."""
    p = o.latents.params
    rows = []
    for k in keep:
        pos = p.position[0, k].double().numpy()
        row = {"slot": k, "position": pos.tolist(), "scale": float(p.scale[0, k])}
        if world is not None:
            from realdata.world import WorldMapping

            row["position_table_m"] = WorldMapping.from_dict(world).to_table(pos[None])[0].tolist()
            row["scale_m"] = row["scale"] * world["metres_per_unit"]
        rows.append(row)
    return rows
