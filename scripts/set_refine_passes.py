"""Write a copy of a trained model that applies its learnt refiner a different number of times (the same weights).

    python3 scripts/set_refine_passes.py runs/clevr3_glimpse 2 runs/clevr3_glimpse_2pass

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
    args = ap.parse_args()
    model, info = load_model(args.model)
    if not model.cfg.refine_passes or args.passes < 1:
        raise SystemExit(f"{args.model}: needs a model with a refiner and passes >= 1 (it has {model.cfg.refine_passes}, asked {args.passes})")
    new = PriSMONet(replace(model.cfg, refine_passes=args.passes), prior=model.prior)
    new.load_state_dict(model.state_dict())
    Path(args.out).mkdir(parents=True, exist_ok=True)
    record = {k: v for k, v in info.items() if k not in ("model", "prior_fingerprint")}
    save_model(new.eval(), Path(args.out) / "model", {**record, "refine_passes_from": {"source": str(args.model), "passes": model.cfg.refine_passes}})
    print(f"wrote {args.out}/model.safetensors + model.json: {model.cfg.refine_passes} -> {args.passes} refinement passes")


if __name__ == "__main__":
    main()
