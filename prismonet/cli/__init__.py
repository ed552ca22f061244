"""The ``prismonet`` command line: ``prismonet <command> [<subcommand>] ...``, one module per stage of
the pipeline, each building its own sub-parser:

========================  =====================================================================
``cli.data``              ``data clevr | sheet | verify | to-folder | subset``
``cli.shapes``            ``shapes pretrain | eval | mesh`` (the DeepSDF prior)
``cli.train``             ``train``, ``distill``, ``refiner``, ``color-step``
``cli.evaluate``          ``demo``, ``evaluate``, ``reconstruct``
``cli.scene``             ``export``, ``edit``, ``views``
``cli.calibrate``         ``calibrate intrinsics | ground``
``cli.real``              ``real prepare | reconstruct | evaluate``
``cli.baselines``         ``baselines train | evaluate`` (the paper's 2-D baselines)
``cli.bench``             ``bench data | train | search | render``
========================  =====================================================================

Every command runs with freed memory kept for reuse (``prismonet.allocator``; ``PRISMONET_MALLOC=default`` turns it
off). Run from the command line, every command first takes only the cores other processes leave free
(``prismonet.threads.use_free_cores``; ``PRISMONET_THREADS=N`` or ``OMP_NUM_THREADS`` choose instead); ``distill`` measures again before
each chunk (``threads.follow_load``). Every command reports a bad
input as one line, ``prismonet: error: ...``, and exit status 2: output
paths are checked before any work (each sub-parser declares them as ``outputs``), the library's
typed errors become that line here, and a command that fails leaves no empty output folder behind.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from prismonet.cli import baselines, bench, calibrate, data, evaluate, real, scene, shapes, train
from prismonet.cli.common import Parser

STAGES = (evaluate, data, shapes, train, scene, calibrate, real, baselines, bench)
"""Sub-parser modules, in the order ``prismonet --help`` lists their commands (the demo first)."""


def build_parser() -> argparse.ArgumentParser:
    p = Parser(prog="prismonet", description="PriSMONet: objects, their 3-D shapes, poses and colours from one RGB(-D) image")
    sub = p.add_subparsers(dest="command", required=True)
    for stage in STAGES:
        stage.add_parsers(sub)
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


def _checked_outputs(args) -> list[Path]:
    """Check every output path the command declared, before any work; returns the folders it will create."""
    from prismonet.files import check_output

    new_dirs = []
    for dest, kind in getattr(args, "outputs", ()):
        if getattr(args, dest, None) is not None:
            p = check_output(getattr(args, dest), kind)
            if kind in ("dir", "new_dir") and not p.exists():
                new_dirs.append(p)
    return new_dirs


def _parse(argv: list[str] | None):
    """``(args, None)``, or ``(None, exit status)`` for ``--help`` (0) and a bad argument (2, one line printed).

    A command with ``--preset NAME`` (its sub-parser's defaults hold ``preset_parser`` and ``presets``) is parsed twice:
    the preset's values become that sub-parser's defaults, so the flags given on the command line still win."""
    try:
        parser = build_parser()
        args = parser.parse_args(argv)
        if getattr(args, "preset", None):
            args.preset_parser.set_defaults(**args.presets[args.preset])
            args = parser.parse_args(argv)
        return args, None
    except SystemExit as e:
        return None, e.code if isinstance(e.code, int) else 2


def main(argv: list[str] | None = None) -> int:
    from calibration.intrinsics import CalibrationError
    from prismonet.allocator import keep_freed_memory
    from prismonet.config import ConfigError
    from prismonet.data.errors import DatasetError, OutputDirError, PlacementError
    from prismonet.files import shown
    from prismonet.model.io import CheckpointError
    from prismonet.model.trainer import TrainingError
    from prismonet.shapes.normalize import MeshError
    from prismonet.threads import use_free_cores
    from realdata.io import PhotoError

    if hasattr(sys.stdout, "reconfigure"):  # print paths that are not valid UTF-8 escaped, as stderr does
        sys.stdout.reconfigure(errors="backslashreplace")
    args, status = _parse(argv)
    if args is None:
        return status
    new_dirs: list[Path] = []
    try:
        if argv is None:  # the command line (a caller passing argv, e.g. a test, keeps its own threads)
            use_free_cores()
        keep_freed_memory()  # every command: no page faults for buffers a loop frees and allocates again
        new_dirs = _checked_outputs(args)
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
