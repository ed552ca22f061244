"""Write a copy of a trained model that renders with another shape prior (the same encoder and refiner weights).

    python3 scripts/swap_prior.py chairs_refiner runs/s59/chairs_prior_ft/prior runs/s59/chairs_refiner_ft

Meant for a prior fine-tuned from the model's own with its codes held (``shapes pretrain --set init=chairs --set
lr_codes=0``): the encoder's shape codes then name the same shapes, drawn better. Any other prior of the same latent
size loads too, and the copy's record says which prior it had (``prior_swapped_from``); whether the result is any
good is for ``prismonet evaluate`` to say.
"""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

from prismonet.model.io import load_model, prior_fingerprint, save_model
from prismonet.model.prismonet import PriSMONet
from prismonet.shapes.prior import load_prior


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("model", help="run folder, .safetensors, or a shipped name")
    ap.add_argument("prior", help="a shipped prior's name or a path stem (PRIOR.safetensors + PRIOR.json)")
    ap.add_argument("out", help="new run folder")
    args = ap.parse_args(argv)
    try:
        model, info = load_model(args.model)
        prior = load_prior(args.prior)
    except (FileNotFoundError, ValueError) as e:  # CheckpointError is a ValueError
        raise SystemExit(f"swap_prior: error: {e}") from None
    if prior.latents.shape[1] != model.prior.latents.shape[1]:
        raise SystemExit(f"{args.prior}: latent size {prior.latents.shape[1]}, the model's prior has {model.prior.latents.shape[1]}")
    new = PriSMONet(replace(model.cfg, prior=str(args.prior)))
    new.load_state_dict(model.state_dict())
    Path(args.out).mkdir(parents=True, exist_ok=True)
    save_model(new.eval(), Path(args.out) / "model", {**info, "prior_swapped_from": {
        "source": str(args.model), "prior": model.cfg.prior, "prior_fingerprint": prior_fingerprint(model.prior)}})
    print(f"wrote {args.out}/model.safetensors + model.json: prior {model.cfg.prior} -> {args.prior}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
