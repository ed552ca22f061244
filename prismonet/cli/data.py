"""``prismonet data``: generate a Clevr-style RGB-D dataset, look at it, check it, convert it."""

from __future__ import annotations

import argparse
from pathlib import Path


def _split(text: str) -> tuple[int, int, int]:
    try:
        parts = tuple(int(p) for p in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected three comma-separated counts like 9000,1000,2500, got {text!r}") from None
    if len(parts) != 3:
        raise argparse.ArgumentTypeError(f"expected three comma-separated counts, got {text!r}")
    return parts  # type: ignore[return-value]


def _scale_range(text: str) -> tuple[float, float]:
    try:
        lo, hi = (float(p) for p in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected LO,HI like 0.3,0.65, got {text!r}") from None
    if not 0 < lo <= hi:
        raise argparse.ArgumentTypeError(f"expected 0 < LO <= HI, got {text!r}")
    return lo, hi


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


def _randomize(args):
    """``RandomizeConfig`` from ``--randomize`` and ``--randomize-range NAME=LO,HI`` (which implies it), or None."""
    from dataclasses import fields

    from prismonet.data.clevr import RandomizeConfig

    if not (args.randomize or args.randomize_range):
        return None
    ranges = {f.name for f in fields(RandomizeConfig) if isinstance(f.default, tuple)}
    over = {}
    for item in args.randomize_range or []:
        name, _, value = item.partition("=")
        parts = value.split(",")
        if name not in ranges or len(parts) != 2:
            raise ValueError(f"--randomize-range: expected NAME=LO,HI with NAME one of {', '.join(sorted(ranges))}, got {item!r}")
        try:
            over[name] = (float(parts[0]), float(parts[1]))
        except ValueError:
            raise ValueError(f"--randomize-range: {item!r}: LO and HI must be numbers") from None
    return RandomizeConfig(**over)


def _colors(text: str | None) -> tuple[int, ...]:
    """``--colors``: comma-separated colour names or ids of ``COLOR_RGB`` (default: CLEVR's eight)."""
    from prismonet.data.clevr import CLEVR_COLORS, COLOR_NAMES

    if text is None:
        return CLEVR_COLORS
    ids = []
    for item in text.split(","):
        item = item.strip().lower()
        if item.isdigit() and int(item) < len(COLOR_NAMES):
            ids.append(int(item))
        elif item in COLOR_NAMES:
            ids.append(COLOR_NAMES.index(item))
        elif item == "clevr":
            ids.extend(CLEVR_COLORS)
        else:
            raise ValueError(f"--colors: {item!r} is not a colour; expected names or ids of {', '.join(COLOR_NAMES)} (or 'clevr')")
    return tuple(dict.fromkeys(ids))


def cmd_clevr(args) -> int:
    from prismonet.data.clevr import ClevrConfig
    from prismonet.data.generate import generate_clevr

    cfg = ClevrConfig(colors=_colors(args.colors), num_objects=args.objects, min_objects=args.min_objects, area_half=args.area, image_size=args.size, depth_noise_eta=1e-3 if args.noisy_depth else 0.0,
                      random_height=args.random_height, full_rotation=args.full_rotation, camera_jitter=args.camera_jitter,
                      shapes=args.shapes, shape_split=args.shape_split, randomize=_randomize(args), cast_shadows=args.shadows)
    meta = generate_clevr(args.out, cfg, split=_scene_split(args), seed=args.seed, workers=args.workers, progress=not args.quiet)
    n = sum(meta["counts"].values())
    print(f"wrote {n} scenes {meta['counts']} to {args.out} in {meta['seconds']:.1f} s ({n / meta['seconds']:.0f} scenes/s)")
    return 0


BLOCK_SCALES = (0.3, 0.65)
"""Scales of the blocks of ``data towers --shapes``: a block's longest half-extent in world units."""


def cmd_towers(args) -> int:
    from dataclasses import replace

    from prismonet.data.clevr import BLOCK_TOWERS, CLEVR_COLORS
    from prismonet.data.generate import generate_clevr
    from prismonet.data.stacks import platforms
    from prismonet.shapes.library import CLEVR, shape_library

    if args.min_objects > args.objects:
        raise ValueError(f"--min-objects ({args.min_objects}) must not exceed --objects ({args.objects})")
    towers = replace(BLOCK_TOWERS.towers, max_towers=args.max_towers)
    cfg = replace(BLOCK_TOWERS, num_objects=args.objects, min_objects=args.min_objects, image_size=args.size, towers=towers,
                  area_half=BLOCK_TOWERS.area_half if args.max_towers == 1 else max(BLOCK_TOWERS.area_half, 0.6 * args.max_towers),
                  randomize=_randomize(args), cast_shadows=args.shadows)
    if args.shapes != CLEVR:  # stacked blocks of a block set (prismonet.data.stacks), in every CLEVR colour
        lib = shape_library(args.shapes)
        if lib.own_colors:
            raise ValueError(f"--shapes {args.shapes}: not a block set (its models keep their own colours); make one with "
                             "`prismonet shapes blocks --out FOLDER`")
        scales = BLOCK_SCALES if args.scale is None else args.scale
        towers = replace(towers, colors=CLEVR_COLORS, platform_share=args.platforms,
                         platform_scale=towers.platform_scale if args.platform_scale is None else args.platform_scale)
        cfg = replace(cfg, shapes=args.shapes, towers=towers, scale_range=scales,
                      area_half=args.area if args.area is not None else cfg.area_half)
        if args.platforms > 0 and not platforms(cfg):
            raise ValueError(f"--platforms: {args.shapes} has no wide, low block with a flat top to serve as a platform")
    else:
        if cfg.randomize is not None:
            raise ValueError("--randomize: only with --shapes (a block set); the cube towers keep Lerer et al.'s fixed camera and look")
        if args.area is not None:
            cfg = replace(cfg, area_half=args.area)
        if args.scale is not None:
            raise ValueError("--scale: only with --shapes (a block set); the cube towers keep one scale range")
        if args.platforms > 0 or args.platform_scale is not None:
            raise ValueError("--platforms / --platform-scale: only with --shapes (a block set); the cube towers have no platform")
    meta = generate_clevr(args.out, cfg, split=_scene_split(args), seed=args.seed, workers=args.workers, progress=not args.quiet)
    n = sum(meta["counts"].values())
    kind = "block-tower" if args.shapes == CLEVR else "stacked-block"
    print(f"wrote {n} {kind} scenes {meta['counts']} to {args.out} in {meta['seconds']:.1f} s")
    return 0


def cmd_sheet(args) -> int:
    from prismonet.data.dataset import SceneDataset
    from prismonet.viz.contact_sheet import contact_sheet

    ds = SceneDataset(args.dataset, split=args.split)
    n = min(args.count, len(ds))
    if n <= 0:
        raise ValueError(f"{args.dataset}: split {args.split!r} has no scenes")
    print(f"wrote {contact_sheet(ds.numpy(range(n)), args.out)}")
    return 0


def cmd_verify(args) -> int:
    from prismonet.data import packed
    from prismonet.data.dataset import SceneDataset

    for split in packed.read_meta(Path(args.dataset))["splits"]:
        ds = SceneDataset(args.dataset, split=split, verify=True)
        print(f"{split}: {len(ds)} scenes ok")
    return 0


def cmd_to_folder(args) -> int:
    from prismonet.data.dataset import SceneDataset
    from prismonet.data.folder import write_folder

    ds = SceneDataset(args.dataset, split=args.split)
    n = len(ds) if args.count is None else min(args.count, len(ds))
    write_folder(Path(args.out), ds.numpy(range(n)))
    print(f"wrote {n} scenes to {args.out}")
    return 0


def cmd_subset(args) -> int:
    from prismonet.data.packed import write_subset

    write_subset(Path(args.dataset), args.split, range(args.count), Path(args.out))
    print(f"wrote the first {args.count} {args.split} scenes of {args.dataset} to {args.out}")
    return 0


def cmd_join(args) -> int:
    from prismonet.data.packed import write_joined

    meta = write_joined(Path(args.dataset), Path(args.more), Path(args.out), args.count)
    print(f"wrote {args.out}: {meta['counts']['train']} training scenes ({meta['joined']['first_train']} of {args.dataset}, "
          f"then {meta['joined']['train_added']} of {args.more}); its other splits are {args.dataset}'s")
    return 0


def cmd_blender(args) -> int:
    from prismonet.data.blender import generate_blender

    meta = generate_blender(args.out, args.rung, scenes=args.scenes, seed=args.seed, first_index=args.first_index,
                            workers=args.workers, python=args.python, progress=not args.quiet)
    vs = meta["blender"]["vs_training_renderer"]
    print(f"wrote {args.scenes} rung-{args.rung} scenes to {args.out} in {meta['seconds']:.1f} s; against the training "
          f"renderer's images of the same scenes: PSNR {vs['PSNR']:.2f} dB, mean |difference| {vs['mean_abs']:.4f}")
    return 0


def _add_blender(dsub) -> None:
    from prismonet.files import arg_int

    p = dsub.add_parser("blender", help="the photoreal test ladder: the generator's test scenes rendered by Blender Cycles "
                                        "with CLEVR's assets (needs scripts/setup_blender.sh)")
    p.add_argument("--rung", choices=("a", "b", "c", "d"), required=True,
                   help="a: rubber, the training light, no shadows; b: + CLEVR's lights and shadows; c: + metal; "
                        "d: + ground colour and camera jitter")
    p.add_argument("--out", required=True, help="new or empty output folder (all scenes go in the test split)")
    p.add_argument("--scenes", type=arg_int(1, 100000), default=500)
    p.add_argument("--seed", type=int, default=0, help="the generator's seed (default 0, as 'data clevr')")
    p.add_argument("--first-index", type=arg_int(0), default=10000,
                   help="first scene index (default 10000: the default dataset's first test scene)")
    p.add_argument("--workers", type=arg_int(1, 64), default=1, help="Blender processes")
    p.add_argument("--python", help="a Python with bpy (default: $PRISMONET_BLENDER_PYTHON, then .venv-blender)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_blender, outputs=[("out", "new_dir")])


def _add_clevr(dsub) -> None:
    from prismonet.files import MAX_SLOTS, arg_float, arg_int

    p = dsub.add_parser("clevr", help="generate a CLEVR-style RGB-D dataset (packed format)")
    p.add_argument("--objects", type=arg_int(1, MAX_SLOTS), default=3, help="objects per scene (paper: 2..5); with --min-objects, the most")
    p.add_argument("--min-objects", type=arg_int(0, MAX_SLOTS), help="each scene draws its count uniformly from MIN..--objects")
    p.add_argument("--area", type=arg_float(0.1, 100, positive=True), default=1.5,
                   help="object centres in [-A, A]^2 (default 1.5, the paper's; the camera's focal length fits the area)")
    _common(p)
    p.add_argument("--noisy-depth", action="store_true", help="depth noise sigma = 0.001 d^2")
    p.add_argument("--random-height", action="store_true", help="heights in [-1.5, 1.5], lowered ground")
    p.add_argument("--full-rotation", action="store_true", help="uniformly random 3-D rotations")
    p.add_argument("--camera-jitter", type=arg_float(0, 5), default=0.0, help="uniform per-axis camera jitter")
    _look(p)
    p.add_argument("--shapes", default="clevr", help="'clevr' (default) or a folder made by 'shapes import-furniture': "
                                                     "its meshes, in their own colours")
    p.add_argument("--shape-split", choices=("seen", "unseen"), default="seen", help="which models of an imported folder")
    p.add_argument("--colors", metavar="C,C,...",
                   help="object colours drawn from, by name or id: CLEVR's gray, red, blue, green, brown, purple, cyan, yellow "
                        "(0-7, the default) and white, silver, black (8-10, for real tables); 'clevr' stands for the first eight")
    p.set_defaults(func=cmd_clevr, outputs=[("out", "new_dir")])


def _common(p) -> None:
    from prismonet.files import MAX_IMAGE_SIDE, arg_int

    p.add_argument("--out", required=True, help="new or empty output folder")
    p.add_argument("--scenes", type=int, help="total scenes, split 72/8/20 %% (default: 9000,1000,2500)")
    p.add_argument("--split", type=_split, help="train,val,test counts, e.g. 9000,1000,2500")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--size", type=arg_int(8, MAX_IMAGE_SIDE), default=64, help="image side in pixels")
    p.add_argument("--workers", type=int, default=2, help="rendering processes")
    p.add_argument("--quiet", action="store_true", help="no progress bar")


def _add_towers(dsub) -> None:
    from prismonet.files import arg_float, arg_int

    p = dsub.add_parser("towers", help="generate block-tower scenes (stacked cubes, Lerer et al.'s style, or stacked blocks "
                                       "of a block set; packed format)")
    p.add_argument("--objects", type=arg_int(1, 12), default=4, help="most blocks per scene (default 4)")
    p.add_argument("--min-objects", type=arg_int(1, 12), default=2, help="fewest blocks per scene (default 2)")
    p.add_argument("--max-towers", type=arg_int(1, 6), default=1, help="towers per scene, uniform in 1..N (default 1)")
    p.add_argument("--shapes", default="clevr", help="'clevr' (default: equal cubes) or a block set made by "
                                                     "'shapes blocks': stacks of its boxes, hexagonal prisms and wedges")
    p.add_argument("--area", type=arg_float(0.1, 100, positive=True), help="tower bases in [-A, A]^2 (default: by the tower count)")
    p.add_argument("--scale", type=_scale_range, help="with --shapes: the blocks' scales, uniform in LO,HI (default 0.3,0.65)")
    p.add_argument("--platforms", type=arg_float(0, 1), default=0.0,
                   help="with --shapes: the share of scenes built around a platform, a wide flat block carrying one or "
                        "two short stacks (default 0)")
    p.add_argument("--platform-scale", type=_scale_range, help="with --platforms: the platform's scale, uniform in LO,HI "
                                                                "(default 0.9,1.2)")
    _common(p)
    _look(p)
    p.set_defaults(func=cmd_towers, outputs=[("out", "new_dir")])


def _look(p) -> None:
    """Shadows and the randomised look (``RandomizeConfig``), shared by ``data clevr`` and ``data towers``."""
    p.add_argument("--shadows", action="store_true", help="objects cast soft shadows from the light (beyond the paper; "
                                                           "the same scenes as without)")
    p.add_argument("--randomize", action="store_true",
                   help="per scene: ground colour, light direction and ambient level, camera distance, elevation, heading, "
                        "look-at point and focal length (RandomizeConfig's ranges; for the real-tabletop model)")
    p.add_argument("--randomize-range", action="append", metavar="NAME=LO,HI",
                   help="another range for one of RandomizeConfig's draws, e.g. focal_scale=0.8,1.8 (repeatable; implies --randomize)")


def add_parsers(sub) -> None:
    from prismonet.files import arg_int

    data = sub.add_parser("data", help="datasets: generate, inspect, convert")
    dsub = data.add_subparsers(dest="data_command", required=True)
    _add_clevr(dsub)
    _add_towers(dsub)
    _add_blender(dsub)
    sheet = dsub.add_parser("sheet", help="contact-sheet PNG of a dataset's first scenes")
    sheet.add_argument("dataset")
    sheet.add_argument("--out", required=True)
    sheet.add_argument("--split", default="train")
    sheet.add_argument("--count", type=arg_int(1, 1024), default=8)
    sheet.set_defaults(func=cmd_sheet, outputs=[("out", "image")])

    verify = dsub.add_parser("verify", help="check a packed dataset's files and checksums")
    verify.add_argument("dataset")
    verify.set_defaults(func=cmd_verify)

    to_folder = dsub.add_parser("to-folder", help="convert a packed split to the interchange folder format")
    to_folder.add_argument("dataset")
    to_folder.add_argument("out")
    to_folder.add_argument("--split", default="test")
    to_folder.add_argument("--count", type=arg_int(1))
    to_folder.set_defaults(func=cmd_to_folder, outputs=[("out", "new_dir")])

    subset = dsub.add_parser("subset", help="copy some scenes of a packed split into a new packed dataset")
    subset.add_argument("dataset")
    subset.add_argument("out")
    subset.add_argument("--split", default="test")
    subset.add_argument("--count", type=arg_int(1), default=16, help="the first N scenes")
    subset.set_defaults(func=cmd_subset, outputs=[("out", "new_dir")])

    join = dsub.add_parser("join", help="a packed dataset whose training split is DATASET's followed by MORE's (other splits: "
                                        "DATASET's), e.g. more training scenes for distillation targets of DATASET")
    join.add_argument("dataset")
    join.add_argument("more", help="a packed dataset from the same generator settings and another seed")
    join.add_argument("out")
    join.add_argument("--count", type=arg_int(1), default=None, help="the first N training scenes of MORE (default all)")
    join.set_defaults(func=cmd_join, outputs=[("out", "new_dir")])
