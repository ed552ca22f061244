"""``prismonet bench search``: the chunked front-to-back root search against the plain one.

Renders ground-truth layouts (poses from a generated dataset, shapes as the shipped prior's
latents of the true shape ids) with both settings in one run, and checks the hits are identical.
"""

from __future__ import annotations

import statistics
import time

import torch


def bench_search(batch: int = 8, objects: int = 3, repeats: int = 12, seed: int = 0) -> str:
    import numpy as np

    from prismonet.data.clevr import ClevrConfig, clevr_camera, sample_scene
    from prismonet.render import RenderSettings, SceneParams, render_objects
    from prismonet.shapes.prior import load_prior

    torch.set_num_threads(2)
    prior = load_prior()
    cfg = ClevrConfig(num_objects=objects)
    cam = clevr_camera(cfg)
    specs = [sample_scene(np.random.default_rng([seed, b]), cfg, cam).objects for b in range(batch)]
    t = lambda f: torch.tensor([[f(o) for o in objs] for objs in specs], dtype=torch.float32)
    params = SceneParams(
        z_sh=prior.latents[torch.tensor([[o.shape_id for o in objs] for objs in specs])],
        z_tex=torch.zeros(batch, objects, 3),
        position=torch.tensor([[o.position for o in objs] for objs in specs], dtype=torch.float32),
        cos_sin=torch.stack([t(lambda o: np.cos(o.yaw)), t(lambda o: np.sin(o.yaw))], -1),
        scale=t(lambda o: o.scale),
    )
    K = cam.K[None].expand(batch, 3, 3).contiguous()
    T = cam.T_world_cam[None].expand(batch, 4, 4).contiguous()
    sdf = lambda z, x: prior.decoder(z[:, None, :], x)
    hits = {}
    times: dict[str, list[float]] = {"plain (all 12 samples)": [], "chunked (4 at a time)": []}
    settings = {"plain (all 12 samples)": RenderSettings(search_chunk=12), "chunked (4 at a time)": RenderSettings(search_chunk=4)}
    stats = {}
    for r in range(repeats + 2):
        for name, s in settings.items():  # interleaved, so drift hits both alike
            t0 = time.perf_counter()
            out = render_objects(sdf, None, params, K, T, 64, 64, s)
            if r >= 2:
                times[name].append(time.perf_counter() - t0)
            hits[name] = out.mask
            stats[name] = out.stats
    base = statistics.median(times["plain (all 12 samples)"])
    lines = [f"{batch} ground-truth layouts x {objects} objects, shipped prior, 64x64, 12 samples; medians of {repeats}, interleaved", "",
             "| search | ms | speed-up | SDF evals/ray | hits |", "|---|---|---|---|---|"]
    for name in settings:
        m = statistics.median(times[name])
        lines.append(f"| {name} | {1e3 * m:.1f} | {base / m:.2f}x | {stats[name]['sdf_evals'] / stats[name]['rays']:.2f} | {stats[name]['hits']} |")
    same = torch.equal(hits["plain (all 12 samples)"], hits["chunked (4 at a time)"])
    lines += ["", f"Identical hit masks: {same}."]
    return "\n".join(lines)
