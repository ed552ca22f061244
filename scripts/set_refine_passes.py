"""Write a copy of a trained model that applies its learnt refiner a different number of times (the same weights).

    python3 scripts/set_refine_passes.py runs/clevr3_glimpse 2 runs/clevr3_glimpse_2pass
    python3 scripts/set_refine_passes.py runs/s48/a18_keep_fit 2 runs/s48/a18_keep_re2 --reanchor 2   # anchored models

``--reanchor N`` also sets ``reanchor_steps`` (``ModelConfig``: encoder steps after refinement, into empty slots,
anchored where the model is);
``--reanchor-keep X`` sets ``reanchor_keep_logit``, the keep logit a re-anchored slot must beat (``none``: never
dropped); ``--anchor-shade K`` sets ``anchor_shade_min``, the least even darkening the anchor rule reads as a cast
shadow (``none``: off, as trained); ``--anchor-gray T`` sets ``anchor_gray_tol``, the luminance difference the anchor
rule reads as unexplained in a greyscale image (``none``: grey images read as colour ones); ``--anchor-color T`` sets
``anchor_color_tol``, the per-channel colour difference the anchor rule reads as unexplained in a colour image.

    python3 scripts/set_refine_passes.py tabletop_keep 2 runs/tabletop_keep_noshade --anchor-shade none   # session 48's

``--keep-passes N`` sets ``refiner_keep_passes`` (the keep output drops slots in the first N passes only; ``none``: every
pass), ``--keep-logit X`` sets ``refiner_keep_logit`` (the bar a keep logit must beat in every pass; default 0) and
``--rescue PX`` sets ``refiner_rescue_px`` (a slot the keep output dropped is taken back where it would show at least PX
pixels the kept slots leave unexplained; ``prismonet.model.rescue``), and ``--snap-shapes on`` sets ``refiner_snap_shape`` (each pass ends with every shape latent on the prior's nearest
training code):

    python3 scripts/set_refine_passes.py tableware_pose_keep 1 runs/s65/tpk_snap --snap-shapes on --keep-logit 1   # session 65's

The copy's record keeps the source's and notes the change (``refine_passes_from``; a copy of a copy keeps the earlier
change under ``before``); the passes were chosen on the validation split (EVALUATION.md, "Session 46").
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
                    help="also set reanchor_steps to N: N more encoder steps after refinement, into empty slots "
                         "(anchored where the model is)")
    ap.add_argument("--reanchor-keep", default=None, metavar="X",
                    help="also set reanchor_keep_logit: a re-anchored slot is dropped where its keep logit is <= X "
                         "('none': never dropped)")
    ap.add_argument("--anchor-shade", default=None, metavar="K",
                    help="also set anchor_shade_min: an evenly darkened composition by a factor >= K counts as a shadow "
                         "('none': off)")
    ap.add_argument("--keep-logit", type=float, default=None, metavar="X",
                    help="also set refiner_keep_logit: in every pass a slot is dropped where its keep logit is <= X (default 0)")
    ap.add_argument("--keep-passes", default=None, metavar="N",
                    help="also set refiner_keep_passes: the keep output drops slots in the first N passes only "
                         "('none': every pass)")
    ap.add_argument("--rescue", type=int, default=None, metavar="PX",
                    help="also set refiner_rescue_px: after the passes a dropped slot is taken back where it would show "
                         "at least PX pixels the kept slots leave unexplained, half of all it shows (0: off)")
    ap.add_argument("--snap-shapes", choices=("on", "off"), default=None,
                    help="also set refiner_snap_shape: after each pass every shape latent becomes the prior's nearest training code")
    ap.add_argument("--anchor-gray", default=None, metavar="T",
                    help="also set anchor_gray_tol: in a greyscale image, a luminance miss above T is unexplained and "
                         "nothing reads as a shadow ('none': off)")
    ap.add_argument("--anchor-color", type=float, default=None, metavar="T",
                    help="also set anchor_color_tol: in a colour image, a per-channel colour miss above T is unexplained")
    args = ap.parse_args()
    model, info = load_model(args.model)
    if not model.cfg.refine_passes or args.passes < 1:
        raise SystemExit(f"{args.model}: needs a model with a refiner and passes >= 1 (it has {model.cfg.refine_passes}, asked {args.passes})")
    fields = {"refine_passes": args.passes}
    if args.reanchor is not None:
        if args.reanchor < 0:
            raise SystemExit(f"{args.model}: --reanchor needs N >= 0, asked {args.reanchor}")
        fields["reanchor_steps"] = args.reanchor
    if args.reanchor_keep is not None:
        fields["reanchor_keep_logit"] = number_or_none("--reanchor-keep", args.reanchor_keep)
    if args.keep_logit is not None:
        if not model.cfg.refiner_keep:
            raise SystemExit(f"{args.model}: --keep-logit needs a refiner with a keep output")
        fields["refiner_keep_logit"] = args.keep_logit
    if args.keep_passes is not None:
        n = number_or_none("--keep-passes", args.keep_passes)
        if n is not None and not n.is_integer():
            raise SystemExit(f"--keep-passes: expected a whole number or 'none', got {args.keep_passes!r}")
        fields["refiner_keep_passes"] = None if n is None else int(n)
    if args.rescue is not None:
        if not model.cfg.refiner_keep:
            raise SystemExit(f"{args.model}: --rescue needs a refiner with a keep output")
        fields["refiner_rescue_px"] = args.rescue
    if args.snap_shapes is not None:
        fields["refiner_snap_shape"] = args.snap_shapes == "on"
    if args.anchor_shade is not None:
        if not model.cfg.anchor:
            raise SystemExit(f"{args.model}: --anchor-shade needs an anchored model")
        fields["anchor_shade_min"] = number_or_none("--anchor-shade", args.anchor_shade)
    if args.anchor_gray is not None:
        if not model.cfg.anchor:
            raise SystemExit(f"{args.model}: --anchor-gray needs an anchored model")
        fields["anchor_gray_tol"] = number_or_none("--anchor-gray", args.anchor_gray)
    if args.anchor_color is not None:
        if not model.cfg.anchor:
            raise SystemExit(f"{args.model}: --anchor-color needs an anchored model")
        fields["anchor_color_tol"] = args.anchor_color
    try:
        cfg = replace(model.cfg, **fields)
    except ValueError as e:
        raise SystemExit(f"{args.model}: {e}") from None
    new = PriSMONet(cfg, prior=model.prior)
    new.load_state_dict(model.state_dict())
    Path(args.out).mkdir(parents=True, exist_ok=True)
    before = {k: getattr(model.cfg, k) for k in fields}  # the source's values of what changed
    change = {"source": str(args.model), "passes": before.pop("refine_passes"), **before}
    if "refine_passes_from" in info:  # the source was itself a copy: keep that change too, as its "before"
        change["before"] = info["refine_passes_from"]
    save_model(new.eval(), Path(args.out) / "model", {**info, "refine_passes_from": change})
    changes = ", ".join(f"{k} {getattr(model.cfg, k)} -> {v}" for k, v in fields.items() if k != "refine_passes")
    print(f"wrote {args.out}/model.safetensors + model.json: {model.cfg.refine_passes} -> {args.passes} refinement passes"
          + (f", {changes}" if changes else ""))


def number_or_none(flag: str, text: str) -> float | None:
    """A flag's value: a number, or ``none``; anything else ends the script with one line."""
    if text.lower() == "none":
        return None
    try:
        return float(text)
    except ValueError:
        raise SystemExit(f"{flag}: expected a number or 'none', got {text!r}") from None


if __name__ == "__main__":
    main()
