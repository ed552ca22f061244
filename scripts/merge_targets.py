"""Merge two rounds of distillation targets made on the same training scenes: a later round's slots where it shows
them, an earlier round's where only the earlier one does.

    python3 scripts/merge_targets.py LATER EARLIER OUT

A slot is shown by a round when its fit renders it over ``MIN_VISIBLE`` pixels (the targets' ``visible``). The merged
slot takes every field (pose, scale, latents) from LATER where LATER shows it, else from EARLIER; its ``visible`` is the
larger of the two, so the merged targets keep every slot either round shows. The background colour is LATER's. Both
rounds must have the same slots and scenes (``targets.json``'s ``num_slots``, ``count`` and ``chunk``), and the slot
order must be one encoder's (a refined model keeps its encoder's order). ``OUT/targets.json`` is LATER's with
``merged_from`` added, so ``prismonet refiner`` checks the encoder as it would for LATER.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch

from prismonet.checkpoint import load_checkpoint, save_checkpoint
from prismonet.model.distill import MIN_VISIBLE, VISIBLE


def merge_chunk(later: dict[str, torch.Tensor], earlier: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """One chunk: every per-slot field from ``later`` where it shows the slot, else from ``earlier``."""
    if VISIBLE not in later or VISIBLE not in earlier:
        raise SystemExit("merge_targets: both rounds need `visible` (targets made by `prismonet distill` since session 47)")
    take_later = later[VISIBLE] >= MIN_VISIBLE  # (B, K)
    out = {}
    for k, v in later.items():
        if k == "bg_color":
            out[k] = v
        elif k == VISIBLE:
            out[k] = torch.maximum(v, earlier[k])
        else:
            if k not in earlier or earlier[k].shape != v.shape:
                raise SystemExit(f"merge_targets: field {k!r} differs between the rounds")
            m = take_later.reshape(*take_later.shape, *([1] * (v.dim() - 2)))
            out[k] = torch.where(m, v, earlier[k])
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("later")
    ap.add_argument("earlier")
    ap.add_argument("out")
    a = ap.parse_args(argv)
    later, earlier, out = Path(a.later), Path(a.earlier), Path(a.out)
    info_l = json.loads((later / "targets.json").read_text())
    info_e = json.loads((earlier / "targets.json").read_text())
    for k in ("num_slots", "count", "chunk", "data", "split"):
        if info_l.get(k) != info_e.get(k):
            raise SystemExit(f"merge_targets: the rounds differ in {k}: {info_l.get(k)!r} against {info_e.get(k)!r}")
    out.mkdir(parents=True, exist_ok=True)
    n = 0
    for i in range(0, info_l["count"], info_l["chunk"]):
        name = f"chunk_{i // info_l['chunk']:05d}.safetensors"
        if not (later / name).is_file() or not (earlier / name).is_file():
            break
        tl, meta = load_checkpoint(later / name)
        te, _ = load_checkpoint(earlier / name)
        save_checkpoint(out / name, merge_chunk(tl, te), meta)
        n += 1
    info = dict(info_l, merged_from={"later": str(later), "earlier": str(earlier)})
    (out / "targets.json").write_text(json.dumps(info, indent=1))
    print(f"{n} chunks merged into {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
