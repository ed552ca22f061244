"""Copy a pre-trained shape prior into the package as a named prior, with its meshes' attributions.

    python3 scripts/ship_prior.py runs/prior_sweep/cars_w64/prior data/furniture/cars cars

Writes ``prismonet/assets/NAME_prior.safetensors`` + ``.json`` (with the object-frame ``bounds`` of the
setting's seen meshes, for priors trained before pre-training recorded them) and
``prismonet/assets/NAME_prior_SOURCES.md``: every mesh the prior learnt, its creator, licence and origin
(the CC-BY models require the attribution). ``load_prior(NAME)`` and ``ModelConfig(prior=NAME)`` then
find it (``prismonet.assets.PRIORS``).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def main(argv: list[str] | None = None) -> int:
    from prismonet.assets import PRIORS, asset_path
    from prismonet.shapes.normalize import shape_bounds
    from prismonet.shapes.pretrain import load_shape_set
    from prismonet.shapes.prior import load_prior

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("prior", help="stem of the pre-trained prior (PRIOR.safetensors + PRIOR.json)")
    ap.add_argument("setting", help="the folder made by 'prismonet shapes import-furniture' it was trained on")
    ap.add_argument("name", help=f"the prior's name in prismonet.assets.PRIORS ({', '.join(PRIORS)})")
    args = ap.parse_args(argv)
    if args.name not in PRIORS or args.name == "clevr":
        print(f"error: add {args.name!r} to prismonet.assets.PRIORS first (as '{args.name}_prior')", file=sys.stderr)
        return 2
    prior = load_prior(args.prior, frozen=False)
    shapes = load_shape_set(args.setting)
    if list(prior.shape_names) != [Path(n).stem for n in shapes.names]:
        print(f"error: {args.prior} was not trained on the seen meshes of {args.setting}", file=sys.stderr)
        return 2
    prior.info.setdefault("bounds", shape_bounds(shapes.meshes))
    stem = asset_path(PRIORS[args.name])
    prior.save(stem)
    models = [m for m in json.loads((Path(args.setting) / "models.json").read_text())["models"] if m["split"] == "seen"]
    lines = [f"# Sources of the `{args.name}` shape prior",
             "",
             f"The prior `{stem.name}` (a DeepSDF auto-decoder) was pre-trained on the following {len(models)} meshes,",
             "imported from Debian's `sweethome3d-furniture` package (Sweet Home 3D's free furniture libraries) by",
             "`prismonet shapes import-furniture`: normalised, decimated and re-coloured. The weights are derived",
             "from them; the CC-BY 3.0 models are attributed here as their licence requires",
             "(https://creativecommons.org/licenses/by/3.0/); CC0 models need no attribution and are listed too.",
             "",
             "| mesh | title | creator | licence | library | catalogue id |",
             "|---|---|---|---|---|---|"]
    for m in models:
        src = m.get("source", {})
        lines.append(f"| {m['name']} | {m.get('title', '')} | {m.get('creator', '')} | {m.get('licence', '')} | "
                     f"{src.get('library', '')} | {src.get('id', '')} |")
    asset_path(f"{PRIORS[args.name]}_SOURCES.md").write_text("\n".join(lines) + "\n")
    print(f"shipped {stem}.safetensors (+ .json, _SOURCES.md): {len(models)} meshes, bounds {prior.info['bounds']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
