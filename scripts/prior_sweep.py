"""Shape-prior width against mesh quality and render cost, per ShapeNet-style setting (issue 22, item 3).

    python3 scripts/prior_sweep.py data/furniture/cars data/furniture/tabletop --widths 64,128,256 --out runs/prior_sweep
    python3 scripts/prior_sweep.py ... --out runs/prior_sweep --table        # only print the table of what is done

For each setting (a folder made by ``prismonet shapes import-furniture``) and each width it pre-trains a
prior (D_sh = 16, 4 layers, 300 epochs, one thread; ``OUT/SETTING_wW``, resumable: rerun the same command),
measures it on the setting's seen shapes (Chamfer-L1 at marching-cubes resolution 64 and IoU on a 32^3
grid, ``quality.json``), and times one render step with it: forward + backward of a depth + image loss
through ``render_scene`` (the renderer's defaults) for 8 scenes of 3 objects, the generator's layouts with
the prior's own training codes, so that rays hit that prior's surfaces, through the prior's tight box. The widths of one setting are timed
interleaved in one process (``--rounds`` rounds of ``--repeats`` steps; medians), so host load falls on
all of them alike. Results go to ``OUT/sweep.json``; the table is printed as Markdown.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch


def run_name(setting: str, width: int) -> str:
    return f"{Path(setting).name}_w{width}"


def pretrain_one(setting: str, width: int, out: Path, epochs: int, threads: int) -> dict:
    from prismonet.shapes.decoder import SDFDecoderConfig
    from prismonet.shapes.evaluate import evaluate_prior
    from prismonet.shapes.pretrain import PretrainConfig, pretrain

    run = out / run_name(setting, width)
    quality = run / "quality.json"
    if quality.is_file():
        return json.loads(quality.read_text())
    cfg = PretrainConfig(decoder=SDFDecoderConfig(latent_dim=16, width=width), epochs=epochs, threads=threads)
    prior = pretrain(cfg, run, shape_set=setting, cache_dir=out / "sdf_samples")
    report = evaluate_prior(prior, shape_set=setting, resolution=64, iou_resolution=32)
    report["train_seconds"] = prior.info["train_seconds"]
    report["parameters"] = sum(p.numel() for p in prior.decoder.parameters())
    tmp = quality.with_name(".quality.json.tmp")
    tmp.write_text(json.dumps(report, indent=2))
    tmp.replace(quality)
    return report


def render_step_ms(setting: str, widths: list[int], out: Path, rounds: int, repeats: int, threads: int) -> dict[int, float]:
    """Median ms of one render forward + backward per width, interleaved."""
    from prismonet.bench.render import make_scenes
    from prismonet.render import RenderSettings, SceneParams, render_scene
    from prismonet.shapes.prior import load_prior

    torch.set_num_threads(threads)
    sc = make_scenes(8, 3, seed=0)
    B, K = sc.params.scale.shape
    priors = {w: load_prior(out / run_name(setting, w) / "prior") for w in widths}
    color = lambda z, x: torch.sigmoid(z[:, :3] + x)
    from prismonet.shapes.normalize import shape_bounds
    from prismonet.shapes.pretrain import load_shape_set

    settings = RenderSettings(box=shape_bounds(load_shape_set(setting).meshes))  # the prior's bounds, as a model renders

    def step(prior) -> None:
        idx = torch.arange(B * K) % len(prior.latents)
        p = sc.params
        params = SceneParams(prior.latents[idx].reshape(B, K, -1).clone(), p.z_tex.clone(), p.position.clone(),
                             p.cos_sin.clone(), p.scale.clone())
        for t in (params.z_sh, params.position, params.cos_sin, params.scale, params.z_tex):
            t.requires_grad_(True)
        sdf = lambda z, x: prior.decoder(z[:, None, :], x)  # the scene model's call: z (R, D), x (R, S, 3)
        comp, _ = render_scene(sdf, color, params, sc.bg_color, sc.bg_depth, sc.K, sc.T, settings)
        ((comp.depth - 9.0).abs().mean() + comp.image.square().mean()).backward()

    times: dict[int, list[float]] = {w: [] for w in widths}
    for prior in priors.values():
        step(prior)  # warm-up
    for _ in range(rounds):
        for w, prior in priors.items():
            for _ in range(repeats):
                t0 = time.perf_counter()
                step(prior)
                times[w].append(1e3 * (time.perf_counter() - t0))
    return {w: statistics.median(t) for w, t in times.items()}


def _scenes_of(setting: str) -> Path | None:
    """``data/NAME`` or ``data/furniture_NAME``, whichever holds scenes of this setting's meshes
    (``prismonet data clevr --shapes SETTING``); ``data/tabletop`` is the real-tabletop Clevr set."""
    for folder in (Path("data") / Path(setting).name, Path("data") / f"furniture_{Path(setting).name}"):
        meta = folder / "meta.json"
        if meta.is_file():
            shapes = json.loads(meta.read_text()).get("config", {}).get("shapes")
            if shapes is not None and Path(shapes).resolve() == Path(setting).resolve():
                return folder
    return None


def _true_pose_render(setting: str, scenes: int):
    """The first ``scenes`` validation scenes of the setting's dataset, and a function that renders them
    with their true poses and each object's own training code of a prior, returning the foreground IoU,
    the instance IoU of every object of at least 25 pixels, and the depth RMSE where both see foreground."""
    from prismonet.data.dataset import SceneDataset
    from prismonet.render import SceneParams, render_scene
    from prismonet.render.background import plane_depth

    b = SceneDataset(_scenes_of(setting), "val").batch(list(range(scenes)))
    B, K = b.obj_shape.shape
    H, W = b.depth.shape[-2:]
    active = torch.arange(K)[None] < b.obj_count[:, None]
    bg_depth = plane_depth(b.K, b.T_world_cam, H, W, b.ground_z)

    def fit(prior, settings) -> tuple[float, np.ndarray, float]:
        z = prior.latents[b.obj_shape.clamp(min=0)]
        params = SceneParams(z, torch.zeros(B, K, 1), b.obj_position, torch.stack([b.obj_yaw.cos(), b.obj_yaw.sin()], -1),
                             b.obj_scale, active=active)
        sdf = lambda zz, x: prior.decoder(zz[:, None, :], x)
        with torch.no_grad():
            comp, _ = render_scene(sdf, lambda zz, x: x.new_zeros(len(x), 3), params, torch.zeros(B, 3), bg_depth,
                                   b.K, b.T_world_cam, settings)
        pred, gt = comp.instance, b.instance
        ious = [((pred[j] == k) & (gt[j] == k)).sum().item() / ((pred[j] == k) | (gt[j] == k)).sum().item()
                for j in range(B) for k in range(1, int(b.obj_count[j]) + 1) if (gt[j] == k).sum() >= 25]
        fg_p, fg_g = pred > 0, gt > 0
        both = fg_p & fg_g
        err = (comp.depth[:, 0] - b.depth[:, 0])[both]
        return (both.sum() / (fg_p | fg_g).sum()).item(), np.asarray(ious), err.square().mean().sqrt().item()

    return fit


def scene_fit(setting: str, widths: list[int], out: Path, scenes: int, threads: int) -> dict[int, dict]:
    """What each prior can explain at the scenes' own resolution: the validation scenes of the setting's
    dataset (``data/NAME``, made from its meshes) rendered with their true poses and each object's own
    training code of the prior (12 samples per ray and 2 bisection steps, through the padded cube and
    through the prior's tight bounds); against the ground truth, the foreground IoU, the instance IoU per
    object (mean) and the depth RMSE on the pixels both call foreground. An upper bound for a scene model
    that uses this prior."""
    from prismonet.render import RenderSettings
    from prismonet.shapes.normalize import shape_bounds
    from prismonet.shapes.pretrain import load_shape_set
    from prismonet.shapes.prior import load_prior

    torch.set_num_threads(threads)
    fit = _true_pose_render(setting, scenes)
    bounds = shape_bounds(load_shape_set(setting).meshes)
    results = {}
    for w, box in [(w, box) for w in widths for box in ("cube", "bounds")]:
        prior = load_prior(out / run_name(setting, w) / "prior")
        settings = RenderSettings(refine_steps=2) if box == "cube" else RenderSettings(refine_steps=2, box=bounds)
        fg, ious, rmse = fit(prior, settings)
        key = "" if box == "cube" else "_bounds"
        results.setdefault(w, {}).update({f"fg_iou{key}": fg, f"instance_iou{key}": float(np.mean(ious)), f"depth_rmse_fg{key}": rmse})
    return results


def samples_reach(setting: str, widths: list[int], out: Path, scenes: int, samples: list[int], threads: int) -> str:
    """How many objects a scene model could find at AP0.5 at most, against the render's samples per ray:
    the true-pose render of ``scene_fit`` (2 bisection steps, the prior's tight box), the share of objects
    whose mask reaches IoU 0.5 with the truth, and their mean IoU. A table."""
    from prismonet.render import RenderSettings
    from prismonet.shapes.prior import load_prior

    torch.set_num_threads(threads)
    fit = _true_pose_render(setting, scenes)
    lines = [f"| {Path(setting).name}: width | " + " | ".join(f"{n} samples: IoU >= 0.5 (mean IoU)" for n in samples) + " |",
             "|---|" + "---|" * len(samples)]
    for w in widths:
        prior = load_prior(out / run_name(setting, w) / "prior")
        cells = []
        for n in samples:
            _, ious, _ = fit(prior, RenderSettings(refine_steps=2, samples=n, box=prior.bounds))
            cells.append(f"{(ious >= 0.5).mean():.3f} ({ious.mean():.3f})")
        lines.append(f"| {w} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def table(results: dict) -> str:
    head = ("| setting | width | parameters | pre-training s (1 thread) | Chamfer-L1 mean / median / max | "
            "IoU mean / median / min | empty meshes | scenes, padded cube: fg IoU / object IoU / fg depth RMSE | "
            "scenes, tight box | render step ms (8 × 3 objects, fwd + bwd, tight box) | × width 64 |")
    lines = [head, "|" + "---|" * 11]
    for setting, by_width in results.items():
        base = by_width.get("64", {}).get("render_ms_bounds")
        for w, r in sorted(by_width.items(), key=lambda kv: int(kv[0])):
            rows = r["per_shape"]
            cd = [x["chamfer_l1"] for x in rows if np.isfinite(x["chamfer_l1"])]
            iou = [x["iou"] for x in rows]
            empty = len(rows) - len(cd)
            ms = r.get("render_ms_bounds")
            ratio = f"{ms / base:.2f}×" if ms and base else "–"
            fit = (f"{r['fg_iou']:.3f} / {r['instance_iou']:.3f} / {r['depth_rmse_fg']:.3f}" if "fg_iou" in r else "–")
            fit += " | " + (f"{r['fg_iou_bounds']:.3f} / {r['instance_iou_bounds']:.3f} / {r['depth_rmse_fg_bounds']:.3f}"
                            if "fg_iou_bounds" in r else "–")
            lines.append(f"| {Path(setting).name} | {w} | {r['parameters']:,} | {r['train_seconds']:.0f} | "
                         f"{np.mean(cd):.4f} / {np.median(cd):.4f} / {np.max(cd):.4f} | "
                         f"{np.mean(iou):.3f} / {np.median(iou):.3f} / {np.min(iou):.3f} | {empty} of {len(rows)} | {fit} | "
                         f"{ms:.0f} | {ratio} |" if ms else
                         f"| {Path(setting).name} | {w} | {r['parameters']:,} | {r['train_seconds']:.0f} | "
                         f"{np.mean(cd):.4f} / {np.median(cd):.4f} / {np.max(cd):.4f} | "
                         f"{np.mean(iou):.3f} / {np.median(iou):.3f} / {np.min(iou):.3f} | {empty} of {len(rows)} | {fit} | – | – |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("settings", nargs="+", help="folders made by 'prismonet shapes import-furniture'")
    ap.add_argument("--widths", default="64,128,256")
    ap.add_argument("--out", default="runs/prior_sweep")
    ap.add_argument("--epochs", type=int, default=300)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--fit-scenes", type=int, default=64, help="validation scenes of data/SETTING for the scene fit")
    ap.add_argument("--table", action="store_true", help="print the table of what is done; train nothing")
    ap.add_argument("--samples", help="comma-separated samples per ray: print what the true-pose render reaches at each "
                                      "(the priors must exist); train nothing")
    args = ap.parse_args(argv)
    widths = [int(w) for w in args.widths.split(",")]
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    summary_path = out / "sweep.json"
    results = json.loads(summary_path.read_text()) if summary_path.is_file() else {}
    for setting in args.settings:
        if not (Path(setting) / "models.json").is_file():
            print(f"error: {setting} is not a folder made by 'prismonet shapes import-furniture'", file=sys.stderr)
            return 2
        by_width = results.setdefault(setting, {})
        if args.table:
            continue
        if args.samples:
            if _scenes_of(setting) is None:
                print(f"error: no scenes of {setting} (data/NAME or data/furniture_NAME)", file=sys.stderr)
                return 2
            print(samples_reach(setting, widths, out, args.fit_scenes, [int(n) for n in args.samples.split(",")], args.threads))
            continue
        for w in widths:
            report = pretrain_one(setting, w, out, args.epochs, args.threads)
            by_width[str(w)] = {**by_width.get(str(w), {}), **report}
        if any("render_ms_bounds" not in by_width[str(w)] for w in widths):
            for w, ms in render_step_ms(setting, widths, out, args.rounds, args.repeats, args.threads).items():
                by_width[str(w)]["render_ms_bounds"] = ms
        if _scenes_of(setting) is not None and any("fg_iou_bounds" not in by_width[str(w)] for w in widths):
            for w, fit in scene_fit(setting, widths, out, args.fit_scenes, args.threads).items():
                by_width[str(w)].update(fit)
        # merge into what is on disk now: another sweep process may have written other settings meanwhile
        on_disk = json.loads(summary_path.read_text()) if summary_path.is_file() else {}
        on_disk[setting] = by_width
        tmp = summary_path.with_name(f".sweep.json.{os.getpid()}.tmp")
        tmp.write_text(json.dumps(on_disk, indent=2))
        tmp.replace(summary_path)
        results.update(on_disk)
    if not args.samples:
        print(table({s: r for s, r in results.items() if s in args.settings}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
