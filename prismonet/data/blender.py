"""The photoreal test ladder: the Clevr generator's scenes rendered by Blender Cycles with CLEVR's assets.

Each rung renders the same scene layouts as ``prismonet data clevr`` (the same sampler, seed, scene
indices and camera; by default the 500 first scenes of the default dataset's test split), and adds one
thing real photos have that the training renderer lacks:

=====  ============================================================================================
rung   what changes
=====  ============================================================================================
a      CLEVR's rubber material; otherwise the training renderer's light (a shadowless sun along
       ``light_dir`` plus uniform ambient light) and its flat, unshaded ground; linear output like
       the training images. The bridge: how far Cycles alone moves the images.
b      CLEVR's lights (key, fill and back area lights and a weak sun, from its base scene) with
       shadows, a shaded ground, and sRGB output as CLEVR's own images: CLEVR's look.
c      b + CLEVR's metal on each object with probability 1/2.
d      c + a ground colour drawn per scene (grey 90-210 with a warm tint up to 25 levels) and CLEVR's
       camera jitter (+-0.5 per axis; the layouts then differ from a-c, as the sampler draws the camera).
=====  ============================================================================================

Depth and instance masks come from the project's own ground-truth raycaster (``raycast_gt``) on the
same meshes and camera, so the ground truth is exact and identical to the training data's; Blender
renders only the colours. Objects are the project's 27 Clevr meshes, smooth-shaded below 30 degrees.

``bpy`` pins ``numpy<2`` and cannot share the project's environment: it lives in its own
(``scripts/setup_blender.sh`` makes ``.venv-blender``), and ``blender_worker.py`` runs there as a
subprocess. The rendered RGB comes back as ``rgb.npy``; everything else is computed here.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from prismonet.data.clevr import COLOR_RGB, ClevrConfig, clevr_camera, sample_scene
from prismonet.files import InputError

BLENDER_ASSETS = Path(__file__).resolve().parents[1] / "assets" / "clevr_blender"
"""CLEVR's base scene and material files (BSD licence, with LICENSE and PATENTS beside them)."""
WORKER = Path(__file__).resolve().with_name("blender_worker.py")
DEFAULT_FIRST_INDEX = 10000
"""The first test scene of ``prismonet data clevr``'s default split (9000 train + 1000 val)."""


@dataclass(frozen=True)
class BlenderRung:
    """What one rung of the ladder renders (see the module's table)."""

    lights: str = "flat"
    """``flat``: the training renderer's sun and ambient light, no shadows, unshaded ground;
    ``clevr``: CLEVR's area lights and sun with shadows, a shaded ground."""
    tone: str = "linear"
    """``linear``: rendered radiance is the pixel value (as the training renderer); ``srgb``: encoded
    with the sRGB curve, as CLEVR's images and cameras' JPEGs."""
    metal: float = 0.0
    """Probability that an object gets CLEVR's metal instead of its rubber."""
    random_ground: bool = False
    """Draw the ground colour per scene instead of the dataset's grey."""
    camera_jitter: float = 0.0
    samples: int = 16
    """Cycles samples per pixel (denoised with OpenImageDenoise; 16 is within 0.4 dB of 1024 at 64 px)."""
    denoise: bool = True
    filter_width: float = 1.5
    """Pixel filter width in pixels (Cycles' default 1.5 anti-aliases; ~0 samples the pixel centre
    only, as the training renderer does)."""
    smooth_angle_deg: float = 30.0

    def __post_init__(self) -> None:
        if self.lights not in ("flat", "clevr") or self.tone not in ("linear", "srgb"):
            raise ValueError(f"rung: lights must be flat|clevr and tone linear|srgb, got {self.lights!r}, {self.tone!r}")
        if not 0 <= self.metal <= 1 or self.samples < 1 or self.filter_width <= 0 or self.camera_jitter < 0:
            raise ValueError(f"rung: metal in [0, 1], samples >= 1, filter_width > 0, camera_jitter >= 0; got {self}")


RUNGS: dict[str, BlenderRung] = {
    "a": BlenderRung(filter_width=0.01),
    "b": BlenderRung(lights="clevr", tone="srgb"),
    "c": BlenderRung(lights="clevr", tone="srgb", metal=0.5),
    "d": BlenderRung(lights="clevr", tone="srgb", metal=0.5, random_ground=True, camera_jitter=0.5),
}


def random_ground_color(rng: np.random.Generator) -> tuple[int, int, int]:
    """A table-like ground: grey level U(90, 210) with a warm tint U(0, 25) (red up, blue down)."""
    g, t = rng.uniform(90, 210), rng.uniform(0, 25)
    return tuple(int(np.clip(round(x), 0, 255)) for x in (g + t, g, g - t))  # type: ignore[return-value]


def find_blender_python(python: str | None = None) -> str:
    """The Python that can ``import bpy``: ``python``, else ``$PRISMONET_BLENDER_PYTHON``, else
    ``.venv-blender/bin/python`` here, else this one; one line if none can."""
    repo = Path(__file__).resolve().parents[2]
    candidates = [python] if python else [os.environ.get("PRISMONET_BLENDER_PYTHON"), ".venv-blender/bin/python",
                                          str(repo / ".venv-blender" / "bin" / "python"), sys.executable]
    for c in candidates:
        if c and (Path(c).is_file() or c == sys.executable):
            probe = subprocess.run([c, "-c", "import bpy; print('bpy', bpy.app.version_string)"], capture_output=True, text=True)
            if probe.returncode == 0 and probe.stdout.startswith("bpy "):
                return c
            if python:
                raise InputError(f"{python}: cannot import bpy (make a Python that can with scripts/setup_blender.sh)")
    raise InputError("no Python with Blender's bpy found: run scripts/setup_blender.sh (it makes .venv-blender), "
                     "or pass --python / set PRISMONET_BLENDER_PYTHON")


def scene_job(spec, ground_color: tuple[int, int, int], materials: list[str]) -> dict:
    """One scene of a worker's job: camera, ground and each object's mesh, pose, colour and material."""
    objects = []
    for o, mat in zip(spec.objects, materials):
        M = np.eye(4)
        M[:3, :3] = o.scale * o.rotation()
        M[:3, 3] = o.position
        objects.append({"mesh": int(o.shape_id), "matrix": M.tolist(), "color": list(COLOR_RGB[o.color_id]), "material": mat})
    return {"K": spec.camera.K.double().numpy().tolist(), "T_world_cam": spec.camera.T_world_cam.double().numpy().tolist(),
            "ground_z": float(spec.ground_z), "ground_color": list(ground_color), "objects": objects}


def _run_workers(python: str, jobs: list[Path], bar) -> None:
    """Run one worker per job folder at once; each prints ``done I`` per scene (the bar's updates)."""
    procs = [subprocess.Popen([python, str(WORKER), str(j)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for j in jobs]
    errors: dict[int, list[str]] = {}

    def pump(k: int, p: subprocess.Popen) -> None:
        for line in p.stdout:  # type: ignore[union-attr]
            if line.startswith("done "):
                bar.update(1)
        errors[k] = p.stderr.read().splitlines()[-8:]  # type: ignore[union-attr]

    threads = [threading.Thread(target=pump, args=(k, p), daemon=True) for k, p in enumerate(procs)]
    try:
        for t in threads:
            t.start()
        for t, p in zip(threads, procs):
            t.join()
            p.wait()
    except BaseException:
        for p in procs:
            p.kill()
        raise
    for k, p in enumerate(procs):
        if p.returncode != 0:
            raise RuntimeError(f"the Blender worker failed (exit {p.returncode}): " + " | ".join(errors.get(k, [])))


def ladder_scenes(cfg: ClevrConfig, rung: BlenderRung, scenes: int, seed: int, first_index: int):
    """The ladder's scenes without their Blender colours: ``(arrays, reference, job_scenes, materials)``.

    ``arrays`` are the packed dataset's arrays (depth, instances, cameras and objects from the generator's
    sampler and ground-truth raycaster, exactly as ``data clevr`` makes scenes ``first_index ..`` for
    ``seed``; ``rgb`` holds the training renderer's images until Blender's replace them); ``reference`` a
    copy of those images;
    ``job_scenes`` what the Blender worker needs; ``materials`` each object's material.
    """
    from prismonet.data.generate import store_scene
    from prismonet.data.raycast_gt import render_scene
    from prismonet.data.scenes import empty_scene_arrays

    camera = clevr_camera(cfg)
    arrays = empty_scene_arrays(scenes, cfg.image_size, cfg.image_size, cfg.num_objects)
    job_scenes, materials = [], []
    for j in range(scenes):
        i = first_index + j
        rng = np.random.default_rng([seed, i])
        spec = sample_scene(rng, cfg, camera)
        r = render_scene(spec, cfg, rng, nthreads=1)
        extra = np.random.default_rng([seed, i, 1])  # the rung's own draws leave the layout's stream alone
        ground = random_ground_color(extra) if rung.random_ground else tuple(cfg.ground_color)
        mats = ["metal" if extra.random() < rung.metal else "rubber" for _ in spec.objects]
        materials.append(mats)
        job_scenes.append(scene_job(spec, ground, mats))
        store_scene(arrays, j, replace(spec, ground_color=ground), r)
    return arrays, arrays["rgb"].copy(), job_scenes, materials


def generate_blender(out: str | Path, rung: str | BlenderRung, cfg: ClevrConfig = ClevrConfig(), scenes: int = 500,
                     seed: int = 0, first_index: int = DEFAULT_FIRST_INDEX, workers: int = 1, python: str | None = None,
                     progress: bool = True, assets: str | Path = BLENDER_ASSETS) -> dict:
    """Render ``scenes`` test scenes of one rung into ``out`` (packed format, all in the test split).

    Scene ``j`` is the Clevr generator's scene ``first_index + j`` for ``seed``: with the defaults, the
    test split of ``prismonet data clevr --seed 0``. Returns the dataset's meta; ``meta["blender"]``
    records the rung, the materials and how far the colours are from the training renderer's.
    """
    from tqdm import tqdm

    from prismonet.data.generate import check_output_dir, write_dataset
    from prismonet.evaluation.metrics import image_metrics

    name = rung if isinstance(rung, str) else "custom"
    if isinstance(rung, str):
        if rung not in RUNGS:
            raise ValueError(f"rung: expected one of {', '.join(RUNGS)}, got {rung!r}")
        rung = RUNGS[rung]
    if cfg.towers is not None or cfg.shapes != "clevr":
        raise ValueError("the Blender ladder renders Clevr's own shapes only (no towers or imported meshes)")
    if scenes < 1 or workers < 1 or first_index < 0:
        raise ValueError(f"scenes and workers must be positive and first_index >= 0, got {scenes}, {workers}, {first_index}")
    assets = Path(assets)
    if not (assets / "base_scene.blend").is_file():
        raise InputError(f"{assets}: has no base_scene.blend (CLEVR's Blender assets)")
    out = Path(out)
    check_output_dir(out)
    python = find_blender_python(python)
    t0 = time.perf_counter()
    cfg = replace(cfg, camera_jitter=rung.camera_jitter)
    arrays, reference, job_scenes, materials = ladder_scenes(cfg, rung, scenes, seed, first_index)

    from prismonet.shapes.library import shape_library

    lib = shape_library("clevr", "seen")
    used = sorted({o["mesh"] for s in job_scenes for o in s["objects"]})
    meshes = {}
    for m in used:
        v, f = lib.mesh(m)
        meshes[f"v{m}"], meshes[f"f{m}"] = np.asarray(v, np.float64), np.asarray(f, np.int64)
    work = Path(tempfile.mkdtemp(prefix=".blender-", dir=out.parent if out.parent.exists() else None))
    try:
        parts = np.array_split(np.arange(scenes), min(workers, scenes))
        jobs = []
        for k, idx in enumerate(parts):
            d = work / f"job{k}"
            d.mkdir()
            job = {"assets": str(assets.resolve()), "width": cfg.image_size, "height": cfg.image_size, "rung": asdict(rung),
                   "light_dir": list(cfg.light_dir), "ambient": cfg.ambient, "diffuse": cfg.diffuse, "threads": 1,
                   "scenes": [job_scenes[j] for j in idx]}
            (d / "job.json").write_text(json.dumps(job))
            np.savez(d / "meshes.npz", **meshes)
            jobs.append(d)
        bar = tqdm(total=scenes, desc=f"Blender rung {name}", unit="scene", disable=not progress)
        _run_workers(python, jobs, bar)
        bar.close()
        for d, idx in zip(jobs, parts):
            if not (d / "rgb.npy").is_file():
                raise RuntimeError(f"the Blender worker ({python}) exited without writing its images")
            arrays["rgb"][idx] = np.load(d / "rgb.npy")
    finally:
        shutil.rmtree(work, ignore_errors=True)

    diff = np.abs(arrays["rgb"].astype(np.float64) - reference) / 255.0
    fg = arrays["instance"] > 0
    vs = {"mean_abs": float(diff.mean()), "mean_abs_objects": float(diff[fg].mean()) if fg.any() else 0.0,
          "mean_abs_ground": float(diff[~fg].mean()),
          **image_metrics(arrays["rgb"].transpose(0, 3, 1, 2) / 255.0, reference.transpose(0, 3, 1, 2) / 255.0)}
    meta = {"generator": "blender", "generator_version": "blender-1", "config": asdict(cfg), "seed": seed,
            "blender": {"rung": name, "settings": asdict(rung), "first_index": first_index, "materials": materials,
                        "vs_training_renderer": vs}}
    return write_dataset(out, arrays, (0, 0, scenes), meta, t0)
