"""Compare refiner variants at one budget on self-distillation targets (the encoder frozen, no render).

Builds the model's unrefined decoding of the target scenes once, then fits each variant's refiner for
``--steps`` steps of ``--batch`` scenes (``prismonet.model.refiner_fit``'s loss) and reports the held-out
loss split by term, against no correction:

    python3 scripts/refiner_sweep.py clevr3_fc data/clevr3 --targets runs/distill_clevr3_fc_r2_8k \
        --variants "base|channels=64,64,128,128;fc=512,512" --steps 3000 --out runs/s46/refiner_sweep.json

A variant is ``;``-separated ``key=value`` of ``ModelConfig``'s refiner fields (``refiner_channels``,
``refiner_fc``, ``refiner_coords``, ``refiner_glimpse``, written without the ``refiner_`` prefix); ``base`` is the
defaults. Each variant's fitted model is written to ``OUT_DIR/<name>/model`` when ``--save`` is given.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import torch
from tqdm import tqdm

from prismonet.data.dataset import SceneDataset
from prismonet.model.distill import DistillTargets, DistillWeights
from prismonet.model.io import load_model, save_model
from prismonet.model.refiner import apply_correction
from prismonet.model.refiner_fit import encoder_cache, refiner_inputs, with_refiner
from prismonet.render import SceneParams

TERMS = ("position", "scale", "rotation", "texture")


def parse_variant(text: str) -> dict:
    if text.strip() in ("", "base"):
        return {}
    out = {}
    for part in text.split(";"):
        k, v = part.split("=")
        k = k.strip()
        if k in ("channels", "fc"):
            out[f"refiner_{k}"] = tuple(int(x) for x in v.split(","))
        elif k in ("coords",):
            out[f"refiner_{k}"] = v.strip().lower() in ("1", "true", "yes")
        elif k in ("glimpse",):
            out[f"refiner_{k}"] = float(v)
        else:
            raise SystemExit(f"unknown variant key {k!r}")
    return out


def term_losses(model, cache, ds, targets, idx: torch.Tensor, correct: bool) -> dict[str, float]:
    """Mean per-term distillation loss over the slots the fit shows (as ``distill_loss``), with or without the refiner."""
    w = DistillWeights()
    sums = {k: 0.0 for k in TERMS}
    n = 0.0
    with torch.no_grad():
        for s in range(0, len(idx), 128):
            i = idx[s:s + 128]
            params = SceneParams(*(cache[k][i] for k in ("z_sh", "z_tex", "position", "cos_sin", "scale")))
            if correct:
                views, lat = refiner_inputs(model, cache, ds, i, params)
                params = apply_correction(params, model.refiner(views, lat), model.pos_scale, model.cfg.scale_range)
            t, _ = targets.lookup(i)
            cs = params.cos_sin / params.cos_sin.norm(dim=-1, keepdim=True).clamp_min(1e-6)
            ct = t["cos_sin"] / t["cos_sin"].norm(dim=-1, keepdim=True).clamp_min(1e-6)
            per = {"position": w.position * (params.position - t["position"]).abs().sum(-1),
                   "scale": w.scale * (params.scale - t["scale"]).abs(),
                   "rotation": w.rotation * (1 - (cs * ct).sum(-1)),
                   "texture": w.texture * ((params.z_tex - t["z_tex"]) ** 2).sum(-1)}
            seen = (t["visible"] >= 25).float() if "visible" in t else torch.ones_like(per["scale"])
            for k in TERMS:
                sums[k] += float((per[k] * seen).sum())
            n += float(seen.sum())
    return {k: v / max(n, 1.0) for k, v in sums.items()}


def main() -> None:
    from prismonet.model.distill import distill_loss

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("model")
    ap.add_argument("data")
    ap.add_argument("--targets", required=True)
    ap.add_argument("--variants", default="base")
    ap.add_argument("--steps", type=int, default=3000)
    ap.add_argument("--batch", type=int, default=32)
    ap.add_argument("--lr", type=float, default=3e-4)
    ap.add_argument("--holdout", type=int, default=256)
    ap.add_argument("--out", required=True)
    ap.add_argument("--save", action="store_true")
    args = ap.parse_args()
    base, info = load_model(args.model)
    ds = SceneDataset(args.data, split="train")
    targets = DistillTargets(args.targets, base.cfg.num_slots)
    count = min(targets.count, len(ds))
    cache = encoder_cache(base, ds, count)
    train_n = count - args.holdout
    held = torch.arange(train_n, count)
    rows = []
    for text in args.variants.split("|"):
        fields = parse_variant(text)
        model = with_refiner(base, 1, **fields)
        before = term_losses(model, cache, ds, targets, held, correct=False)
        opt = torch.optim.AdamW(model.refiner.parameters(), lr=args.lr, weight_decay=1e-4)
        weights = DistillWeights(background=0.0)
        model.refiner.train()
        t0 = time.perf_counter()
        for step in tqdm(range(args.steps), desc=text or "base"):
            for g in opt.param_groups:
                g["lr"] = args.lr * (0.01 + 0.99 * 0.5 * (1 + math.cos(math.pi * step / args.steps)))
            gen = torch.Generator().manual_seed(step)
            idx = torch.randint(0, train_n, (args.batch,), generator=gen)
            params = SceneParams(*(cache[k][idx] for k in ("z_sh", "z_tex", "position", "cos_sin", "scale")))
            views, lat = refiner_inputs(model, cache, ds, idx, params)
            new = apply_correction(params, model.refiner(views, lat), model.pos_scale, model.cfg.scale_range)
            t, have = targets.lookup(idx)
            loss = distill_loss(new, t["bg_color"], t, have, weights)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
        seconds = time.perf_counter() - t0
        model.refiner.eval()
        after = term_losses(model, cache, ds, targets, held, correct=True)
        row = {"variant": text or "base", "steps": args.steps, "seconds": seconds, "before": before, "after": after,
               "held_out_before": sum(before.values()), "held_out_after": sum(after.values())}
        rows.append(row)
        print(json.dumps(row))
        if args.save:
            name = (text or "base").replace(";", "_").replace("=", "").replace(",", "-")
            save_model(model.eval(), Path(args.out).with_suffix("") / name / "model",
                       {k: v for k, v in info.items() if k not in ("model", "prior_fingerprint")})
    Path(args.out).write_text(json.dumps({"model": args.model, "targets": args.targets, "rows": rows}, indent=1))
    print("| variant | steps | s | held-out before | after | position | scale | rotation | texture |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        a, b = r["after"], r["before"]
        print(f"| {r['variant']} | {r['steps']} | {r['seconds']:.0f} | {r['held_out_before']:.4f} | {r['held_out_after']:.4f} | "
              + " | ".join(f"{b[k]:.4f} → {a[k]:.4f}" for k in TERMS) + " |")


if __name__ == "__main__":
    main()
