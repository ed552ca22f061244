"""What a scene model could reach at most with each of several priors of one setting (issue 22).

    python3 scripts/prior_reach.py data/furniture/chairs chairs runs/s59/chairs_prior_ft/prior --samples 32 [--scenes 64]

Renders the first ``--scenes`` validation scenes of the setting's dataset with their true poses and each object's
own training code of the prior (``prior_sweep.py``'s true-pose render: 2 bisection steps, the prior's box) and
prints, per prior and samples per ray, the share of objects whose mask reaches IoU 0.5 with the truth (the most an
AP0.5 can find), their mean IoU, the foreground IoU and the foreground depth RMSE. The priors must have been
trained on the setting's seen shapes, in its order (a shipped prior's name or a path stem).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("setting", help="a folder made by 'prismonet shapes import-furniture'")
    ap.add_argument("priors", nargs="+", help="shipped prior names or path stems")
    ap.add_argument("--samples", default="32", help="comma-separated samples per ray")
    ap.add_argument("--scenes", type=int, default=64)
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args(argv)

    from prior_sweep import _scenes_of, _true_pose_render

    from prismonet.render import RenderSettings
    from prismonet.shapes.prior import load_prior

    try:
        priors = [(name, load_prior(name)) for name in args.priors]
    except (FileNotFoundError, ValueError) as e:
        print(f"prior_reach: error: {e}", file=sys.stderr)
        return 2
    if _scenes_of(args.setting) is None:
        print(f"prior_reach: error: no scenes of {args.setting} under data/ (prismonet data clevr --shapes {args.setting})", file=sys.stderr)
        return 2
    torch.set_num_threads(args.threads)
    samples = [int(s) for s in args.samples.split(",")]
    fit = _true_pose_render(args.setting, args.scenes)
    print(f"| {Path(args.setting).name}, first {args.scenes} val scenes, true poses and codes | samples | objects at IoU >= 0.5 "
          "| mean object IoU | foreground IoU | foreground depth RMSE |")
    print("|---|---|---|---|---|---|")
    for name, prior in priors:
        for n in samples:
            fg, ious, rmse = fit(prior, RenderSettings(refine_steps=2, samples=n, box=prior.bounds))
            print(f"| {name} | {n} | {(ious >= 0.5).mean():.3f} | {ious.mean():.3f} | {fg:.3f} | {rmse:.3f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
