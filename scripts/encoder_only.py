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

from prismonet.model.color_step_fit import without_color_step
from prismonet.model.io import CheckpointError, load_model, save_model
from prismonet.model.refiner_fit import with_refiner


def encoder_only(model):
    """``model`` without its colour step and refiner (the same object when it has neither): the project's own
    ``without_color_step``, then ``with_refiner`` with no passes (the inference-only refiner settings back at their
    defaults, which ``ModelConfig`` requires without passes)."""
    if model.cfg.color_step:
        model = without_color_step(model)
    if model.cfg.refine_passes:
        model = with_refiner(model, 0, refiner_keep_logit=0.0, refiner_snap_shape=False)
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
    save_model(enc, out / "model", {**info, "encoder_of": str(args.model)})
    print(f"wrote {out}/model.safetensors + model.json: the encoder of {args.model} "
          f"({sum(p.numel() for p in enc.parameters()):,} weights)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
