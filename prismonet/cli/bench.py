"""``prismonet bench``: timings to record in BENCHMARKS.md (commands, never timed tests)."""

from __future__ import annotations

from pathlib import Path

from prismonet.cli.common import int_list, replace_section


def cmd_data(args) -> int:
    from prismonet.bench.data import bench_data

    print(bench_data(args.scenes, args.objects, int_list(args.workers, "--workers", 1), args.repeats))
    return 0


def cmd_train(args) -> int:
    from prismonet.bench.train import bench_train

    r = bench_train(args.data, args.steps, args.batch, args.objects)
    print(f"training step (batch {args.batch}, 64x64, {args.objects} objects): median {r['step_ms']:.0f} ms "
          f"(min {r['step_ms_min']:.0f}, max {r['step_ms_max']:.0f}) over {r['steps']} steps = {r['steps_per_hour']:.0f} steps/hour")
    print(f"inference, one 64x64 scene: median {r['infer_ms']:.1f} ms")
    print(f"(median rendered object pixels per batch: {r['object_pixels_per_batch']})")
    return 0


def cmd_search(args) -> int:
    from prismonet.bench.search import bench_search

    print(bench_search(args.batch, args.objects, args.repeats))
    return 0


def cmd_render(args) -> int:
    from prismonet.bench.render import format_table, plot, run_bench

    samples, refine = int_list(args.samples, "--samples", 2), int_list(args.refine, "--refine", 0)
    rows, extra = run_bench(args.batch, args.objects, args.mlp_width, args.repeats, samples_list=samples, refine_list=refine)
    table = format_table(rows, extra, args.batch, args.objects, args.mlp_width)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "render.md").write_text(table + "\n")
    plot(rows, out / "render_time_vs_error.png")
    print(table)
    print(f"\nwrote {out / 'render.md'} and {out / 'render_time_vs_error.png'}")
    if args.update:
        replace_section(Path(args.update), "render-bench", table)
        print(f"updated {args.update}")
    return 0


def cmd_stopping(args) -> int:
    from prismonet.bench.stopping import bench_stopping, format_rows
    from prismonet.data.dataset import SceneDataset
    from prismonet.model.io import load_model

    model, _ = load_model(args.model)
    ds = SceneDataset(args.data, split=args.split)
    rows = bench_stopping(model, ds, args.per_count, args.repeats, use_depth=not args.color_only, progress=not args.quiet)
    print(format_rows(rows, model.cfg.num_slots))
    return 0


def add_parsers(sub) -> None:
    from prismonet.files import MAX_SLOTS, arg_int

    bench = sub.add_parser("bench", help="benchmarks (timings to record in BENCHMARKS.md)")
    bsub = bench.add_subparsers(dest="bench_command", required=True)
    objects = dict(type=arg_int(1, MAX_SLOTS), default=3)
    bdata = bsub.add_parser("data", help="dataset generation time per worker count")
    bdata.add_argument("--scenes", type=arg_int(1), default=12500)
    bdata.add_argument("--objects", **objects)
    bdata.add_argument("--workers", default="1,2", help="comma-separated worker counts; the first is the baseline")
    bdata.add_argument("--repeats", type=arg_int(1), default=3)
    bdata.set_defaults(func=cmd_data)
    btrain = bsub.add_parser("train", help="training-step and inference time of the scene model")
    btrain.add_argument("--data", help="dataset (default: 64 generated scenes)")
    btrain.add_argument("--steps", type=arg_int(1), default=30)
    btrain.add_argument("--batch", type=arg_int(1, 4096), default=8)
    btrain.add_argument("--objects", **objects)
    btrain.set_defaults(func=cmd_train)
    bsearch = bsub.add_parser("search", help="chunked vs plain root search on ground-truth layouts")
    bsearch.add_argument("--batch", type=arg_int(1, 4096), default=8)
    bsearch.add_argument("--objects", **objects)
    bsearch.add_argument("--repeats", type=arg_int(1), default=12)
    bsearch.set_defaults(func=cmd_search)
    bstop = bsub.add_parser("stopping", help="inference time per scene against its object count, with and without the stop rule")
    bstop.add_argument("model", help="run folder or model stem")
    bstop.add_argument("data", help="dataset with varying object counts (e.g. data clevr --min-objects 1)")
    bstop.add_argument("--split", default="test")
    bstop.add_argument("--per-count", type=arg_int(1), default=8, help="scenes per object count")
    bstop.add_argument("--repeats", type=arg_int(1), default=3, help="timings per scene and way (median)")
    bstop.add_argument("--color-only", action="store_true", help="the stop rule reads colour alone")
    bstop.add_argument("--quiet", action="store_true")
    bstop.set_defaults(func=cmd_stopping)
    brender = bsub.add_parser("render", help="renderer run time against depth error, fast path vs reference")
    brender.add_argument("--batch", type=arg_int(1, 4096), default=8)
    brender.add_argument("--objects", **objects)
    brender.add_argument("--mlp-width", type=arg_int(1, 4096), default=128)
    brender.add_argument("--samples", default="6,12,24,48")
    brender.add_argument("--refine", default="0,2,4", help="bisection steps to compare")
    brender.add_argument("--repeats", type=arg_int(1), default=5)
    brender.add_argument("--out", default="benchmarks", help="folder for render.md and the PNG plot")
    brender.add_argument("--update", metavar="BENCHMARKS.md", help="also replace the render-bench section of this file")
    brender.set_defaults(func=cmd_render, outputs=[("out", "dir"), ("update", "file")])
