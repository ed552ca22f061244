"""Write a copy of a refined model without its learnt refiner and colour step: the encoder alone, which a training
config can start from (``init_from``) to train the encoder on.

    python3 scripts/encoder_only.py chairs_pose_keep gpu_pack_ch/init/chairs_pose_ft3     # session 68's GPU round

A keep-refiner model (``prismonet refiner``) holds its encoder's weights unchanged (the fit freezes them), so the copy is
that encoder: it decodes as the model did with ``refine=False``. Every other weight and setting is the source's; the
copy's record names the source (``encoder_of``).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from prismonet.model.io import CheckpointError, load_model, rebuilt, save_model

LEARNT_PARTS = {"refiner.": {"refine_passes": 0, "refiner_keep_logit": 0.0, "refiner_snap_shape": False},
                "color_step.": {"color_step": False}}
"""The weights' prefix of each learnt part that follows the encoder, and the config fields that turn it off."""


def encoder_only(model):
    """``model`` without its refiner and colour step (the same object when it has neither)."""
    for prefix, fields in LEARNT_PARTS.items():
        if any(k.startswith(prefix) for k in model.state_dict()):
            model = rebuilt(model, prefix, **fields)
    return model


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("model", help="run folder, .safetensors, or a shipped name")
    ap.add_argument("out", help="new run folder (model.json + model.safetensors)")
    args = ap.parse_args(argv)
    try:
        model, info = load_model(args.model)
    except CheckpointError as e:
        raise SystemExit(f"encoder_only: error: {e}") from None
    enc = encoder_only(model)
    if enc is model:
        raise SystemExit(f"encoder_only: error: {args.model} has no refiner or colour step: it is an encoder already")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    save_model(enc, out / "model", {k: v for k, v in info.items() if k not in ("model", "prior_fingerprint")}
               | {"encoder_of": str(args.model)})
    print(f"wrote {out}/model.safetensors + model.json: the encoder of {args.model} "
          f"({sum(p.numel() for p in enc.parameters()):,} weights)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
