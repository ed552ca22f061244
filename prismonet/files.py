"""Files in and out, checked once: output paths before any work starts, readers that return
validated structures, and bounds on sizes and counts. Every failure is a ``ValueError`` subclass
with one line that names the path or the setting, which the command line prints as
``prismonet: error: ...`` with exit status 2.

- ``check_output(path, kind)``: the output has the right kind (file, image, folder), its folder can
  be written (probed by creating a file, which also catches read-only file systems and root), and
  an image's extension is one OpenCV can write. Nothing is created, so a refused command leaves
  nothing behind.
- ``read_image``: bytes read by Python and decoded by ``cv2.imdecode``, so a file name that is not
  valid UTF-8 never reaches OpenCV's path handling (``cv2.imread`` crashed on one).
- ``read_json``: parse errors, non-UTF-8 text and the wrong top-level type as one line.
- ``bounded``: integers and finite floats within stated limits, the limits in the message.
- ``shown``: a path as printable text (undecodable bytes escaped), for messages.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import tempfile
from pathlib import Path

import numpy as np


class InputError(ValueError):
    """A bad input file, output path or setting (one line, naming it)."""


MAX_IMAGE_SIDE = 4096
"""Largest side of any image a command renders or prepares (views, real prepare)."""
MAX_MESH_RESOLUTION = 512
"""Largest marching-cubes grid per object (export): 512^3 SDF samples is ~0.5 GB of float32."""
MAX_SLOTS = 64
"""Most object slots (recurrent encoder steps) a model may have."""


def shown(path) -> str:
    """``path`` as printable text: bytes that are not valid UTF-8 are shown as ``\\xNN``."""
    return os.fsencode(path).decode("utf-8", "backslashreplace")


def pid_alive(pid) -> bool:
    """Whether a process with this id runs (for files a killed process left: ``NAME.tmp-PID``)."""
    try:
        os.kill(int(pid), 0)
    except (ValueError, ProcessLookupError):
        return False
    except PermissionError:  # it runs, as another user
        return True
    return True


def probe_writable(folder: Path, what: Path) -> None:
    """Raise unless a file can be created in ``folder`` or, if it does not exist yet, in the
    nearest existing folder above it (where it would be made)."""
    f = folder
    while not f.exists():
        if f.parent == f:
            break
        f = f.parent
    if not f.is_dir():
        raise InputError(f"{shown(what)}: is not writable ({shown(f)} is a file, not a folder)")
    try:
        fd, probe = tempfile.mkstemp(dir=f, prefix=".prismonet-probe-")
        os.close(fd)
        os.unlink(probe)
    except OSError as e:
        raise InputError(f"{shown(what)}: is not writable ({e.strerror or e} in {shown(f)})") from None


def check_output(path, kind: str = "file") -> Path:
    """Check an output path before any work: ``kind`` is ``"file"``, ``"image"`` (a file whose
    extension OpenCV can write), ``"dir"`` (a folder, new or existing) or ``"new_dir"`` (a folder
    that is new or empty). Returns ``Path(path)``; creates nothing."""
    p = Path(path)
    if kind in ("file", "image"):
        if p.is_dir():
            raise InputError(f"{shown(p)}: is a folder; expected a file name")
        if kind == "image":
            import cv2

            if not p.suffix or not cv2.haveImageWriter(str(p.with_name("x" + p.suffix))):
                raise InputError(f"{shown(p)}: OpenCV cannot write images of type {p.suffix or '(no extension)'!r}; use .png or .jpg")
        probe_writable(p.parent, p)
    elif kind in ("dir", "new_dir"):
        if p.exists() and not p.is_dir():
            raise InputError(f"{shown(p)}: exists and is not a folder")
        if kind == "new_dir" and p.is_dir() and any(p.iterdir()):
            raise InputError(f"{shown(p)}: output folder is not empty")
        probe_writable(p, p)
    else:
        raise ValueError(f"check_output: unknown kind {kind!r}")
    return p


def read_image(path, flags: int | None = None) -> np.ndarray:
    """An image as OpenCV decodes it (BGR by default), read as bytes first; one line on failure."""
    import cv2

    p = Path(path)
    if not p.is_file():
        raise InputError(f"{shown(p)}: no such file" if not p.exists() else f"{shown(p)}: is not a file")
    data = np.frombuffer(p.read_bytes(), np.uint8)
    img = cv2.imdecode(data, cv2.IMREAD_COLOR if flags is None else flags) if data.size else None
    if img is None:
        raise InputError(f"{shown(p)}: cannot be read as an image")
    return img


def read_json(path, expect: type = dict, required: tuple[str, ...] = ()) -> object:
    """Parse a JSON file whose top level is an ``expect`` (with the ``required`` keys, for a dict)."""
    p = Path(path)
    if not p.is_file():
        raise InputError(f"{shown(p)}: no such file" if not p.exists() else f"{shown(p)}: is not a file")
    try:
        data = json.loads(p.read_bytes().decode("utf-8"))
    except UnicodeDecodeError:
        raise InputError(f"{shown(p)}: is not UTF-8 text") from None
    except json.JSONDecodeError as e:
        raise InputError(f"{shown(p)}: not valid JSON ({e.msg} at line {e.lineno})") from None
    if not isinstance(data, expect):
        raise InputError(f"{shown(p)}: expected a JSON {'object' if expect is dict else expect.__name__}, got {type(data).__name__}")
    missing = [k for k in required if k not in data] if isinstance(data, dict) else []
    if missing:
        raise InputError(f"{shown(p)}: missing {', '.join(repr(k) for k in missing)}")
    return data


def bounded(name: str, value, lo=None, hi=None, integer: bool = False):
    """``value`` if it is finite (an integer with ``integer``) and within ``[lo, hi]``; else one line."""
    if integer and (isinstance(value, bool) or not isinstance(value, (int, np.integer))):
        raise InputError(f"{name} must be an integer, got {value!r}")
    if not isinstance(value, (int, float, np.integer, np.floating)) or isinstance(value, bool) or not math.isfinite(value):
        raise InputError(f"{name} must be a finite number, got {value!r}")
    if (lo is not None and value < lo) or (hi is not None and value > hi):
        rng = f"in [{lo}, {hi}]" if lo is not None and hi is not None else (f">= {lo}" if lo is not None else f"<= {hi}")
        raise InputError(f"{name} must be {rng}, got {value}")
    return value


def arg_int(lo: int | None = None, hi: int | None = None):
    """An argparse ``type``: an integer within ``[lo, hi]`` (the limits in the message)."""
    import argparse

    def parse(text: str) -> int:
        try:
            return bounded("value", int(text), lo, hi, integer=True)
        except (InputError, ValueError) as e:
            msg = str(e) if isinstance(e, InputError) else f"expected an integer, got {text!r}"
            raise argparse.ArgumentTypeError(msg.replace("value must", "must")) from None

    return parse


def arg_float(lo: float | None = None, hi: float | None = None, positive: bool = False):
    """An argparse ``type``: a finite number within ``[lo, hi]`` (``positive``: also > 0)."""
    import argparse

    def parse(text: str) -> float:
        try:
            v = bounded("value", float(text), lo, hi)
        except (InputError, ValueError) as e:
            msg = str(e) if isinstance(e, InputError) else f"expected a number, got {text!r}"
            raise argparse.ArgumentTypeError(msg.replace("value must", "must")) from None
        if positive and v <= 0:
            raise argparse.ArgumentTypeError(f"must be positive, got {text}")
        return v

    return parse


def write_image(path, image: np.ndarray) -> Path:
    """Write an image (OpenCV's BGR order) by encoding it in memory and writing the bytes from
    Python, so a file name that is not valid UTF-8 never reaches OpenCV; one line on failure. The bytes go
    through ``write_atomic``: an interrupted write leaves the old file or none, never a truncated image."""
    import cv2

    p = Path(path)
    ok, buf = cv2.imencode(p.suffix or ".png", np.ascontiguousarray(image)) if p.suffix else (False, None)
    if not ok:
        raise InputError(f"{shown(p)}: OpenCV cannot write images of type {p.suffix or '(no extension)'!r}")
    return write_atomic(p, buf.tobytes())


def write_atomic(path, data: bytes | str) -> Path:
    """Write ``data`` to a hidden temporary file beside ``path`` and rename it into place, so that an
    interrupted write never leaves a half-written ``path``."""
    p = Path(path)
    tmp = p.with_name(f".{p.name}.tmp-{os.getpid()}")
    try:
        tmp.write_bytes(data.encode() if isinstance(data, str) else data)
        os.replace(tmp, p)
    finally:
        tmp.unlink(missing_ok=True)
    return p


def sha256_file(path: str | Path, chunk: int = 1 << 24) -> str:
    """The SHA-256 of a file's bytes, read in ``chunk``-byte blocks (packed datasets' manifests, shared model weights)."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk):
            h.update(block)
    return h.hexdigest()
