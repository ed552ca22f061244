"""The ``prismonet`` command line: ``prismonet <command> [<subcommand>] ...``.

Every command reports a bad input as one line, ``prismonet: error: ...``, and exit status 2.
"""

from __future__ import annotations

import argparse
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


def cmd_demo(args) -> int:
    import shutil

    from prismonet.data.clevr import ClevrConfig
    from prismonet.data.dataset import SceneDataset
    from prismonet.data.generate import generate_clevr
    from prismonet.viz.contact_sheet import contact_sheet

    out = Path(args.out)
    data = out / "data"
    if (data / "meta.json").is_file():
        shutil.rmtree(data)  # the demo's own earlier output
    generate_clevr(data, ClevrConfig(num_objects=args.objects), split=(args.scenes, 0, 0), seed=args.seed, workers=1)
    ds = SceneDataset(data, split="train")
    sheet = contact_sheet(ds.numpy(range(len(ds))), out / "contact_sheet.png")
    print(f"dataset:       {data}  ({len(ds)} scenes, {args.objects} objects each)")
    print(f"contact sheet: {sheet}  (RGB | depth | instance masks)")
    return 0


def cmd_bench_data(args) -> int:
    from prismonet.bench.data import bench_data

    workers = [int(w) for w in args.workers.split(",")]
    print(bench_data(args.scenes, args.objects, workers, args.repeats))
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="prismonet", description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="command", required=True)

    demo = sub.add_parser("demo", help="the main job on embedded defaults")
    demo.add_argument("--out", default="outputs/demo", help="output folder (default: outputs/demo)")
    demo.add_argument("--scenes", type=int, default=8)
    demo.add_argument("--objects", type=int, default=3)
    demo.add_argument("--seed", type=int, default=0)
    demo.set_defaults(func=cmd_demo)

    data = sub.add_parser("data", help="datasets: generate, inspect, convert")
    dsub = data.add_subparsers(dest="data_command", required=True)

    clevr = dsub.add_parser("clevr", help="generate a CLEVR-style RGB-D dataset (packed format)")
    clevr.add_argument("--objects", type=int, default=3, help="objects per scene (paper: 2..5)")
    clevr.add_argument("--out", required=True, help="new or empty output folder")
    clevr.add_argument("--scenes", type=int, help="total scenes, split 72/8/20 %% (default: 9000,1000,2500)")
    clevr.add_argument("--split", type=_split, help="train,val,test counts, e.g. 9000,1000,2500")
    clevr.add_argument("--seed", type=int, default=0)
    clevr.add_argument("--size", type=int, default=64, help="image side in pixels")
    clevr.add_argument("--noisy-depth", action="store_true", help="depth noise sigma = 0.001 d^2")
    clevr.add_argument("--random-height", action="store_true", help="heights in [-1.5, 1.5], lowered ground")
    clevr.add_argument("--full-rotation", action="store_true", help="uniformly random 3-D rotations")
    clevr.add_argument("--camera-jitter", type=float, default=0.0, help="uniform per-axis camera jitter")
    clevr.add_argument("--workers", type=int, default=2, help="rendering processes")
    clevr.add_argument("--quiet", action="store_true", help="no progress bar")
    clevr.set_defaults(func=cmd_data_clevr)

    sheet = dsub.add_parser("sheet", help="contact-sheet PNG of a dataset's first scenes")
    sheet.add_argument("dataset")
    sheet.add_argument("--out", required=True)
    sheet.add_argument("--split", default="train")
    sheet.add_argument("--count", type=int, default=8)
    sheet.set_defaults(func=cmd_data_sheet)

    verify = dsub.add_parser("verify", help="check a packed dataset's files and checksums")
    verify.add_argument("dataset")
    verify.set_defaults(func=cmd_data_verify)

    to_folder = dsub.add_parser("to-folder", help="convert a packed split to the interchange folder format")
    to_folder.add_argument("dataset")
    to_folder.add_argument("out")
    to_folder.add_argument("--split", default="test")
    to_folder.add_argument("--count", type=int)
    to_folder.set_defaults(func=cmd_data_to_folder)

    bench = sub.add_parser("bench", help="benchmarks (timings to record in BENCHMARKS.md)")
    bsub = bench.add_subparsers(dest="bench_command", required=True)
    bdata = bsub.add_parser("data", help="dataset generation time per worker count")
    bdata.add_argument("--scenes", type=int, default=12500)
    bdata.add_argument("--objects", type=int, default=3)
    bdata.add_argument("--workers", default="1,2", help="comma-separated worker counts; the first is the baseline")
    bdata.add_argument("--repeats", type=int, default=3)
    bdata.set_defaults(func=cmd_bench_data)
    return p


def main(argv: list[str] | None = None) -> int:
    from prismonet.data.errors import DatasetError, OutputDirError, PlacementError

    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return args.func(args)
    except (DatasetError, OutputDirError, PlacementError, ValueError) as e:
        print(f"prismonet: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("prismonet: interrupted", file=sys.stderr)
        return 130
