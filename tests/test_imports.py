"""Every module imports on its own (in a fresh interpreter), and no import cycle exists among the
project's modules (module-level and function-level imports alike)."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("prismonet", "realdata", "calibration")


def modules() -> list[str]:
    out = []
    for pkg in PACKAGES:
        for p in sorted((ROOT / pkg).rglob("*.py")):
            parts = p.relative_to(ROOT).with_suffix("").parts
            if parts[-1] != "__main__":  # running it is its job
                out.append(".".join(parts[:-1] if parts[-1] == "__init__" else parts))
    return out


FORK_EACH = """
import importlib, os, sys
import numpy, torch, cv2, scipy, safetensors, tqdm  # third-party, once: every child starts from here
bad = []
for m in sys.argv[1:]:
    pid = os.fork()
    if pid == 0:  # a fresh child holds no project module: m must import on its own
        try:
            importlib.import_module(m)
        except BaseException as e:
            print(f"{m}: {type(e).__name__}: {e}", flush=True)
            os._exit(1)
        os._exit(0)
    if os.waitpid(pid, 0)[1] != 0:
        bad.append(m)
print("FAILED", bad)
sys.exit(1 if bad else 0)
"""


def test_each_module_imports_alone():
    # one interpreter per module would take minutes (torch's import each time): one interpreter imports
    # the third-party libraries, then forks a child per project module, which imports that module alone
    r = subprocess.run([sys.executable, "-c", FORK_EACH, *modules()], cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, (r.stdout + r.stderr)[-3000:]


@pytest.mark.parametrize("module", ["prismonet.files", "prismonet.threads", "calibration.board", "calibration.intrinsics",
                                    "prismonet.model.distill", "prismonet.cli"])
def test_module_imports_first(module):
    r = subprocess.run([sys.executable, "-c", f"import {module}"], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]


def _imports(path: Path, name: str) -> set[str]:
    """Project modules ``name`` imports anywhere in its file (resolved to existing modules)."""
    known = set(modules())
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            base = node.module
            for alias in node.names:
                cand = f"{base}.{alias.name}"
                found.add(cand if cand in known else base)
        elif isinstance(node, ast.Import):
            found.update(a.name for a in node.names)
    return {m for m in found if m in known and m != name and not name.startswith(m + ".") and m.split(".")[0] in PACKAGES}


def test_no_import_cycles():
    graph = {}
    for pkg in PACKAGES:
        for p in (ROOT / pkg).rglob("*.py"):
            parts = p.relative_to(ROOT).with_suffix("").parts
            name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
            if parts[-1] != "__init__":  # a package's __init__ re-exports its children by design
                graph[name] = _imports(p, name)
    state: dict[str, int] = {}

    def visit(n, stack):
        state[n] = 1
        for m in graph.get(n, ()):
            if state.get(m) == 1:
                raise AssertionError("import cycle: " + " -> ".join(stack[stack.index(m):] + [m]) if m in stack else m)
            if state.get(m) is None:
                visit(m, stack + [m])
        state[n] = 2

    for n in sorted(graph):
        if state.get(n) is None:
            visit(n, [n])
