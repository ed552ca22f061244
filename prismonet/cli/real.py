"""``prismonet real``: photos of real tabletops: prepare them for the model (undistort, crop, resize,
colour-normalise), and reconstruct them (figure, latent scene, mesh and object count each)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from prismonet.cli.common import add_inference_args, check_finite_positive, floats, inference_config, ints

PRESETS = {
    "measured": {"tiles": 2, "tile_below": 120.0, "normalize": "flat", "gray_tint": "both", "gray_no_steps": True,
                 "reseed": 4, "reseed_replace": True, "reseed_cycles": 2, "search": 3, "fit_color": 50,
                 "search_scales": "0.8,0.9,1.1,1.25", "prune": True},
}
"""``real reconstruct|evaluate --preset NAME``: flag values set as one. ``measured`` is the photo setting every figure of
the labelled photos since session 86 was read with (EVALUATION.md): ``--tiles 2 --tile-below 120 --normalize flat
--gray-tint both --gray-no-steps --reseed 4 --reseed-replace --reseed-cycles 2 --search 3 --fit-color 50
--search-scales 0.8,0.9,1.1,1.25 --prune``."""


def preset_flags(name: str) -> str:
    """A preset as the command-line flags it stands for."""
    flags = []
    for dest, v in PRESETS[name].items():
        flag = "--" + dest.replace("_", "-")
        flags.append(flag if v is True else f"{flag} {v:g}" if isinstance(v, float) else f"{flag} {v}")
    return " ".join(flags)


def box_and_gain(args):
    """``--box x0,y0,w,h`` and ``--gain r,g,b``, checked (the gain goes with ``--normalize manual``)."""
    box = ints(args.box, 4, "--box (x0,y0,width,height)") if args.box else None
    gain = tuple(floats(args.gain, 3, "--gain (r,g,b)")) if args.gain else None
    if gain is not None:
        check_finite_positive(gain, "--gain", args.gain)
    if (gain is not None) != (args.normalize == "manual"):
        raise ValueError("--gain and --normalize manual go together" if gain is not None else "--normalize manual needs --gain r,g,b")
    return box, gain


def _tiling(args):
    """The ``--tile*`` options as a ``TileConfig`` (``None``: the whole region at once)."""
    from realdata.tiles import TileConfig

    if args.tiles == 1 and args.tile_size is None and args.tiles_fine is None and args.zoom_out is None:
        return None
    fine, zoom = args.tiles_fine, args.zoom_out
    return TileConfig(args.tiles, args.tile_overlap, args.tile_color, args.tile_size, args.tile_below, args.tile_psnr_below,
                      None if fine is None else fine[0], None if fine is None else fine[1],
                      None if zoom is None else zoom[0], None if zoom is None else zoom[1])


def _warn(recs: list[dict]) -> None:
    for r in recs:
        for w in r.get("warnings", []):
            print(f"prismonet: warning: {r['photo']}: {w}", file=sys.stderr)


def _placed(r: dict) -> str:
    if "world" not in r:
        return f"crop {r['crop_box']}"
    if r.get("own_camera"):
        return f"crop {r['crop_box']} with its own camera at {r['world']['metres_per_unit']:.4g} m per model unit ({r['world']['scale_source']})"
    return (f"rectified to the model's view at {r['world']['metres_per_unit']:.4g} m per model unit "
            f"({r['world']['scale_source']}), {r['coverage']:.0%} covered")


def cmd_prepare(args) -> int:
    from prismonet.model.io import load_model, training_camera
    from realdata.pipeline import prepare_photos

    box, gain = box_and_gain(args)
    model, info = load_model(args.model)
    recs = prepare_photos(args.photos, args.out, args.size, args.camera, box, args.normalize, gain,
                          view=training_camera(model, info), metres_per_unit=args.unit, own_camera=args.own_camera,
                          highlights=args.highlights, gray_tint=args.gray_tint)
    for r in recs:
        g = r["color_mapping"]["gain"]
        tint = f", greyscale: tinted ({r['gray_tint']})" if "gray_tint" in r else ""
        print(f"  {r['photo']}: {_placed(r)}, colour gain ({g[0]:.2f}, {g[1]:.2f}, {g[2]:.2f}){tint}")
    _warn(recs)
    print(f"wrote {len(recs)} prepared photos to {args.out} (folder dataset: rgb/, annotations/, dataset.json)")
    return 0


def cmd_reconstruct(args) -> int:
    from realdata.reconstruct import reconstruct_photos

    box, gain = box_and_gain(args)
    cfg = inference_config(args, has_depth=False)
    recs = reconstruct_photos(args.photos, args.out, args.model, args.camera, box, args.normalize, gain, args.objects,
                              args.min_pixels, args.format, inference=cfg, progress=not args.quiet, metres_per_unit=args.unit,
                              elevation=args.elevation, tiling=_tiling(args), highlights=args.highlights,
                              gray_tint=args.gray_tint, gray_inference=_gray_inference(args))
    for r in recs:
        psnr = " -> ".join(f"{v:.1f}" for v in r["psnr"].values())
        if "tiles" in r:
            print(f"  {r['photo']}: {r['objects_found']} objects found in {len(r['tiles'])} tiles (mean PSNR {psnr} dB); {r['figure']}, "
                  f"{r['scene']}" + (f", {r['mesh']}" if r["mesh"] else "") + f"; each tile's own outputs in {args.out}/tiles")
            continue
        print(f"  {r['photo']}: {r['objects_found']} objects found, PSNR {psnr} dB; {r['figure']}" + (f", {r['mesh']}" if r["mesh"] else ""))
        for obj in r["objects"]:
            if "position_table_m" in obj:
                x, y, z = obj["position_table_m"]
                print(f"      object {obj['slot']}: at ({x:.3f}, {y:.3f}, {z:.3f}) m on the table, half-size {obj['scale_m']:.3f} m")
    _warn(recs)
    write_settings(args, cfg)
    print(f"wrote figures, latent scenes, meshes, summary.json and settings.json to {args.out} (model {_name(args)}; "
          f"{cfg.describe()}{_gray_note(args)})")
    return 0


def cmd_evaluate(args) -> int:
    from realdata.evaluate import evaluate_photos, format_real_table, rescore

    if args.rescore:
        print(format_real_table(rescore(args.out, args.labels)))
        print(f"(the run in {args.out} measured again against {args.labels}; no model was run; {args.out}/real_evaluation.json)")
        return 0
    box, gain = box_and_gain(args)
    cfg = inference_config(args, has_depth=False)
    result = evaluate_photos(args.labels, args.out, args.model, args.camera, box, args.normalize, gain, args.objects,
                             args.min_pixels, inference=cfg, progress=not args.quiet, metres_per_unit=args.unit,
                             elevation=args.elevation, label_elevations=args.label_elevations, tiling=_tiling(args),
                             highlights=args.highlights, gray_tint=args.gray_tint, gray_inference=_gray_inference(args))
    write_settings(args, cfg)
    print(format_real_table(result))
    print(f"(model {_name(args)}; {cfg.describe()}{_gray_note(args)}; boxes from the model's instance masks mapped "
          "back to the photos; "
          f"figures, {args.out}/real_evaluation.json and settings.json)")
    return 0


NOT_SETTINGS = ("func", "outputs", "preset_parser", "presets", "quiet", "command", "real_command", "preset")
"""Parsed values ``settings.json`` leaves out of its ``flags``: the parser's plumbing, what only changes the terminal
output, and what it records on their own (the command, the preset)."""


def run_settings(args, cfg) -> dict:
    """What a photo run was asked: its command, the model's resolved name, the test-time steps, and every flag's value
    after the preset was applied (so a ``--preset`` run records the flags it stood for)."""
    flags = {k: v for k, v in vars(args).items() if k not in NOT_SETTINGS}
    return {"command": f"prismonet real {args.real_command}", "model": _name(args), "inference": cfg.describe(),
            "preset": args.preset, "flags": flags}


def write_settings(args, cfg) -> Path:
    """``run_settings`` as ``OUT/settings.json`` (written when the run has finished, atomically)."""
    from prismonet.files import write_atomic

    dest = Path(args.out) / "settings.json"
    write_atomic(dest, json.dumps(run_settings(args, cfg), indent=1, default=str))
    return dest


def _name(args) -> str:
    from prismonet.assets import model_name

    return model_name(args.model)


def _gray_inference(args):
    """``--gray-no-steps``: the encoder alone for the views ``--gray-tint`` changed (None: the same steps for every view)."""
    if not args.gray_no_steps:
        return None
    if args.gray_tint == "off":
        raise ValueError("--gray-no-steps reads the views that --gray-tint changed: give --gray-tint light or both")
    from prismonet.model.inference import InferenceConfig

    return InferenceConfig()


def _gray_note(args) -> str:
    preset = f"; preset {args.preset}" if args.preset else ""
    if args.gray_tint == "off":
        return preset
    return f"{preset}; greyscale photos tinted ({args.gray_tint})" + (" and read by the encoder alone" if args.gray_no_steps else "")


def _percentile(text: str) -> float | None:
    """``--highlights``: a percentile in (0, 100], or ``none``."""
    if text.strip().lower() == "none":
        return None
    try:
        v = float(text)
    except ValueError:
        v = float("nan")
    if not 0 < v <= 100:
        raise argparse.ArgumentTypeError(f"expected a percentile in (0, 100] or none, got {text!r}")
    return v


def _add_photo_args(p: argparse.ArgumentParser, photos: bool = True) -> None:
    from prismonet.assets import PHOTO_NAME
    from prismonet.files import arg_float

    if photos:
        p.add_argument("photos", nargs="+")
    p.add_argument("--out", required=True)
    p.add_argument("--model", default=PHOTO_NAME,
                   help=f"model name, run folder or stem (default: {PHOTO_NAME}, the real-tabletop model; 'shipped' is "
                        "the 3-object Clevr model, which does not decompose photos); with a ground calibration, "
                        "photos are rectified to a one-camera model's training view, or keep their own camera for a "
                        "camera-frame model")
    p.add_argument("--unit", type=arg_float(1e-6, 1e6, positive=True), metavar="METRES",
                   help="metres per model unit (with a ground calibration; default: derived so that the photo camera is as far "
                        "from the table point it looks at as the training camera)")
    p.add_argument("--box", help="crop x0,y0,width,height (default: automatic, around the table)")
    from realdata.color import HIGHLIGHT_PERCENTILE

    p.add_argument("--normalize", default="auto", choices=["auto", "flat", "none", "manual"],
                   help="auto: map the table colour onto the training ground's (where that gain would clip more than 1 %% of "
                        "the photo, as on a dark table, the brightness above the table's is compressed instead); flat: first "
                        "divide out the table's uneven light (a smooth field fitted to its pixels); none; manual (with --gain)")
    p.add_argument("--gain", help="manual colour gain r,g,b (with --normalize manual)")
    p.add_argument("--highlights", type=_percentile, default=HIGHLIGHT_PERCENTILE, metavar="PCT|none",
                   help=f"with auto or flat: the percentile of the photo's brightness that the tone curve lands on 1 "
                        f"(default {HIGHLIGHT_PERCENTILE:g}); none: the plain gain, which clips what it lifts beyond 1")
    from realdata.gray_tint import TINTS

    p.add_argument("--gray-tint", default="off", choices=TINTS,
                   help="a greyscale photo only: give what is lighter than the table a yellow hue (light), and what is darker "
                        "a blue one too (both), before the model reads it: the colour-trained model takes a hueless region "
                        "for the table (colour photos are unchanged; EVALUATION.md, session 85)")


def add_parsers(sub) -> None:
    from prismonet.files import MAX_IMAGE_SIDE, arg_int

    real = sub.add_parser("real", help="real photos: prepare them for the model, and reconstruct them")
    rsub = real.add_subparsers(dest="real_command", required=True)
    rp = rsub.add_parser("prepare", help="undistort, crop, resize and colour-normalise photos")
    _add_photo_args(rp)
    rp.add_argument("--size", type=arg_int(8, MAX_IMAGE_SIDE), default=64)
    rp.add_argument("--camera", help="calibration YAML (prismonet calibrate)")
    rp.add_argument("--own-camera", action="store_true",
                    help="with a ground pose: keep the photo's calibrated camera (crop and resize around the model's view) "
                         "instead of rectifying to the training view; what camera-frame models take (reconstruct does "
                         "this by itself for them)")
    rp.set_defaults(func=cmd_prepare, outputs=[("out", "dir")])

    rr = rsub.add_parser("reconstruct", help="prepare photos and decompose them: figure, latent scene, mesh and object count each")
    _add_photo_args(rr)
    _add_model_args(rr)
    rr.add_argument("--format", default="ply", choices=["ply", "obj", "glb"], help="mesh format")
    add_inference_args(rr, depth=False)
    rr.set_defaults(func=cmd_reconstruct, outputs=[("out", "dir")])

    re = rsub.add_parser("evaluate", help="reconstruct labelled photos and measure them: objects found, box AP0.5/AR0.5, foreground IoU")
    re.add_argument("labels", help="folder of photo labels (e.g. realdata/samples/labels)")
    _add_photo_args(re, photos=False)
    _add_model_args(re)
    re.add_argument("--label-elevations", action="store_true",
                    help="see each photo from its label's elevation_deg (by eye; models that take the camera as an input)")
    re.add_argument("--rescore", action="store_true",
                    help="run no model: measure the run already in --out again against these labels (e.g. after they changed)")
    add_inference_args(re, depth=False)
    re.set_defaults(func=cmd_evaluate, outputs=[("out", "dir")])


def _add_model_args(p: argparse.ArgumentParser) -> None:
    from prismonet.files import arg_float, arg_int

    p.add_argument("--camera", help="calibration YAML; with a ground pose the photos are rectified to the model's view")
    p.add_argument("--objects", type=arg_int(1, 64), help="recurrent steps (default: as trained)")
    p.add_argument("--min-pixels", type=arg_int(0, 1 << 24), default=25, help="visible pixels for an object to count as found")
    p.add_argument("--gray-no-steps", action="store_true",
                   help="with --gray-tint: read the greyscale (tinted) photos with the encoder alone, the colour ones with the "
                        "test-time steps given (the measured photo setting: EVALUATION.md, session 85)")
    p.add_argument("--elevation", type=arg_float(0.0, 89.0, positive=True), metavar="DEG",
                   help="uncalibrated photos: the camera's elevation above the table, by eye (about 80 from above); the "
                        "training camera is moved to it. Only models that take the camera as an input (e.g. a tabletop model); "
                        "a photo with a calibrated ground pose keeps its own camera (a warning says so)")
    p.add_argument("--tiles", type=arg_int(1, 16), default=1,
                   help="uncalibrated photos: read the table region as overlapping square tiles, this many along its shorter "
                        "side, each decoded as its own photo, and merge their objects (for photos with more or smaller objects "
                        "than the model's view holds; default 1: the whole region at once)")
    p.add_argument("--tile-overlap", type=arg_float(0.0, 0.9), default=0.25, metavar="FRACTION",
                   help="the part of a tile's side that neighbouring tiles share (default 0.25)")
    p.add_argument("--tile-color", choices=["region", "tile"], default="region",
                   help="read the colour mapping off the whole table region (default) or off each tile")
    p.add_argument("--tile-size", type=arg_float(0.0, 1e6, positive=True), metavar="PX",
                   help="size the tiles per photo: read it whole first, then zoom so that its objects' median size becomes PX "
                        "visible pixels of the model's view (instead of --tiles)")
    p.add_argument("--tile-below", type=arg_float(0.0, 1e6, positive=True), metavar="PX",
                   help="tile only the photos whose whole reading finds objects of a median size under PX visible pixels of the "
                        "model's view (or none); the rest keep the whole reading (default: tile every photo)")
    p.add_argument("--tile-psnr-below", type=arg_float(0.0, 1e3, positive=True), metavar="DB",
                   help="with --tile-below: also tile the photos whose whole reading's reconstruction is under DB PSNR (read "
                        "poorly, e.g. many small alike objects taken as a few blobs)")
    p.add_argument("--tiles-fine", nargs=2, type=arg_float(1.0, 1e6), metavar=("N", "PX"),
                   help="with --tile-below: read the photos whose whole reading finds objects of a median size under PX "
                        "visible pixels in N tiles across instead of --tiles")
    p.add_argument("--zoom-out", nargs=2, type=arg_float(1.0, 1e6), metavar=("Z", "PX"),
                   help="uncalibrated photos: read whole first, then zoomed out Z times those whose objects' median size is above "
                        "PX visible pixels of the model's view (a view Z times as wide, the rest filled with the colour of the view's "
                        "border): close-ups whose objects are larger than the model was trained on (measured, not chosen: "
                        "EVALUATION.md, session 86)")
    p.add_argument("--preset", choices=sorted(PRESETS),
                   help="set many flags at once; a flag given on the command line still wins (but one the preset switches on "
                        "stays on). measured: the setting of the labelled photos' figures (EVALUATION.md, session 86): "
                        + preset_flags("measured"))
    p.set_defaults(preset_parser=p, presets=PRESETS)
    p.add_argument("--quiet", action="store_true")
