"""What the command modules share: the one-line-error parser, the test-time step flags (one set for
every command that decodes scenes), and small argument parsers."""

from __future__ import annotations

import argparse
import math
from pathlib import Path


class Parser(argparse.ArgumentParser):
    """argparse with the project's one-line errors: ``prismonet: error: ...``, exit status 2 (no usage block)."""

    def error(self, message: str):
        where = self.prog.removeprefix("prismonet").strip()
        self.exit(2, f"prismonet: error: {where + ': ' if where else ''}{message}\n")


def add_inference_args(p: argparse.ArgumentParser, search: int = 0, fit_color: int = 0, depth: bool = True,
                       shape_trials: bool | None = False) -> None:
    """The flags of ``prismonet.model.inference.InferenceConfig``, with this command's defaults (``shape_trials`` ``None``:
    the command decides by the model, as ``prismonet.demo.run_demo`` does).

    ``depth``: whether the command's input can have depth (then ``--color-only`` is offered)."""
    g = p.add_argument_group("test-time steps after the encoder (beyond the paper; all 0: its feed-forward decoding)")
    g.add_argument("--extra-slots", type=int, default=0, metavar="E",
                   help="decode E more encoder steps and keep the slots that best explain the input")
    g.add_argument("--stop", action="store_true",
                   help="stop the encoder once the slots found explain the input; the slots left cost nothing (up to --objects slots)")
    g.add_argument("--reseed", type=int, default=0, metavar="R",
                   help="before the search, move idle slots onto the largest parts of the input that no slot explains, "
                        "up to R per scene (default 0)")
    g.add_argument("--reseed-cycles", type=int, default=1, metavar="C",
                   help="with --search: re-seed, then search, C times (default 1)")
    g.add_argument("--reseed-grow", type=int, default=0, metavar="G",
                   help="add G empty slots to the model's before re-seeding, for scenes with more objects than slots (default 0)")
    g.add_argument("--reseed-on-objects", action="store_true",
                   help="with --reseed: also try each proposal resting on the object surface under it, not only on the ground "
                        "(for stacked objects)")
    g.add_argument("--reseed-replace", action="store_true",
                   help="with --reseed: a scene with no idle slot left tries each proposal with the slot that explains the "
                        "fewest pixels alone, kept only where the scene then fits better")
    g.add_argument("--search", type=int, default=search, metavar="R",
                   help=f"search each slot's scale, position and yaw for R rounds (default {search}; 3 is the measured setting)")
    g.add_argument("--search-scales", metavar="S,S,...",
                   help="the search's trial scales, relative to each slot's (default 0.9,1.1,1.2,1.3,1.45: set for the "
                        "3-object model, whose last step under-scales; symmetric ones suit a model that does not)")
    g.add_argument("--search-far-clip", action="store_true",
                   help="score the search's trials with the render's depth clipped at the model's far depth, like the sensor's")
    g.add_argument("--search-coarse", type=int, default=0, metavar="C",
                   help="run the search's first C rounds at half the image size (a quarter of the rays; default 0)")
    g.add_argument("--search-grid", type=int, default=None, metavar="G",
                   help="render the search's trials from each slot's shape tabulated at G^3 points instead of the MLP "
                        "(the result is rendered with the MLP; with the shape trials one more pass with the MLP follows; "
                        "default: the MLP throughout, except in the demo's shape trials for the 3-object model, 24)")
    g.add_argument("--search-shapes", type=int, default=0, metavar="N",
                   help="in the search's first round, also try each slot's N nearest training shapes of the prior (default 0)")
    by_default = ("on for the Clevr models of 2-5 objects, where it was measured, else off" if shape_trials is None
                  else "on" if shape_trials else "off")
    g.add_argument("--shape-trials", action=argparse.BooleanOptionalAction, default=shape_trials,
                   help="with --search 3 or more: in the third pass try every shape of the prior at each slot's footprint "
                        f"(draws cubes as cubes; about 4x the search's time; default: {by_default})")
    g.add_argument("--search-set", action="append", default=[], metavar="FIELD=VALUE",
                   help="any other setting of the search (SearchConfig), as JSON, e.g. shape_trials=true or "
                        "shape_yaws=[30,60] (repeatable; applied after the flags above)")
    g.add_argument("--refine", type=int, default=0, metavar="K", help="refine all latents for K gradient steps against the training losses")
    g.add_argument("--refine-lr", type=float, help="Adam step of the latents during refinement (default 0.01)")
    g.add_argument("--refine-pose-lr-scale", type=float, help="positions and rotations step this many times faster (default 3)")
    g.add_argument("--fit-color", type=int, default=fit_color, metavar="K",
                   help=f"fit texture latents and background colour to the image for K steps last, geometry held "
                        f"(default {fit_color}; 50 is the measured setting)")
    g.add_argument("--prune", action="store_true",
                   help="last, drop the slots that explain nothing (fewer than 10 pixels of the input that the other slots do not)")
    if depth:
        g.add_argument("--color-only", "--search-color-only", dest="color_only", action="store_true",
                       help="every step reads colour alone, as if the input had no depth (the paper's test-time input)")


def inference_config(args, has_depth: bool = True):
    """The ``InferenceConfig`` of ``add_inference_args``'s flags (validated); depth is read only
    when the input has it and ``--color-only`` is not given."""
    from prismonet.model.inference import InferenceConfig

    return InferenceConfig.of(args.extra_slots, args.search, args.refine, args.fit_color,
                              use_depth=has_depth and not getattr(args, "color_only", False),
                              refine_lr=args.refine_lr, refine_pose_lr_scale=args.refine_pose_lr_scale,
                              stop=getattr(args, "stop", False), prune=getattr(args, "prune", False),
                              search_scales=None if args.search_scales is None else floats(args.search_scales, None, "--search-scales"),
                              search_far_clip=getattr(args, "search_far_clip", False),
                              search_coarse=getattr(args, "search_coarse", 0),
                              search_grid=getattr(args, "search_grid", None),
                              search_shapes=getattr(args, "search_shapes", 0),
                              reseed=getattr(args, "reseed", 0), reseed_cycles=getattr(args, "reseed_cycles", 1),
                              reseed_grow=getattr(args, "reseed_grow", 0), search_set=getattr(args, "search_set", None),
                              shape_trials=bool(getattr(args, "shape_trials", False)),
                              reseed_on_objects=getattr(args, "reseed_on_objects", False),
                              reseed_replace=getattr(args, "reseed_replace", False))


def ints(text: str, n: int, what: str) -> tuple[int, ...]:
    """``"a,b,c"`` -> n integers, or one line naming the flag."""
    try:
        vals = tuple(int(v) for v in text.split(","))
    except ValueError:
        vals = ()
    if len(vals) != n:
        raise ValueError(f"{what}: expected {n} comma-separated integers, got {text!r}")
    return vals


def floats(text: str, n: int | None, what: str) -> list[float]:
    """``"a,b,c"`` -> n numbers (``None``: one or more, each finite), or one line naming the flag."""
    import math

    try:
        vals = [float(v) for v in text.split(",")]
    except ValueError:
        vals = []
    if n is None:
        if not vals or not all(math.isfinite(v) for v in vals):
            raise ValueError(f"{what}: expected comma-separated finite numbers, got {text!r}")
    elif len(vals) != n:
        raise ValueError(f"{what}: expected {n} comma-separated numbers, got {text!r}")
    return vals


def int_list(text: str, what: str, low: int = 0) -> list[int]:
    """``"1,2"`` -> ``[1, 2]``, each at least ``low``."""
    try:
        vals = [int(v) for v in text.split(",")]
    except ValueError:
        vals = []
    if not vals or min(vals) < low:
        raise ValueError(f"{what}: expected comma-separated integers >= {low}, got {text!r}")
    return vals


def replace_section(path: Path, name: str, body: str) -> None:
    """Replace the text between ``<!-- name:start -->`` and ``<!-- name:end -->`` in a Markdown file."""
    start, end = f"<!-- {name}:start -->", f"<!-- {name}:end -->"
    text = path.read_text()
    if start not in text or end not in text:
        raise ValueError(f"{path}: no {start} ... {end} section to update")
    head, rest = text.split(start, 1)
    _, tail = rest.split(end, 1)
    path.write_text(f"{head}{start}\n{body}\n{end}{tail}")


def check_finite_positive(values, what: str, text: str) -> None:
    if not all(math.isfinite(v) and v > 0 for v in values):
        raise ValueError(f"{what}: expected finite positive numbers, got {text!r}")
