"""A copy of a model with some of its ``model.json`` (``ModelConfig``) fields changed: inference settings tried
without training, e.g. more samples per ray.

    python3 scripts/model_variant.py [--shared] MODEL OUT FIELD=JSON [FIELD=JSON ...]
    python3 scripts/model_variant.py chairs_refiner runs/chairs_s48 render_samples=48
    python3 scripts/model_variant.py --shared clevr3_r4 runs/s108/clevr5 num_slots=5

MODEL is a shipped name or a run folder; OUT gets ``model.json`` and ``model.safetensors`` (the weights unchanged),
which ``prismonet evaluate OUT ...`` reads. With ``--shared`` (MODEL a shipped name) OUT gets ``model.json`` alone, which
names MODEL's weights file and its SHA-256 (``"weights_of"``, ``prismonet.model.io.weights_file``): how a model that is
a shipped one with other settings ships without a second copy of the weights (``clevr2``, ``clevr4``, ``clevr5``: the
default's). A MODEL that is itself such a file passes on the name of the model whose file it names.
"""

from __future__ import annotations

import dataclasses
import json
import shutil
import sys
from pathlib import Path


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    shared = "--shared" in argv
    argv = [a for a in argv if a != "--shared"]
    if len(argv) < 3 or any("=" not in a for a in argv[2:]):
        print("model_variant: usage: model_variant.py [--shared] MODEL OUT FIELD=JSON [FIELD=JSON ...]", file=sys.stderr)
        return 2
    from prismonet.assets import named_model
    from prismonet.config import _build
    from prismonet.model.config import ModelConfig

    named = named_model(argv[0])
    p = named or Path(argv[0])
    if shared and named is None:
        print(f"model_variant: error: --shared needs a shipped model's name, got {argv[0]!r}", file=sys.stderr)
        return 2
    stem = p / "model" if p.is_dir() else p.with_suffix("")
    if not stem.with_suffix(".json").is_file():
        print(f"model_variant: error: {stem.with_suffix('.json')}: no such model", file=sys.stderr)
        return 2
    info = json.loads(stem.with_suffix(".json").read_text())
    names = {f.name for f in dataclasses.fields(ModelConfig)}
    for kv in argv[2:]:
        key, value = kv.split("=", 1)
        if key not in names:
            print(f"model_variant: error: {key!r} is not a ModelConfig field", file=sys.stderr)
            return 2
        info["model"][key] = json.loads(value)
    try:
        _build(ModelConfig, info["model"], "model.")  # checks the values as load_model does
    except (TypeError, ValueError) as e:
        print(f"model_variant: error: {e}", file=sys.stderr)
        return 2
    from prismonet.files import write_atomic
    from prismonet.model.io import CheckpointError, weights_file

    try:
        weights = weights_file(stem, info)  # a model that ships as JSON alone: the weights it names
    except CheckpointError as e:
        print(f"model_variant: error: {e}", file=sys.stderr)
        return 2
    out = Path(argv[1])
    out.mkdir(parents=True, exist_ok=True)
    owner = info.pop("weights_of", None)
    if shared:  # name the model whose file holds the weights: MODEL itself, or the one MODEL names in turn
        from prismonet.assets import model_name
        from prismonet.files import sha256_file

        owner = owner["model"] if owner else model_name(argv[0])
        info["weights_of"] = {"model": owner, "sha256": sha256_file(weights)}
    else:
        shutil.copy(weights, out / "model.safetensors")
    write_atomic(out / "model.json", json.dumps(info, indent=1))  # last: a copy cut short has no model.json
    print(f"wrote {out} ({', '.join(argv[2:])})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
