"""Generate a packed CLEVR-style RGB-D dataset, deterministically given a seed.

Scene ``i`` draws all its randomness from ``numpy.random.default_rng([seed, i])``, so the result
does not depend on the number of worker processes or on chunking. The dataset is written into a
hidden temporary folder beside ``out`` that is renamed into place only when complete.
"""

from __future__ import annotations

import os
import shutil
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict
from pathlib import Path

import numpy as np

from prismonet.data.clevr import GENERATOR_VERSION, ClevrConfig, check_placement_feasible, clevr_camera, sample_scene
from prismonet.data.errors import OutputDirError
from prismonet.data.scenes import empty_scene_arrays
from prismonet.shapes.library import CLEVR

DEFAULT_SPLIT = (9000, 1000, 2500)
SPLIT_NAMES = ("train", "val", "test")
CHUNK = 250
"""Scenes per worker task: large enough to amortise process overhead, small for a smooth bar."""


def _die_with_parent() -> None:
    """Worker initializer: on Linux, have the kernel kill this worker when its parent dies (even by
    SIGKILL), so an interrupted ``data clevr`` leaves no orphaned workers blocked on a pipe."""
    import ctypes
    import signal
    import sys

    if sys.platform.startswith("linux"):
        try:
            ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, int(signal.SIGKILL))  # PR_SET_PDEATHSIG
        except OSError:
            pass
    if os.getppid() == 1:  # the parent died before prctl took effect
        os._exit(1)


def _remove_stale_partials(out: Path) -> None:
    """Remove hidden partial folders of earlier runs for ``out`` whose process is gone (killed)."""
    from prismonet.files import pid_alive

    for p in out.parent.glob(f".{out.name}.partial-*"):
        pid = p.name.rsplit("-", 1)[1]
        if pid.isdigit() and not pid_alive(pid):
            shutil.rmtree(p, ignore_errors=True)


def generator_name(cfg: ClevrConfig) -> str:
    """``"clevr"`` (scattered objects), ``"towers"`` (stacked Clevr cubes) or ``"stacks"`` (stacked blocks of a
    block set, ``prismonet.data.stacks``)."""
    if cfg.towers is None:
        return "clevr"
    return "towers" if cfg.shapes == CLEVR else "stacks"


def render_range(cfg_dict: dict, seed: int, start: int, stop: int) -> dict[str, np.ndarray]:
    """Sample and render scenes ``start..stop-1`` (runs in worker processes)."""
    from prismonet.data.raycast_gt import render_scene, world_rays

    from prismonet.data.stacks import sample_stacks
    from prismonet.data.towers import sample_towers, tower_camera

    cfg = ClevrConfig(**{k: tuple(v) if isinstance(v, list) else v for k, v in cfg_dict.items()})
    camera = tower_camera(cfg) if cfg.towers is not None else clevr_camera(cfg)
    sample = {"clevr": sample_scene, "towers": sample_towers, "stacks": sample_stacks}[generator_name(cfg)]
    out = empty_scene_arrays(stop - start, cfg.image_size, cfg.image_size, cfg.num_objects)
    rays = None
    for j, i in enumerate(range(start, stop)):
        rng = np.random.default_rng([seed, i])
        spec = sample(rng, cfg, camera)
        if rays is None or cfg.camera_jitter > 0 or cfg.randomize is not None:
            rays = world_rays(spec)
        store_scene(out, j, spec, render_scene(spec, cfg, rng, nthreads=1, rays=rays))
    return out


def store_scene(out: dict[str, np.ndarray], j: int, spec, rendered) -> None:
    """Write scene ``j``'s layout (``SceneSpec``) and renders (``RenderedScene``) into the scene arrays."""
    out["rgb"][j], out["depth"][j], out["instance"][j] = rendered.rgb, rendered.depth, rendered.instance
    out["K"][j] = spec.camera.K.numpy()
    out["T_world_cam"][j] = spec.camera.T_world_cam.numpy()
    out["ground_z"][j] = spec.ground_z
    out["ground_color"][j] = spec.ground_color
    out["obj_count"][j] = len(spec.objects)
    for k, o in enumerate(spec.objects):
        out["obj_shape"][j, k] = o.shape_id
        out["obj_category"][j, k] = o.category_id
        out["obj_color"][j, k] = o.color_id
        out["obj_scale"][j, k] = o.scale
        out["obj_position"][j, k] = o.position
        out["obj_yaw"][j, k] = o.yaw
        out["obj_axis"][j, k] = o.axis


def check_output_dir(out: Path) -> None:
    """Raise ``OutputDirError`` unless ``out`` is a new or empty folder that can be written, in a
    folder that can be written too (the data are written beside it, then renamed into place).
    Writability is probed by creating a file (``prismonet.files``), which also catches read-only file
    systems and root, for whom ``os.access`` always says yes."""
    from prismonet.files import InputError, check_output, probe_writable

    try:
        check_output(out, "new_dir")
        if out.exists():
            probe_writable(out.parent, out)
    except InputError as e:
        raise OutputDirError(str(e)) from None


def generate_clevr(
    out: str | Path,
    cfg: ClevrConfig = ClevrConfig(),
    split: tuple[int, ...] = DEFAULT_SPLIT,
    seed: int = 0,
    workers: int = 2,
    progress: bool = True,
    chunk: int = CHUNK,
) -> dict:
    """Generate ``sum(split)`` scenes into ``out`` as a packed dataset; returns its meta.

    Args:
        out: new or empty output folder.
        cfg: generator settings.
        split: scene counts of the train, val and test splits (consecutive scene indices).
        seed: base seed.
        workers: processes; 1 renders in this process.
        progress: show a progress bar.
        chunk: scenes per worker task (does not change the result).
    """
    from tqdm import tqdm

    if len(split) != 3 or any(int(n) < 0 for n in split) or sum(split) <= 0:
        raise ValueError(f"split: expected three non-negative scene counts with a positive sum, got {split}")
    if workers <= 0 or chunk <= 0:
        raise ValueError(f"workers and chunk must be positive, got {workers} and {chunk}")
    check_placement_feasible(cfg)
    out = Path(out)
    check_output_dir(out)
    total = int(sum(split))
    t0 = time.perf_counter()
    previous_term = _sigterm_interrupts()
    try:
        arrays = empty_scene_arrays(total, cfg.image_size, cfg.image_size, cfg.num_objects)
        chunks = [(s, min(s + chunk, total)) for s in range(0, total, chunk)]
        cfg_dict = asdict(cfg)
        bar = tqdm(total=total, desc="rendering scenes", unit="scene", disable=not progress)
        if workers == 1 or len(chunks) == 1:
            results = (render_range(cfg_dict, seed, a, b) for a, b in chunks)
            for (a, b), part in zip(chunks, results):
                for k in arrays:
                    arrays[k][a:b] = part[k]
                bar.update(b - a)
        else:
            import multiprocessing as mp

            with ProcessPoolExecutor(workers, mp_context=mp.get_context("spawn"), initializer=_die_with_parent) as pool:
                futures = [pool.submit(render_range, cfg_dict, seed, a, b) for a, b in chunks]
                for (a, b), fut in zip(chunks, futures):
                    part = fut.result()
                    for k in arrays:
                        arrays[k][a:b] = part[k]
                    bar.update(b - a)
        bar.close()
        meta = {"generator": generator_name(cfg), "generator_version": GENERATOR_VERSION,
                "config": cfg_dict, "seed": seed}
        return write_dataset(out, arrays, split, meta, t0)
    finally:
        if previous_term is not None:
            import signal

            signal.signal(signal.SIGTERM, previous_term)


def write_dataset(out: Path, arrays: dict[str, np.ndarray], split: tuple[int, ...], meta: dict, t0: float) -> dict:
    """Write scenes ``arrays`` as a packed dataset at ``out`` (checked by ``check_output_dir``): the
    splits take consecutive scenes; ``meta`` gets the format, counts, splits and seconds since ``t0``.
    Everything goes into a hidden folder beside ``out`` renamed into place at the end."""
    from prismonet.data import packed

    _remove_stale_partials(out)
    tmp = out.parent / f".{out.name}.partial-{os.getpid()}"
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    try:
        meta = {"format": packed.PACKED_FORMAT, "version": packed.PACKED_VERSION, **meta,
                "counts": dict(zip(SPLIT_NAMES, map(int, split))), "splits": {}}
        start = 0
        for name, n in zip(SPLIT_NAMES, split):
            meta["splits"][name] = packed.write_split(tmp / name, {k: v[start : start + n] for k, v in arrays.items()})
            start += n
        meta["seconds"] = round(time.perf_counter() - t0, 2)
        packed.write_meta(tmp, meta)
        if out.exists():
            os.chmod(tmp, out.stat().st_mode & 0o7777)  # the folder the user made keeps its mode
            out.rmdir()  # checked empty above
        tmp.rename(out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return meta


def _sigterm_interrupts():
    """SIGTERM raises ``KeyboardInterrupt`` (so the partial folder is removed) while generating;
    returns the previous handler, or ``None`` off the main thread."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        return None

    def handler(signum, frame):
        raise KeyboardInterrupt(f"signal {signum}")

    return signal.signal(signal.SIGTERM, handler)
