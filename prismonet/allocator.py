"""Keeping freed memory for reuse: glibc's ``malloc`` tuned so that a training step stops paging its buffers in.

A training step allocates and frees the same few dozen multi-megabyte tensors every time (the root search's
``(16384, 64)`` activation blocks, the encoders' ``(8, 32, 64, 64)`` feature maps and their gradients). glibc serves
a block above its mmap threshold with a fresh ``mmap`` and unmaps it on ``free``; its dynamic threshold rises only
up to 32 MiB, and it trims the heap's top whenever more than its trim threshold lies free there. Either way the next
step gets memory the kernel must fault in and zero again: about 5,000-7,000 minor page faults and 11-18 ms of
system time per step on the project's 2-core machines (BENCHMARKS.md, "Freed memory kept for reuse").

``keep_freed_memory`` raises both thresholds (``mallopt``), so these blocks come from the heap and go back to it,
where the next step finds them already mapped. Numbers are unchanged: only where memory comes from moves. The price
is that freed memory (up to ``TRIM_THRESHOLD`` above the heap's top) stays with the process instead of going back
to the system. Elsewhere than glibc (macOS, musl) it does nothing and says so. ``PRISMONET_MALLOC=default`` in the
environment leaves the allocator as it is.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os

MMAP_THRESHOLD = 256 << 20
"""Blocks below this many bytes come from the heap (glibc's default: 128 KiB, rising with use to at most 32 MiB).
Above a training step's largest buffer (a 64 x 64 x 32 x 8 float map is 4 MiB; a search block 4 MiB)."""
TRIM_THRESHOLD = 1 << 30
"""Free memory at the heap's top kept before it is returned to the system (glibc's default: 128 KiB, then twice
the mmap threshold). About a step's peak working set, several times over."""
ENV = "PRISMONET_MALLOC"
"""Set to ``default`` to leave the allocator alone."""

_M_TRIM_THRESHOLD = -1  # glibc's <malloc.h> parameter numbers
_M_MMAP_THRESHOLD = -3


def _libc():
    """glibc's ``mallopt``, or ``None`` where there is none."""
    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name) if name else None
    except OSError:
        return None
    f = getattr(libc, "mallopt", None)
    if f is not None:
        f.argtypes, f.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    return f


def keep_freed_memory(mmap_threshold: int = MMAP_THRESHOLD, trim_threshold: int = TRIM_THRESHOLD) -> bool:
    """Tune this process's ``malloc`` to keep freed blocks for reuse (module docstring); ``True`` if it was applied.

    Args:
        mmap_threshold: bytes; blocks up to this size come from the heap (at most 2**31 - 1).
        trim_threshold: bytes of free memory at the heap's top that are kept (at most 2**31 - 1).

    ``False`` without glibc's ``mallopt`` (macOS, musl) and when ``PRISMONET_MALLOC=default`` is set. Safe to call
    more than once; it affects allocations made after the call.
    """
    limit = 2**31 - 1  # mallopt takes a C int
    if not (0 < mmap_threshold <= limit and 0 < trim_threshold <= limit):
        raise ValueError(f"malloc thresholds: expected 1 .. {limit} bytes, got {mmap_threshold} and {trim_threshold}")
    setting = os.environ.get(ENV, "")
    if setting not in ("", "default", "keep"):
        raise ValueError(f"{ENV}: expected 'default' or 'keep', got {setting!r}")
    if setting == "default":
        return False
    mallopt = _libc()
    if mallopt is None:
        return False
    return bool(mallopt(_M_MMAP_THRESHOLD, mmap_threshold) and mallopt(_M_TRIM_THRESHOLD, trim_threshold))
