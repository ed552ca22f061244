"""Write a copy of a model whose weights that another model also has are that model's: e.g. a refit encoder and refiner
under a model's colour step, which was fitted on the same kind of slots.

    python3 scripts/swap_weights.py tabletop_keep runs/s69/tt4_keep OUT     # session 69: tt4_keep's weights, tabletop_keep's colour step

Every weight of SOURCE must exist in MODEL with the same shape (else nothing is written); MODEL's own settings
(``model.json``) are kept, and its record names the source (``weights_from``). Run ``prismonet evaluate`` on the copy:
the parts that were not refitted together were not trained together.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from prismonet.model.io import CheckpointError, load_model, save_model


def swap_weights(model, source) -> list[str]:
    """Load every weight of ``source`` into ``model`` (in place); returns their names. Raises ``ValueError`` naming the
    first weight ``model`` lacks or holds in another shape, before changing anything."""
    mine, theirs = model.state_dict(), source.state_dict()
    for k, v in theirs.items():
        if k not in mine:
            raise ValueError(f"the model has no weight {k!r} (the source's parts must be the model's)")
        if mine[k].shape != v.shape:
            raise ValueError(f"{k!r}: shape {tuple(v.shape)} in the source, {tuple(mine[k].shape)} in the model")
    mine.update(theirs)
    model.load_state_dict(mine)
    return list(theirs)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("model", help="run folder, .safetensors, or a shipped name: its settings and the weights the source lacks")
    ap.add_argument("source", help="the model whose weights replace the model's")
    ap.add_argument("out", help="new run folder (model.json + model.safetensors)")
    args = ap.parse_args(argv)
    try:
        model, info = load_model(args.model)
        source, _ = load_model(args.source)
        names = swap_weights(model, source)
    except (CheckpointError, ValueError) as e:
        raise SystemExit(f"swap_weights: error: {e}") from None
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    save_model(model, out / "model",
               {**info, "weights_from": f"{args.source} ({len(names)} tensors) into {args.model}"})
    parts = sorted({n.split(".")[0] for n in names})
    print(f"wrote {out}/model.safetensors + model.json: {args.model} with the {', '.join(parts)} weights of {args.source}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
