"""``prismonet.allocator``: freed blocks are reused instead of paged in again (glibc), and the one-line refusals."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from prismonet.allocator import ENV, _libc, keep_freed_memory

# A fresh process mallocs, writes and frees a 40 MiB block five times (glibc's own malloc, through ctypes: what is
# tested is the policy, not torch's use of it) and counts the minor page faults of the last four. 40 MiB is above
# glibc's largest dynamic mmap threshold (32 MiB), so its default allocator maps the block anew each time.
PROBE = """
import ctypes, json, resource
from prismonet.allocator import keep_freed_memory
applied = keep_freed_memory()
libc = ctypes.CDLL("libc.so.6")
libc.malloc.restype, libc.malloc.argtypes, libc.free.argtypes = ctypes.c_void_p, (ctypes.c_size_t,), (ctypes.c_void_p,)
n = 40 << 20
def once():
    p = libc.malloc(n)
    ctypes.memset(p, 1, n)
    libc.free(p)
once()
r0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(4):
    once()
print(json.dumps({"applied": applied, "faults": resource.getrusage(resource.RUSAGE_SELF).ru_minflt - r0}))
"""

needs_glibc = pytest.mark.skipif(_libc() is None or not sys.platform.startswith("linux"), reason="glibc's mallopt only")


def _probe(setting: str) -> dict:
    env = dict(os.environ, **{ENV: setting})
    out = subprocess.run([sys.executable, "-c", PROBE], env=env, capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


@needs_glibc
def test_freed_blocks_are_reused():
    kept, default = _probe("keep"), _probe("default")
    assert kept["applied"] and not default["applied"]
    pages = 4 * (40 << 20) // os.sysconf("SC_PAGE_SIZE")  # four tensors' worth of pages
    assert default["faults"] > 0.9 * pages  # glibc maps each one anew: the control, which shows the probe can fail
    assert kept["faults"] < 0.05 * pages  # the heap keeps the block: nothing is paged in again


def test_refusals():
    with pytest.raises(ValueError, match="malloc thresholds"):
        keep_freed_memory(mmap_threshold=0)
    with pytest.raises(ValueError, match="malloc thresholds"):
        keep_freed_memory(trim_threshold=2**31)


def test_bad_setting(monkeypatch):
    monkeypatch.setenv(ENV, "fast")
    with pytest.raises(ValueError, match=f"{ENV}: expected 'default' or 'keep'"):
        keep_freed_memory()


def test_default_leaves_it(monkeypatch):
    monkeypatch.setenv(ENV, "default")
    assert keep_freed_memory() is False
