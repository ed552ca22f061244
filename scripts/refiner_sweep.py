"""Compare refiner variants at one budget on self-distillation targets (the encoder frozen, no render).

Builds the model's unrefined decoding of the target scenes once, then fits each variant's refiner with
``prismonet.model.refiner_fit.fit_refiner`` (``OUT_DIR/<variant>/``: resumable, and a whole model at the end)
and reports the held-out loss split by term, against no correction:

    python3 scripts/refiner_sweep.py clevr3_fc data/clevr3 --targets runs/distill_clevr3_fc_r2_8k \
        --variants "base|channels=64,64,128,128;fc=512,512" --steps 3000 --out runs/s46/refiner_sweep.json

A variant is ``;``-separated ``key=value`` of ``ModelConfig``'s refiner fields (``channels``, ``fc``, ``coords``,
``glimpse``, ``shape``, ``keep``: ``refiner_`` left off); ``base`` is the defaults. A model that has a refiner gets a fresh one.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch

from prismonet.data.dataset import SceneDataset
from prismonet.model.distill import DistillTargets, distill_terms, seen_slots
from prismonet.model.io import load_model
from prismonet.model.refiner import apply_correction, split_keep
from prismonet.model.refiner_fit import RefinerFitConfig, cached_refiner_inputs, encoder_cache, fit_refiner, with_refiner
from prismonet.render import SceneParams

TERMS = ("position", "scale", "rotation", "texture")


def parse_variant(text: str) -> dict:
    if text.strip() in ("", "base"):
        return {}
    out = {}
    for part in text.split(";"):
        k, v = (x.strip() for x in part.split("="))
        if k in ("channels", "fc"):
            out[f"refiner_{k}"] = tuple(int(x) for x in v.split(","))
        elif k == "coords":
            out["refiner_coords"] = v.lower() in ("1", "true", "yes")
        elif k == "glimpse":
            out["refiner_glimpse"] = float(v)
        elif k in ("shape", "keep"):
            out[f"refiner_{k}"] = v.lower() in ("1", "true", "yes")
        else:
            raise SystemExit(f"unknown variant key {k!r} (channels, fc, coords, glimpse, shape, keep)")
    return out


@torch.no_grad()
def term_losses(model, cache, ds, targets, idx: torch.Tensor, correct: bool) -> dict[str, float]:
    """Mean per-term distillation loss over the target slots of scenes ``idx``, with or without the refiner
    (``TERMS``, plus ``shape`` when the targets have shape latents). A refiner with a keep output adds
    ``keep_wrong``: the fraction of all slots it keeps where the fit hides them or drops where the fit shows them."""
    sums: dict[str, float] = {}
    n, wrong, slots = 0.0, 0.0, 0
    for s in range(0, len(idx), 128):
        i = idx[s:s + 128]
        params = SceneParams(*(cache[k][i] for k in ("z_sh", "z_tex", "position", "cos_sin", "scale")))
        t, _ = targets.lookup(i)
        if correct:
            delta, logit = split_keep(model.refiner(*cached_refiner_inputs(model, cache, ds, i, params)), model.cfg.refiner_keep)
            params = apply_correction(params, delta, model.pos_scale, model.cfg.scale_range)
            if logit is not None:
                shown = seen_slots(t, t["scale"]) > 0
                wrong += float(((logit.reshape(shown.shape) > 0) != shown).sum())
                slots += logit.numel()
        terms = distill_terms(params, t)
        seen = seen_slots(t, terms["scale"])
        for k, v in terms.items():
            sums[k] = sums.get(k, 0.0) + float((v * seen).sum())
        n += float(seen.sum())
    out = {k: v / max(n, 1.0) for k, v in sums.items()}
    if slots:
        out["keep_wrong"] = wrong / slots
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("model")
    ap.add_argument("data")
    ap.add_argument("--targets", required=True)
    ap.add_argument("--variants", default="base")
    ap.add_argument("--steps", type=int, default=3000)
    ap.add_argument("--batch", type=int, default=32)
    ap.add_argument("--lr", type=float, default=3e-4)
    ap.add_argument("--holdout", type=int, default=256)
    ap.add_argument("--out", required=True, help="JSON of the results; each variant's run folder goes beside it")
    args = ap.parse_args()
    from prismonet.threads import use_free_cores

    use_free_cores(exit_on_error=True)  # the cores others leave free; PRISMONET_THREADS=N to choose
    base, info = load_model(args.model)
    ds = SceneDataset(args.data, split="train")
    targets = DistillTargets(args.targets, base.cfg.num_slots)
    count = min(targets.count, len(ds))
    cache = encoder_cache(base, ds, count)
    held = torch.arange(count - args.holdout, count)
    cfg = RefinerFitConfig(steps=args.steps, batch_size=args.batch, lr=args.lr, holdout=args.holdout)
    rows = []
    for text in args.variants.split("|"):
        name = (text.strip() or "base").replace(";", "_").replace("=", "").replace(",", "-")
        model = with_refiner(base, 1, **parse_variant(text))
        before = term_losses(model, cache, ds, targets, held, correct=False)
        summary = fit_refiner(model, ds, args.targets, Path(args.out).with_suffix("") / name, cfg,
                              info={**info, "init_from": str(args.model)}, cache=cache)
        after = term_losses(model, cache, ds, targets, held, correct=True)
        row = {"variant": text or "base", "steps": summary["steps"], "seconds": summary["seconds"], "before": before,
               "after": after, "held_out_before": sum(before.values()),
               "held_out_after": sum(v for k, v in after.items() if k in before)}
        rows.append(row)
        print(json.dumps(row))
    Path(args.out).write_text(json.dumps({"model": args.model, "targets": args.targets, "rows": rows}, indent=1))
    names = sorted({k for r in rows for k in r["after"]}, key=lambda k: (k == "keep_wrong", k)) or list(TERMS)
    print("| variant | steps | s | held-out before | after | " + " | ".join(names) + " |")
    print("|---" * (5 + len(names)) + "|")
    for r in rows:
        a, b = r["after"], r["before"]
        print(f"| {r['variant']} | {r['steps']} | {r['seconds']:.0f} | {r['held_out_before']:.4f} | {r['held_out_after']:.4f} | "
              + " | ".join(f"{b.get(k, float('nan')):.4f} → {a.get(k, float('nan')):.4f}" for k in names) + " |")

if __name__ == "__main__":
    main()
