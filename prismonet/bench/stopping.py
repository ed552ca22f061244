"""Inference time per scene against the number of objects in it, with the encoder's stop rule and
without (``prismonet.model.stopping``), in one run: each scene is decoded alone (batch of one, as a
photo is), both ways, interleaved, so that load on the machine affects both alike."""

from __future__ import annotations

import statistics
import time

import numpy as np
import torch


def bench_stopping(model, ds, scenes_per_count: int = 8, repeats: int = 3, use_depth: bool = True,
                   progress: bool = True) -> list[dict]:
    """One row per object count present in ``ds``: median ms per scene without and with stopping,
    the slots decoded with stopping, and the ratio. Uses the first ``scenes_per_count`` scenes of
    each count; each scene is timed ``repeats`` times each way (median)."""
    from tqdm import tqdm

    from prismonet.model.stopping import StopRule

    counts = np.asarray(ds.arrays["obj_count"])
    by_count: dict[int, list[int]] = {}
    for i, c in enumerate(counts):
        if len(by_count.setdefault(int(c), [])) < scenes_per_count:
            by_count[int(c)].append(i)
    rule = StopRule()
    rows = []
    model.eval()
    todo = sum(len(v) for v in by_count.values())
    bar = tqdm(total=todo, desc="bench stopping", unit="scene", disable=not progress)
    for c in sorted(by_count):
        plain, stopped, slots = [], [], []
        for i in by_count[c]:
            b = ds.batch([i])
            depth = b.depth if use_depth else None
            t_plain, t_stop = [], []
            with torch.no_grad():
                for _ in range(repeats):
                    t0 = time.perf_counter()
                    model(b.rgb, b.K, b.T_world_cam, b.ground_z)
                    t_plain.append(time.perf_counter() - t0)
                    t0 = time.perf_counter()
                    out = model(b.rgb, b.K, b.T_world_cam, b.ground_z, stop=rule.bind(b.rgb, depth))
                    t_stop.append(time.perf_counter() - t0)
            plain.append(statistics.median(t_plain))
            stopped.append(statistics.median(t_stop))
            slots.append(int(out.latents.params.active.sum()))
            bar.update(1)
        rows.append({"objects": c, "scenes": len(by_count[c]), "ms_all_slots": 1e3 * statistics.median(plain),
                     "ms_stop": 1e3 * statistics.median(stopped), "slots_stop": float(np.mean(slots))})
    bar.close()
    eight = max(rows, key=lambda r: r["objects"])
    for r in rows:
        r["stop_vs_most"] = r["ms_stop"] / eight["ms_stop"]
    return rows


def format_rows(rows: list[dict], num_slots: int) -> str:
    lines = [f"| objects | scenes | ms/scene, all {num_slots} slots | ms/scene, stopping | slots decoded | stopping: x the {rows[-1]['objects']}-object time |",
             "|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['objects']} | {r['scenes']} | {r['ms_all_slots']:.1f} | {r['ms_stop']:.1f} | {r['slots_stop']:.2f} | {r['stop_vs_most']:.2f} |")
    return "\n".join(lines)
