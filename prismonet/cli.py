"""The ``prismonet`` command line: ``prismonet <command> [<subcommand>] ...``.

Every command reports a bad input as one line, ``prismonet: error: ...``, and exit status 2.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path


def _split(text: str) -> tuple[int, int, int]:
    try:
        parts = tuple(int(p) for p in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected three comma-separated counts like 9000,1000,2500, got {text!r}") from None
    if len(parts) != 3:
        raise argparse.ArgumentTypeError(f"expected three comma-separated counts, got {text!r}")
    return parts  # type: ignore[return-value]


def _scene_split(args) -> tuple[int, int, int]:
    from prismonet.data.generate import DEFAULT_SPLIT

    if args.split is not None:
        return args.split
    if args.scenes is None:
        return DEFAULT_SPLIT
    if args.scenes <= 0:
        raise ValueError(f"--scenes must be positive, got {args.scenes}")
    n = args.scenes
    train, val = round(n * 0.72), round(n * 0.08)
    return (train, val, n - train - val)


def cmd_data_clevr(args) -> int:
    from prismonet.data.clevr import ClevrConfig
    from prismonet.data.generate import generate_clevr

    cfg = ClevrConfig(
        num_objects=args.objects,
        image_size=args.size,
        depth_noise_eta=1e-3 if args.noisy_depth else 0.0,
        random_height=args.random_height,
        full_rotation=args.full_rotation,
        camera_jitter=args.camera_jitter,
    )
    meta = generate_clevr(args.out, cfg, split=_scene_split(args), seed=args.seed, workers=args.workers, progress=not args.quiet)
    n = sum(meta["counts"].values())
    print(f"wrote {n} scenes {meta['counts']} to {args.out} in {meta['seconds']:.1f} s ({n / meta['seconds']:.0f} scenes/s)")
    return 0


def cmd_data_sheet(args) -> int:
    from prismonet.data.dataset import SceneDataset
    from prismonet.viz.contact_sheet import contact_sheet

    ds = SceneDataset(args.dataset, split=args.split)
    n = min(args.count, len(ds))
    if n <= 0:
        raise ValueError(f"{args.dataset}: split {args.split!r} has no scenes")
    path = contact_sheet(ds.numpy(range(n)), args.out)
    print(f"wrote {path}")
    return 0


def cmd_data_verify(args) -> int:
    from prismonet.data import packed
    from prismonet.data.dataset import SceneDataset

    meta = packed.read_meta(Path(args.dataset))
    for split in meta["splits"]:
        ds = SceneDataset(args.dataset, split=split, verify=True)
        print(f"{split}: {len(ds)} scenes ok")
    return 0


def cmd_data_to_folder(args) -> int:
    from prismonet.data.dataset import SceneDataset
    from prismonet.data.folder import write_folder
    from prismonet.data.generate import check_output_dir

    ds = SceneDataset(args.dataset, split=args.split)
    check_output_dir(Path(args.out))
    n = len(ds) if args.count is None else min(args.count, len(ds))
    write_folder(Path(args.out), ds.numpy(range(n)))
    print(f"wrote {n} scenes to {args.out}")
    return 0


def cmd_data_subset(args) -> int:
    from prismonet.data.packed import write_subset

    if args.count <= 0:
        raise ValueError(f"--count must be positive, got {args.count}")
    write_subset(Path(args.dataset), args.split, range(args.count), Path(args.out))
    print(f"wrote the first {args.count} {args.split} scenes of {args.dataset} to {args.out}")
    return 0


def cmd_demo(args) -> int:
    import time

    from prismonet.demo import format_demo_table, run_demo

    t0 = time.perf_counter()
    result = run_demo(args.out, args.scenes, args.model, args.data, args.refine, progress=not args.quiet,
                      search_rounds=args.search, color_fit_steps=args.fit_color)
    print(format_demo_table(result))
    out = Path(args.out)
    print(f"\n{len(result['scenes'])} scenes decomposed by the {'shipped 3-object' if args.model == 'shipped' else args.model} model "
          f"in {time.perf_counter() - t0:.1f} s ({_demo_steps(result)})")
    print(f"figures:       {out}/scene_*.png  (input | reconstruction | depth target | depth | instances; each object alone)")
    print(f"latent scenes: {out}/scene_*.json  (prismonet export / edit / views take these)")
    print(f"metrics:       {out / 'metrics.json'}")
    return 0


def _demo_steps(result: dict) -> str:
    steps = [f"{result['search_rounds']} pose-search rounds" if result["search_rounds"] else "",
             f"{result['refine_steps']} refinement steps" if result["refine_steps"] else "",
             f"{result['color_fit_steps']} colour-fit steps" if result["color_fit_steps"] else ""]
    steps = [s for s in steps if s]
    return "encoder, then " + ", ".join(steps) if steps else "encoder only, as the paper"


def cmd_bench_data(args) -> int:
    from prismonet.bench.data import bench_data

    workers = [int(w) for w in args.workers.split(",")]
    print(bench_data(args.scenes, args.objects, workers, args.repeats))
    return 0


def cmd_shapes_pretrain(args) -> int:
    import json

    from prismonet.config import load_config
    from prismonet.shapes.evaluate import evaluate_prior
    from prismonet.shapes.pretrain import PretrainConfig, pretrain

    cfg = load_config(PretrainConfig, args.config, args.set)
    prior = pretrain(cfg, args.out, progress=not args.quiet)
    print(f"prior: {Path(args.out) / 'prior.safetensors'} (+ prior.json), {prior.info['train_seconds']:.0f} s of training")
    if not args.no_eval:
        report = evaluate_prior(prior, resolution=args.resolution, progress=not args.quiet)
        prior.info["quality"] = {k: v for k, v in report.items() if k != "per_shape"}
        prior.save(Path(args.out) / "prior")
        (Path(args.out) / "quality.json").write_text(json.dumps(report, indent=2))
        print(_quality_line(report))
    return 0


def _quality_line(r: dict) -> str:
    return (
        f"Chamfer-L1 mean {r['mean_chamfer_l1']:.4f} (max {r['max_chamfer_l1']:.4f}) at marching-cubes resolution "
        f"{r['resolution']}; IoU mean {r['mean_iou']:.4f} (min {r['min_iou']:.4f}) on a {r['iou_resolution']}^3 grid; "
        f"non-empty interpolations {r['interpolation_nonempty']:.0%}"
    )


def cmd_shapes_eval(args) -> int:
    import json

    from prismonet.shapes.evaluate import evaluate_prior
    from prismonet.shapes.prior import load_prior

    report = evaluate_prior(load_prior(args.prior), resolution=args.resolution, progress=not args.quiet)
    if args.json:
        Path(args.json).write_text(json.dumps(report, indent=2))
    for row in report["per_shape"]:
        print(f"  {row['shape']:<12} Chamfer-L1 {row['chamfer_l1']:.4f}  IoU {row['iou']:.4f}")
    print(_quality_line(report))
    return 0


def cmd_shapes_mesh(args) -> int:
    import torch

    from prismonet.shapes.mesh import extract_mesh
    from prismonet.shapes.prior import load_prior

    prior = load_prior(args.prior)
    if args.latent is not None:
        z = torch.tensor([float(v) for v in args.latent.split(",")])
    else:
        if not 0 <= args.shape < len(prior.latents):
            raise ValueError(f"--shape: expected 0..{len(prior.latents) - 1}, got {args.shape}")
        z = prior.latents[args.shape]
    mesh = extract_mesh(prior.decoder, z, args.resolution)
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    mesh.export(args.out)
    print(f"wrote {args.out} ({len(mesh.vertices)} vertices, {len(mesh.faces)} faces)")
    return 0


def cmd_bench_render(args) -> int:
    from prismonet.bench.render import format_table, plot, run_bench

    samples = [int(v) for v in args.samples.split(",")]
    refine = [int(v) for v in args.refine.split(",")]
    if args.batch <= 0 or args.repeats <= 0 or min(samples) < 2 or min(refine) < 0:
        raise ValueError("--batch and --repeats must be positive, --samples at least 2, --refine non-negative")
    rows, extra = run_bench(args.batch, args.objects, args.mlp_width, args.repeats, samples_list=samples, refine_list=refine)
    table = format_table(rows, extra, args.batch, args.objects, args.mlp_width)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "render.md").write_text(table + "\n")
    plot(rows, out / "render_time_vs_error.png")
    print(table)
    print(f"\nwrote {out / 'render.md'} and {out / 'render_time_vs_error.png'}")
    if args.update:
        _replace_section(Path(args.update), "render-bench", table)
        print(f"updated {args.update}")
    return 0


def _replace_section(path: Path, name: str, body: str) -> None:
    """Replace the text between ``<!-- name:start -->`` and ``<!-- name:end -->`` in a Markdown file."""
    start, end = f"<!-- {name}:start -->", f"<!-- {name}:end -->"
    text = path.read_text()
    if start not in text or end not in text:
        raise ValueError(f"{path}: no {start} ... {end} section to update")
    head, rest = text.split(start, 1)
    _, tail = rest.split(end, 1)
    path.write_text(f"{head}{start}\n{body}\n{end}{tail}")


def cmd_train(args) -> int:
    import json

    from prismonet.config import load_config
    from prismonet.model.trainer import TrainConfig, train

    cfg = load_config(TrainConfig, args.config, args.set)
    out = Path(args.out)
    summary = train(cfg, out, progress=not args.quiet)
    if summary.get("world_size", 1) == 1 or int(__import__("os").environ.get("RANK", "0")) == 0:
        print(json.dumps(summary))
        print(f"run folder: {out}  (model.safetensors + model.json, checkpoint.safetensors, tb/, images/, log.jsonl)")
    return 0


def cmd_evaluate(args) -> int:
    import json

    from prismonet.data.dataset import SceneDataset
    from prismonet.evaluation.evaluate import check_compatible, evaluate_model, format_steps, format_table
    from prismonet.model.io import load_model, training_loss_config
    from prismonet.model.refine import RefineConfig
    from prismonet.model.color_fit import ColorFitConfig
    from prismonet.model.search import SearchConfig

    model, info = load_model(args.checkpoint, num_slots=args.objects)
    ds = SceneDataset(args.data, split=args.split)
    check_compatible(model, info, ds, any_camera=args.any_camera)
    overrides = {"lr": args.refine_lr, "pose_lr_scale": args.refine_pose_lr_scale}
    refine_cfg = RefineConfig(args.refine, **{k: v for k, v in overrides.items() if v is not None})  # validates even with K = 0
    search_cfg = SearchConfig(rounds=args.search)
    color_cfg = ColorFitConfig(args.fit_color)
    results = evaluate_model(model, ds, batch_size=args.batch, num_slots=args.objects, limit=args.limit, progress=not args.quiet,
                             refine_cfg=refine_cfg, loss_cfg=training_loss_config(info), extra_slots=args.extra_slots,
                             search_cfg=search_cfg, color_cfg=color_cfg, use_depth=not args.search_color_only)
    trained = info.get("model", {}).get("num_slots", "?")
    print(format_table([(f"{trained}/{results['num_slots']}", results)]))
    print(f"({results['scenes']} scenes of {args.data} [{args.split}], {results['matched_objects']} matched objects, "
          f"{results['extra_slots']} extra slots, {results['search_rounds']} search rounds, {results['refine_steps']} refinement steps, "
          f"{results['color_fit_steps']} colour-fit steps, {1000 * results['seconds_per_scene']:.1f} ms per scene)")
    print("\nper encoder step:\n" + format_steps(results))
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=2))
        print(f"wrote {args.json}")
    return 0


def cmd_bench_train(args) -> int:
    from prismonet.bench.train import bench_train

    if args.steps <= 0 or args.batch <= 0:
        raise ValueError("--steps and --batch must be positive")
    r = bench_train(args.data, args.steps, args.batch, args.objects)
    print(f"training step (batch {args.batch}, 64x64, {args.objects} objects): median {r['step_ms']:.0f} ms "
          f"(min {r['step_ms_min']:.0f}, max {r['step_ms_max']:.0f}) over {r['steps']} steps = {r['steps_per_hour']:.0f} steps/hour")
    print(f"inference, one 64x64 scene: median {r['infer_ms']:.1f} ms")
    print(f"(median rendered object pixels per batch: {r['object_pixels_per_batch']})")
    return 0


def cmd_bench_search(args) -> int:
    from prismonet.bench.search import bench_search

    print(bench_search(args.batch, args.objects, args.repeats))
    return 0


def _board(args):
    from calibration.board import Charuco, Chessboard

    grid = Chessboard.parse(args.board, args.square)
    return Charuco(grid.cols, grid.rows, args.square, args.marker, args.dictionary) if args.charuco else grid


def cmd_calibrate_intrinsics(args) -> int:
    from calibration.intrinsics import calibrate_folder
    from calibration.storage import save_calibration

    cal = calibrate_folder(args.photos, _board(args), fix_aspect_ratio=args.fix_aspect)
    for p in cal.per_image:
        status = f"found, reprojection RMS {p['rms_px']:.3f} px" if p["found"] else "board NOT found (skipped)"
        print(f"  {p['image']}: {status}")
    K = cal.K
    print(f"fx {K[0, 0]:.2f}  fy {K[1, 1]:.2f}  cx {K[0, 2]:.2f}  cy {K[1, 2]:.2f}  RMS {cal.rms:.3f} px  "
          f"({sum(p['found'] for p in cal.per_image)} of {len(cal.per_image)} photos)")
    print(f"wrote {save_calibration(cal, args.out)}")
    return 0


def cmd_calibrate_ground(args) -> int:
    import cv2

    from calibration.ground import ground_pose
    from calibration.storage import load_calibration, save_calibration

    from prismonet.files import read_image

    cal, _ = load_calibration(args.camera)
    img = read_image(args.photo, cv2.IMREAD_GRAYSCALE)
    T, rms = ground_pose(img, cal.K, cal.dist, _board(args))
    print(f"camera height above the table {T[2, 3]:.3f}, reprojection RMS {rms:.3f} px")
    print(f"wrote {save_calibration(cal, args.out, T)} (with T_world_cam: z up, table at z = 0)")
    return 0


def _box_and_gain(args):
    """``--box x0,y0,w,h`` and ``--gain r,g,b`` of the real-photo commands."""
    try:
        box = tuple(int(v) for v in args.box.split(",")) if args.box else None
        gain = tuple(float(v) for v in args.gain.split(",")) if args.gain else None
    except ValueError:
        raise ValueError(f"--box takes four integers and --gain three numbers, got {args.box!r} and {args.gain!r}") from None
    if box is not None and len(box) != 4:
        raise ValueError(f"--box: expected x0,y0,width,height, got {args.box!r}")
    if gain is not None and len(gain) != 3:
        raise ValueError(f"--gain: expected r,g,b, got {args.gain!r}")
    if gain is not None and not all(math.isfinite(g) and g > 0 for g in gain):
        raise ValueError(f"--gain: expected three finite positive numbers, got {args.gain!r}")
    if (gain is not None) != (args.normalize == "manual"):
        raise ValueError("--gain and --normalize manual go together" if gain is not None else "--normalize manual needs --gain r,g,b")
    return box, gain


def cmd_real_prepare(args) -> int:
    from realdata.pipeline import prepare_photos

    box, gain = _box_and_gain(args)
    recs = prepare_photos(args.photos, args.out, args.size, args.camera, box, args.normalize, gain)
    for r in recs:
        g = r["color_mapping"]["gain"]
        print(f"  {r['photo']}: crop {r['crop_box']}, colour gain ({g[0]:.2f}, {g[1]:.2f}, {g[2]:.2f})")
    print(f"wrote {len(recs)} prepared photos to {args.out} (folder dataset: rgb/, annotations/, dataset.json)")
    return 0


def cmd_reconstruct(args) -> int:
    import torch

    from prismonet.data.dataset import SceneDataset
    from prismonet.evaluation.evaluate import check_compatible
    from prismonet.model.io import load_model, prior_fingerprint, training_loss_config
    from prismonet.model.refine import RefineConfig, refine
    from prismonet.model.color_fit import ColorFitConfig, fit_colors
    from prismonet.model.search import SearchConfig, search_latents
    from prismonet.model.select import check_extra_slots, decode_overcomplete
    from prismonet.scene import LatentScene
    from prismonet.viz.decomposition import decomposition_figure

    refine_cfg = RefineConfig(args.refine)
    search_cfg = SearchConfig(rounds=args.search)
    color_cfg = ColorFitConfig(args.fit_color)
    check_extra_slots(args.extra_slots)
    model, info = load_model(args.checkpoint, num_slots=args.objects)
    loss_cfg = training_loss_config(info)
    fp = prior_fingerprint(model.prior)
    ds = SceneDataset(args.data, split=args.split)
    H, W = ds.arrays["rgb"].shape[1:3]
    if (H, W) != (model.cfg.image_size, model.cfg.image_size):
        raise ValueError(f"{args.data}: images are {W}x{H} but the model expects {model.cfg.image_size}x{model.cfg.image_size}")
    check_compatible(model, info, ds, any_camera=args.any_camera)
    n = len(ds) if args.count is None else min(args.count, len(ds))
    out_dir = Path(args.out)
    has_depth = bool((ds.arrays["depth"][:n] > 0).any())
    with torch.no_grad():
        for s in range(0, n, 8):
            idx = list(range(s, min(s + 8, n)))
            b = ds.batch(idx)
            out = decode_overcomplete(model, b, args.objects, args.extra_slots, use_depth=has_depth,
                                      w_image=loss_cfg.w_image, w_depth=loss_cfg.w_depth)
            out = search_latents(model, out, b, search_cfg, use_depth=has_depth)
            if args.refine > 0:
                out = refine(model, out, b, loss_cfg, refine_cfg, use_depth=has_depth)
            out = fit_colors(model, out, b, color_cfg)
            for j, i in enumerate(idx):
                name = ds.names[i]
                fig = decomposition_figure(b.rgb, out, j, out_dir / f"{name}.png", b.depth if has_depth else None)
                LatentScene.from_output(out, b, j, fp).save(out_dir / f"{name}.json")
                print(f"  {fig}")
    print(f"wrote {n} figures and latent scenes to {out_dir}")
    return 0


def cmd_real_reconstruct(args) -> int:
    from realdata.reconstruct import reconstruct_photos

    box, gain = _box_and_gain(args)
    recs = reconstruct_photos(args.photos, args.out, args.model, args.camera, box, args.normalize, gain, args.objects,
                              args.min_pixels, args.format, refine_steps=args.refine, extra_slots=args.extra_slots,
                              search_rounds=args.search, color_fit_steps=args.fit_color, progress=not args.quiet)
    for r in recs:
        psnr = " -> ".join(f"{v:.1f}" for v in r["psnr"].values())
        print(f"  {r['photo']}: {r['objects_found']} objects found, PSNR {psnr} dB; {r['figure']}" + (f", {r['mesh']}" if r["mesh"] else ""))
    print(f"wrote figures, latent scenes, meshes and summary.json to {args.out}")
    return 0


def _add_board_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--board", default="9x6", help="inner corners COLSxROWS (default 9x6); with --charuco: squares")
    p.add_argument("--square", type=float, default=0.025, help="square side in world units")
    p.add_argument("--charuco", action="store_true", help="a ChArUco board (with --marker, --dictionary)")
    p.add_argument("--marker", type=float, default=0.03, help="ChArUco marker side")
    p.add_argument("--dictionary", default="DICT_4X4_50", help="ArUco dictionary name")


class _Parser(argparse.ArgumentParser):
    """argparse with the project's one-line errors: ``prismonet: error: ...``, exit status 2 (no usage block)."""

    def error(self, message: str):
        where = self.prog.removeprefix("prismonet").strip()
        self.exit(2, f"prismonet: error: {where + ': ' if where else ''}{message}\n")


def build_parser() -> argparse.ArgumentParser:
    from prismonet.files import MAX_IMAGE_SIDE, MAX_MESH_RESOLUTION, arg_float, arg_int

    p = _Parser(prog="prismonet", description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="command", required=True)

    demo = sub.add_parser("demo", help="the main job: the shipped model decomposes the shipped test scenes")
    demo.add_argument("--out", default="outputs/demo", help="output folder (default: outputs/demo)")
    demo.add_argument("--scenes", type=int, default=8, help="how many of the 16 shipped scenes")
    demo.add_argument("--model", default="shipped", help="run folder or model stem (default: the shipped 3-object model)")
    demo.add_argument("--data", help="a packed dataset with a test split instead of the shipped scenes")
    demo.add_argument("--refine", type=int, default=0, metavar="K", help="test-time refinement steps per scene")
    demo.add_argument("--search", type=int, default=3, metavar="R", help="search each slot's scale, position and yaw against the RGB-D for R rounds before any refinement (default 3; 0: the paper's feed-forward decoding)")
    demo.add_argument("--fit-color", type=int, default=50, metavar="K", help="fit texture latents and background colour to the image for K steps last, geometry held (default 50; 0: none)")
    demo.add_argument("--quiet", action="store_true")
    demo.set_defaults(func=cmd_demo, outputs=[("out", "dir")])

    data = sub.add_parser("data", help="datasets: generate, inspect, convert")
    dsub = data.add_subparsers(dest="data_command", required=True)

    clevr = dsub.add_parser("clevr", help="generate a CLEVR-style RGB-D dataset (packed format)")
    clevr.add_argument("--objects", type=int, default=3, help="objects per scene (paper: 2..5)")
    clevr.add_argument("--out", required=True, help="new or empty output folder")
    clevr.add_argument("--scenes", type=int, help="total scenes, split 72/8/20 %% (default: 9000,1000,2500)")
    clevr.add_argument("--split", type=_split, help="train,val,test counts, e.g. 9000,1000,2500")
    clevr.add_argument("--seed", type=int, default=0)
    clevr.add_argument("--size", type=arg_int(8, MAX_IMAGE_SIDE), default=64, help="image side in pixels")
    clevr.add_argument("--noisy-depth", action="store_true", help="depth noise sigma = 0.001 d^2")
    clevr.add_argument("--random-height", action="store_true", help="heights in [-1.5, 1.5], lowered ground")
    clevr.add_argument("--full-rotation", action="store_true", help="uniformly random 3-D rotations")
    clevr.add_argument("--camera-jitter", type=arg_float(0, 5), default=0.0, help="uniform per-axis camera jitter")
    clevr.add_argument("--workers", type=int, default=2, help="rendering processes")
    clevr.add_argument("--quiet", action="store_true", help="no progress bar")
    clevr.set_defaults(func=cmd_data_clevr, outputs=[("out", "new_dir")])

    sheet = dsub.add_parser("sheet", help="contact-sheet PNG of a dataset's first scenes")
    sheet.add_argument("dataset")
    sheet.add_argument("--out", required=True)
    sheet.add_argument("--split", default="train")
    sheet.add_argument("--count", type=arg_int(1, 1024), default=8)
    sheet.set_defaults(func=cmd_data_sheet, outputs=[("out", "image")])

    verify = dsub.add_parser("verify", help="check a packed dataset's files and checksums")
    verify.add_argument("dataset")
    verify.set_defaults(func=cmd_data_verify)

    to_folder = dsub.add_parser("to-folder", help="convert a packed split to the interchange folder format")
    to_folder.add_argument("dataset")
    to_folder.add_argument("out")
    to_folder.add_argument("--split", default="test")
    to_folder.add_argument("--count", type=arg_int(1))
    to_folder.set_defaults(func=cmd_data_to_folder, outputs=[("out", "new_dir")])

    subset = dsub.add_parser("subset", help="copy some scenes of a packed split into a new packed dataset")
    subset.add_argument("dataset")
    subset.add_argument("out")
    subset.add_argument("--split", default="test")
    subset.add_argument("--count", type=arg_int(1), default=16, help="the first N scenes")
    subset.set_defaults(func=cmd_data_subset, outputs=[("out", "new_dir")])

    tr = sub.add_parser("train", help="train the scene model from RGB-D (resumable; works under torchrun)")
    tr.add_argument("config", help="JSON file of TrainConfig fields (e.g. configs/clevr3.json)")
    tr.add_argument("--out", required=True, help="run folder; rerunning resumes from its checkpoint")
    tr.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override, e.g. loss.blur=false")
    tr.add_argument("--quiet", action="store_true")
    tr.set_defaults(func=cmd_train, outputs=[("out", "dir")])

    ev = sub.add_parser("evaluate", help="the paper's measures for a trained model on a dataset split")
    ev.add_argument("checkpoint", help="run folder, or model.safetensors / model.json")
    ev.add_argument("data", help="packed or folder dataset")
    ev.add_argument("--split", default="test")
    ev.add_argument("--objects", type=arg_int(1, 64), help="recurrent steps (object-count generalisation); default: as trained")
    ev.add_argument("--batch", type=int, default=16)
    ev.add_argument("--limit", type=int, help="evaluate only the first N scenes")
    ev.add_argument("--any-camera", action="store_true", help="evaluate scenes whose camera differs from training (measures then mean little)")
    ev.add_argument("--json", help="also write the results here")
    ev.add_argument("--extra-slots", type=int, default=0, metavar="E", help="decode E more encoder steps and keep the best-explaining slots (beyond the paper)")
    ev.add_argument("--search", type=int, default=0, metavar="R",
                    help="search each slot's scale, position and yaw against the RGB-D for R rounds before any refinement (beyond the paper; 3 is the measured setting)")
    ev.add_argument("--search-color-only", action="store_true", help="the extra-slot selection and the search read colour alone, as if the input had no depth (the paper's test-time input)")
    ev.add_argument("--fit-color", type=int, default=0, metavar="K", help="fit texture latents and background colour to the image for K steps last, geometry held (beyond the paper; 50 is the measured setting)")
    ev.add_argument("--refine", type=int, default=0, metavar="K", help="refine the latents for K gradient steps per scene (beyond the paper)")
    ev.add_argument("--refine-lr", type=float, help="Adam step of the latents during refinement (default: RefineConfig's, 0.01)")
    ev.add_argument("--refine-pose-lr-scale", type=float,
                    help="positions and rotations step this many times faster than --refine-lr (default: RefineConfig's, 3)")
    ev.add_argument("--quiet", action="store_true")
    ev.set_defaults(func=cmd_evaluate, outputs=[("json", "file")])

    rc = sub.add_parser("reconstruct", help="decompose scenes (synthetic or prepared real photos): a figure and the latent scene each")
    rc.add_argument("checkpoint", help="run folder, or model.safetensors / model.json")
    rc.add_argument("data", help="packed or folder dataset (e.g. the output of 'real prepare')")
    rc.add_argument("--out", required=True)
    rc.add_argument("--split", default="test")
    rc.add_argument("--count", type=arg_int(1), help="only the first N scenes")
    rc.add_argument("--objects", type=arg_int(1, 64), help="recurrent steps (default: as trained)")
    rc.add_argument("--any-camera", action="store_true", help="allow a camera that differs from training (real photos)")
    rc.add_argument("--extra-slots", type=int, default=0, metavar="E", help="decode E more encoder steps and keep the slots that best explain the RGB(-D)")
    rc.add_argument("--search", type=int, default=0, metavar="R", help="search each slot's scale, position and yaw for R rounds (against depth too, when the data has it)")
    rc.add_argument("--fit-color", type=int, default=0, metavar="K", help="fit texture latents and background colour to the image for K steps last, geometry held (beyond the paper; 50 is the measured setting)")
    rc.add_argument("--refine", type=int, default=0, metavar="K", help="refine the latents for K steps (against depth too, when the data has it)")
    rc.set_defaults(func=cmd_reconstruct, outputs=[("out", "dir")])

    shapes = sub.add_parser("shapes", help="the DeepSDF shape prior: pre-train, evaluate, extract meshes")
    ssub = shapes.add_subparsers(dest="shapes_command", required=True)
    pre = ssub.add_parser("pretrain", help="pre-train the auto-decoder on the Clevr shape set (resumable)")
    pre.add_argument("--out", required=True, help="run folder; rerunning resumes from its checkpoint")
    pre.add_argument("--config", help="JSON file with PretrainConfig fields")
    pre.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a field, e.g. decoder.width=128")
    pre.add_argument("--resolution", type=arg_int(8, MAX_MESH_RESOLUTION), default=64, help="marching-cubes resolution of the quality check")
    pre.add_argument("--no-eval", action="store_true")
    pre.add_argument("--quiet", action="store_true")
    pre.set_defaults(func=cmd_shapes_pretrain, outputs=[("out", "dir")])
    ev = ssub.add_parser("eval", help="Chamfer-L1 and IoU of a prior on its training shapes")
    ev.add_argument("prior", nargs="?", help="prior path stem (default: the shipped Clevr prior)")
    ev.add_argument("--resolution", type=arg_int(8, MAX_MESH_RESOLUTION), default=64)
    ev.add_argument("--json", help="also write the full report here")
    ev.add_argument("--quiet", action="store_true")
    ev.set_defaults(func=cmd_shapes_eval, outputs=[("json", "file")])
    me = ssub.add_parser("mesh", help="extract a mesh (PLY/OBJ/GLB by extension) for a training shape or latent")
    me.add_argument("--prior", help="prior path stem (default: the shipped Clevr prior)")
    me.add_argument("--shape", type=int, default=0, help="training shape index")
    me.add_argument("--latent", help="comma-separated latent instead of --shape")
    me.add_argument("--resolution", type=arg_int(8, MAX_MESH_RESOLUTION), default=64)
    me.add_argument("--out", required=True)
    me.set_defaults(func=cmd_shapes_mesh, outputs=[("out", "file")])

    from prismonet.model.distill_cli import add_parsers as add_distill_parsers
    from prismonet.scene.cli import add_parsers as add_scene_parsers

    add_scene_parsers(sub)
    add_distill_parsers(sub)

    cal = sub.add_parser("calibrate", help="camera calibration with OpenCV (intrinsics, ground plane)")
    csub = cal.add_subparsers(dest="calibrate_command", required=True)
    ci = csub.add_parser("intrinsics", help="intrinsics and distortion from chessboard photos")
    ci.add_argument("photos", nargs="+")
    _add_board_args(ci)
    ci.add_argument("--fix-aspect", action="store_true", help="fx = fy (as OpenCV's sample calibration)")
    ci.add_argument("--out", required=True, help="OpenCV FileStorage YAML")
    ci.set_defaults(func=cmd_calibrate_intrinsics, outputs=[("out", "file")])
    cg = csub.add_parser("ground", help="T_world_cam from one photo of the board lying on the table")
    cg.add_argument("photo")
    cg.add_argument("--camera", required=True, help="YAML from 'calibrate intrinsics'")
    _add_board_args(cg)
    cg.add_argument("--out", required=True)
    cg.set_defaults(func=cmd_calibrate_ground, outputs=[("out", "file")])

    real = sub.add_parser("real", help="real photos: prepare them for the model, and reconstruct them")
    rsub = real.add_subparsers(dest="real_command", required=True)
    rp = rsub.add_parser("prepare", help="undistort, crop, resize and colour-normalise photos")
    rp.add_argument("photos", nargs="+")
    rp.add_argument("--out", required=True)
    rp.add_argument("--size", type=arg_int(8, MAX_IMAGE_SIDE), default=64)
    rp.add_argument("--camera", help="calibration YAML (prismonet calibrate)")
    rp.add_argument("--box", help="crop x0,y0,width,height (default: automatic, around the table)")
    rp.add_argument("--normalize", default="auto", choices=["auto", "none", "manual"])
    rp.add_argument("--gain", help="manual colour gain r,g,b (with --normalize manual)")
    rp.set_defaults(func=cmd_real_prepare, outputs=[("out", "dir")])
    rr = rsub.add_parser("reconstruct", help="prepare photos and decompose them: figure, latent scene, mesh and object count each")
    rr.add_argument("photos", nargs="+")
    rr.add_argument("--out", required=True)
    rr.add_argument("--model", default="shipped", help="run folder or model stem (default: the shipped 3-object model)")
    rr.add_argument("--camera", help="calibration YAML; with a ground pose it replaces the assumed training camera")
    rr.add_argument("--box", help="crop x0,y0,width,height (default: automatic, around the table)")
    rr.add_argument("--normalize", default="auto", choices=["auto", "none", "manual"])
    rr.add_argument("--gain", help="manual colour gain r,g,b (with --normalize manual)")
    rr.add_argument("--objects", type=arg_int(1, 64), help="recurrent steps (default: as trained)")
    rr.add_argument("--min-pixels", type=arg_int(0, 1 << 24), default=25, help="visible pixels for an object to count as found")
    rr.add_argument("--format", default="ply", choices=["ply", "obj", "glb"], help="mesh format")
    rr.add_argument("--extra-slots", type=int, default=0, metavar="E", help="decode E more encoder steps and keep the slots that best explain each photo")
    rr.add_argument("--search", type=int, default=0, metavar="R", help="search each slot's scale, position and yaw against each photo for R rounds (colour only)")
    rr.add_argument("--fit-color", type=int, default=0, metavar="K", help="fit texture latents and background colour to the image for K steps last, geometry held (beyond the paper; 50 is the measured setting)")
    rr.add_argument("--refine", type=int, default=0, metavar="K", help="refine the latents against each photo for K steps (image term only)")
    rr.add_argument("--quiet", action="store_true")
    rr.set_defaults(func=cmd_real_reconstruct, outputs=[("out", "dir")])

    bench = sub.add_parser("bench", help="benchmarks (timings to record in BENCHMARKS.md)")
    bsub = bench.add_subparsers(dest="bench_command", required=True)
    bdata = bsub.add_parser("data", help="dataset generation time per worker count")
    bdata.add_argument("--scenes", type=int, default=12500)
    bdata.add_argument("--objects", type=int, default=3)
    bdata.add_argument("--workers", default="1,2", help="comma-separated worker counts; the first is the baseline")
    bdata.add_argument("--repeats", type=int, default=3)
    bdata.set_defaults(func=cmd_bench_data)
    btrain = bsub.add_parser("train", help="training-step and inference time of the scene model")
    btrain.add_argument("--data", help="dataset (default: 64 generated scenes)")
    btrain.add_argument("--steps", type=int, default=30)
    btrain.add_argument("--batch", type=int, default=8)
    btrain.add_argument("--objects", type=int, default=3)
    btrain.set_defaults(func=cmd_bench_train)
    bsearch = bsub.add_parser("search", help="chunked vs plain root search on ground-truth layouts")
    bsearch.add_argument("--batch", type=int, default=8)
    bsearch.add_argument("--objects", type=int, default=3)
    bsearch.add_argument("--repeats", type=int, default=12)
    bsearch.set_defaults(func=cmd_bench_search)
    brender = bsub.add_parser("render", help="renderer run time against depth error, fast path vs reference")
    brender.add_argument("--batch", type=int, default=8)
    brender.add_argument("--objects", type=int, default=3)
    brender.add_argument("--mlp-width", type=int, default=128)
    brender.add_argument("--samples", default="6,12,24,48")
    brender.add_argument("--refine", default="0,2,4", help="bisection steps to compare")
    brender.add_argument("--repeats", type=int, default=5)
    brender.add_argument("--out", default="benchmarks", help="folder for render.md and the PNG plot")
    brender.add_argument("--update", metavar="BENCHMARKS.md", help="also replace the render-bench section of this file")
    brender.set_defaults(func=cmd_bench_render, outputs=[("out", "dir")])
    return p


def _one_line(e: BaseException) -> str:
    """An error's message on one line (some library messages span several)."""
    return " ".join(str(e).split()) or type(e).__name__


def _remove_empty_tree(p: Path) -> None:
    """Remove ``p`` if it holds nothing but empty folders (never a file)."""
    if not p.is_dir():
        return
    for sub in sorted(p.rglob("*"), key=lambda q: len(q.parts), reverse=True):
        if sub.is_dir() and not any(sub.iterdir()):
            sub.rmdir()
    if not any(p.iterdir()):
        p.rmdir()


def _error(message: str) -> int:
    print(f"prismonet: error: {message}", file=sys.stderr)
    return 2


def main(argv: list[str] | None = None) -> int:
    from calibration.intrinsics import CalibrationError
    from realdata.io import PhotoError

    from prismonet.config import ConfigError
    from prismonet.data.errors import DatasetError, OutputDirError, PlacementError
    from prismonet.files import check_output, shown
    from prismonet.model.io import CheckpointError
    from prismonet.model.trainer import TrainingError
    from prismonet.shapes.normalize import MeshError

    if hasattr(sys.stdout, "reconfigure"):  # print paths that are not valid UTF-8 escaped, as stderr does
        sys.stdout.reconfigure(errors="backslashreplace")
    try:
        args = build_parser().parse_args(argv)
    except SystemExit as e:  # argparse: --help (0) or a bad argument (2, one line already printed)
        return e.code if isinstance(e.code, int) else 2
    new_dirs: list[Path] = []
    try:
        for dest, kind in getattr(args, "outputs", ()):  # every output path, before any work
            if getattr(args, dest, None) is not None:
                p = check_output(getattr(args, dest), kind)
                if kind in ("dir", "new_dir") and not p.exists():
                    new_dirs.append(p)
        rc = args.func(args)
        new_dirs = []
        return rc
    except (DatasetError, OutputDirError, PlacementError, MeshError, ConfigError, CheckpointError, TrainingError, CalibrationError, PhotoError,
            ValueError, FileNotFoundError) as e:
        return _error(_one_line(e))
    except OSError as e:  # a file system refusal the checks above could not foresee (full disk, a race)
        return _error(f"{shown(e.filename) + ': ' if e.filename else ''}{e.strerror or e}")
    except MemoryError:
        return _error("out of memory (a size or count too large for this machine?)")
    except KeyboardInterrupt:
        print("prismonet: interrupted", file=sys.stderr)
        return 130
    finally:
        for p in new_dirs:  # a command that failed leaves no empty output folders behind
            _remove_empty_tree(p)
