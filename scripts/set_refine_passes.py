"""Write a copy of a trained model that applies its learnt refiner a different number of times (the same weights).

    python3 scripts/set_refine_passes.py runs/clevr3_glimpse 2 runs/clevr3_glimpse_2pass
    python3 scripts/set_refine_passes.py runs/s48/a18_keep_fit 2 runs/s48/a18_keep_re2 --reanchor 2   # anchored models

``--reanchor N`` also sets ``reanchor_steps`` (``ModelConfig``: anchored steps after refinement, into empty slots);
``--reanchor-keep X`` sets ``reanchor_keep_logit``, the keep logit a re-anchored slot must beat (``none``: never
dropped); ``--anchor-shade K`` sets ``anchor_shade_min``, the least even darkening the anchor rule reads as a cast
shadow (``none``: off, as trained).

    python3 scripts/set_refine_passes.py tabletop_keep 2 runs/tabletop_keep_noshade --anchor-shade none   # session 48's

The copy's record keeps the source's and notes the change (``refine_passes_from``); the passes were chosen on
the validation split (EVALUATION.md, "Session 46").
"""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

from prismonet.model.io import load_model, save_model
from prismonet.model.prismonet import PriSMONet


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("model", help="run folder, .safetensors, or a shipped name (with a refiner)")
    ap.add_argument("passes", type=int)
    ap.add_argument("out", help="new run folder")
    ap.add_argument("--reanchor", type=int, default=None, metavar="N",
                    help="also set reanchor_steps to N (an anchored model: N more anchored steps after refinement)")
    ap.add_argument("--reanchor-keep", default=None, metavar="X",
                    help="also set reanchor_keep_logit: a re-anchored slot is dropped where its keep logit is <= X "
                         "('none': never dropped)")
    ap.add_argument("--anchor-shade", default=None, metavar="K",
                    help="also set anchor_shade_min: an evenly darkened composition by a factor >= K counts as a shadow "
                         "('none': off)")
    args = ap.parse_args()
    model, info = load_model(args.model)
    if not model.cfg.refine_passes or args.passes < 1:
        raise SystemExit(f"{args.model}: needs a model with a refiner and passes >= 1 (it has {model.cfg.refine_passes}, asked {args.passes})")
    fields = {"refine_passes": args.passes}
    if args.reanchor is not None:
        if not model.cfg.anchor or args.reanchor < 0:
            raise SystemExit(f"{args.model}: --reanchor needs an anchored model and N >= 0 (anchor {model.cfg.anchor}, asked {args.reanchor})")
        fields["reanchor_steps"] = args.reanchor
    if args.reanchor_keep is not None:
        try:
            fields["reanchor_keep_logit"] = None if args.reanchor_keep.lower() == "none" else float(args.reanchor_keep)
        except ValueError:
            raise SystemExit(f"--reanchor-keep: expected a number or 'none', got {args.reanchor_keep!r}") from None
    if args.anchor_shade is not None:
        if not model.cfg.anchor:
            raise SystemExit(f"{args.model}: --anchor-shade needs an anchored model")
        try:
            fields["anchor_shade_min"] = None if args.anchor_shade.lower() == "none" else float(args.anchor_shade)
        except ValueError:
            raise SystemExit(f"--anchor-shade: expected a number or 'none', got {args.anchor_shade!r}") from None
    try:
        cfg = replace(model.cfg, **fields)
    except ValueError as e:
        raise SystemExit(f"{args.model}: {e}") from None
    new = PriSMONet(cfg, prior=model.prior)
    new.load_state_dict(model.state_dict())
    Path(args.out).mkdir(parents=True, exist_ok=True)
    record = {k: v for k, v in info.items() if k not in ("model", "prior_fingerprint")}
    save_model(new.eval(), Path(args.out) / "model", {**record, "refine_passes_from": {"source": str(args.model), "passes": model.cfg.refine_passes, "reanchor_steps": model.cfg.reanchor_steps,
                                                                                   "reanchor_keep_logit": model.cfg.reanchor_keep_logit,
                                                                                   "anchor_shade_min": model.cfg.anchor_shade_min}})
    print(f"wrote {args.out}/model.safetensors + model.json: {model.cfg.refine_passes} -> {args.passes} refinement passes"
          + ("" if args.reanchor is None else f", reanchor_steps {model.cfg.reanchor_steps} -> {args.reanchor}")
          + ("" if args.reanchor_keep is None else f", reanchor_keep_logit {model.cfg.reanchor_keep_logit} -> {cfg.reanchor_keep_logit}")
          + ("" if args.anchor_shade is None else f", anchor_shade_min {model.cfg.anchor_shade_min} -> {cfg.anchor_shade_min}"))


if __name__ == "__main__":
    main()
