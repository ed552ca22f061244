"""The pose search of a git revision against the working tree's: identical outputs, and time per scene.

    python3 scripts/search_ab.py 5510d98 data/clevr3 --limit 64 --passes 3 "rounds=4,coarse_rounds=2"

Loads ``prismonet/model/search.py`` as it was at the revision beside the current module, runs both on
the same encoder outputs (batches of 16 of the split), interleaved pass by pass in one process, and
prints each one's time per scene, the medians, and whether the latents and composites are equal.
The setting is ``SearchConfig`` fields as in ``search_sweep.py`` (fields the old module lacks are an error).
"""

from __future__ import annotations

import argparse
import importlib.util
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from search_sweep import parse_setting  # noqa: E402

from prismonet.data.dataset import SceneDataset  # noqa: E402
from prismonet.model.inference import decode_overcomplete  # noqa: E402
from prismonet.model.io import load_model  # noqa: E402
from prismonet.model.search import SearchConfig, search_latents  # noqa: E402

MODULE = "prismonet/model/search.py"


def old_module(rev: str):
    src = subprocess.run(["git", "show", f"{rev}:{MODULE}"], capture_output=True, text=True,
                         cwd=Path(__file__).resolve().parents[1])
    if src.returncode:
        sys.exit(f"search_ab: error: no {MODULE} at {rev!r}: {src.stderr.strip().splitlines()[0]}")
    path = Path(tempfile.mkdtemp()) / "search_at_rev.py"
    path.write_text(src.stdout)
    spec = importlib.util.spec_from_file_location("search_at_rev", path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # dataclasses look their module up
    spec.loader.exec_module(mod)
    return mod


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("rev")
    ap.add_argument("data")
    ap.add_argument("setting", nargs="?", default="")
    ap.add_argument("--checkpoint", default="shipped")
    ap.add_argument("--split", default="val")
    ap.add_argument("--limit", type=int, default=64)
    ap.add_argument("--passes", type=int, default=3)
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_intermixed_args()  # the setting may follow the options
    old = old_module(args.rev)
    try:
        fields = parse_setting(args.setting) if args.setting else {}
        cfgs = {"old": old.SearchConfig(**fields), "new": SearchConfig(**fields)}
    except (SyntaxError, ValueError, TypeError) as e:
        ap.error(f"setting {args.setting!r}: {str(e).splitlines()[0]}")
    torch.set_num_threads(args.threads)
    model, _ = load_model(args.checkpoint)
    model.eval()
    ds = SceneDataset(args.data, split=args.split)
    n = min(args.limit, len(ds))
    batches = [ds.batch(range(i, min(i + 16, n))) for i in range(0, n, 16)]
    with torch.no_grad():
        outs = [decode_overcomplete(model, b, None, 0, use_depth=True, w_image=1.0, w_depth=0.1, stop=None) for b in batches]
    fns = {"old": old.search_latents, "new": search_latents}
    times: dict[str, list[float]] = {"old": [], "new": []}
    same = True
    for _ in range(args.passes):
        res = {}
        for name in ("old", "new"):
            t = time.perf_counter()
            res[name] = [fns[name](model, o, b, cfgs[name]) for o, b in zip(outs, batches)]
            times[name].append((time.perf_counter() - t) / n * 1e3)
        for a, b in zip(res["old"], res["new"]):
            pa, pb = a.latents.params, b.latents.params
            same &= all(torch.equal(getattr(pa, f), getattr(pb, f)) for f in ("scale", "position", "cos_sin", "z_sh"))
            same &= torch.equal(a.composite.image, b.composite.image) and torch.equal(a.obj_depth, b.obj_depth)
    med = {k: statistics.median(v) for k, v in times.items()}
    for k, v in times.items():
        print(f"{k} ({args.rev if k == 'old' else 'working tree'}): " + " / ".join(f"{t:.1f}" for t in v)
              + f" ms per scene, median {med[k]:.1f}")
    print(f"speed-up {med['old'] / med['new']:.2f}x; outputs identical: {same}")


if __name__ == "__main__":
    main()
