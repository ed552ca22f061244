"""Does the fit score pay for a category's true shape, and which part of the pose must be right for it to?

    python3 scripts/pose_shape_truth.py shipped data/clevr3 --split val --limit 96 --category 2

For every true object of the category (2: the Clevr cubes) that a slot takes (paired as L_pose pairs them: Hungarian on
position; no mask is read), the slot is given the object's own prior code and, one part at a time, the object's true
yaw, scale and position; each variant is scored against the input RGB-D with the search's ``fit_score`` (colour MSE +
0.1 x depth L1) and compared with the encoder's own slot. Then whole scenes: the encoder, the search, and the true poses
with the encoder's codes, with the true codes for the category, and with every object's true code.

It answers where a shape is lost (EVALUATION.md, session 74): if the true code at the true pose fits better than the
encoder's latent, the objective pays for it and the encoder sits in a local minimum; the part-by-part table says which
part of the pose it is held by. Uses the data's true poses and shape ids: a diagnostic, not an inference mode.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from dataclasses import replace

import numpy as np
import torch

PARTS = ("encoder's pose", "+ true yaw", "+ true scale", "+ true position", "+ true yaw and scale", "all true")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run")
    ap.add_argument("data")
    ap.add_argument("--split", default="val")
    ap.add_argument("--limit", type=int, default=96)
    ap.add_argument("--batch", type=int, default=16)
    ap.add_argument("--category", type=int, default=2, help="the prior's category id (Clevr: 0 sphere, 1 cylinder, 2 cube)")
    ap.add_argument("--library", default="clevr", help="the shape library whose yaw periods the true poses take")
    ap.add_argument("--figure", metavar="PNG", help="also draw the first --figure-rows objects: the input, the encoder's "
                    "render, and the true code with the encoder's pose, with the true yaw and scale, and with the whole true pose")
    ap.add_argument("--figure-rows", type=int, default=6)
    ap.add_argument("--best-code", action="store_true",
                    help="also draw every matched object, of every category, with each of the prior's codes at the true poses, "
                         "and tabulate which code fits best (slower: one scene render per code and object)")
    args = ap.parse_args(argv)
    from prismonet.threads import use_free_cores

    if argv is None:  # the command line; a caller passing argv (a test) keeps its own threads
        use_free_cores(exit_on_error=True)  # the cores others leave free; PRISMONET_THREADS=N to choose
    if args.limit <= 0 or args.batch <= 0 or args.figure_rows <= 0:
        print("pose_shape_truth: error: --limit, --batch and --figure-rows must be positive", file=sys.stderr)
        return 2
    from prismonet.data.dataset import SceneDataset
    from prismonet.model.fit_score import fit_score
    from prismonet.model.io import load_model
    from prismonet.model.pose_targets import match_slots, posed_at_truth
    from prismonet.model.refine import render_latents
    from prismonet.model.search import SearchConfig, search_latents
    from prismonet.render import SceneParams
    from prismonet.shapes.symmetry import library_yaw_periods

    try:  # ValueError covers the checkpoint's, the dataset's and the shape library's errors
        model, _ = load_model(args.run)
        ds = SceneDataset(args.data, args.split)
        periods = library_yaw_periods(args.library)
    except (ValueError, FileNotFoundError) as e:
        print(f"pose_shape_truth: error: {str(e).splitlines()[0]}", file=sys.stderr)
        return 2
    codes, cats = model.prior.latents.detach(), torch.tensor(model.prior.category_ids)
    if args.category not in set(cats.tolist()):
        print(f"pose_shape_truth: error: the prior has no category {args.category} (it has {sorted(set(cats.tolist()))})", file=sys.stderr)
        return 2
    n = min(args.limit, len(ds))
    rows, ratio, figure = [], [], []
    own_nearest, best = [], {c: [] for c in sorted(set(cats.tolist()))}  # per category: (best code's category, best is own)
    scenes = {k: [] for k in ("encoder", "search (R = 3)", "true poses, encoder codes", "true poses, true codes for the category",
                              "true poses, every object's code")}
    with torch.no_grad():
        for s in range(0, n, args.batch):
            b = ds.batch(list(range(s, min(s + args.batch, n))))
            out = model(b.rgb, b.K, b.T_world_cam, b.ground_z)
            H, W = b.rgb.shape[-2:]

            every = torch.arange(len(b))

            def score(p, idx=every, b=b, out=out, images=False):
                """``fit_score`` of slots ``p``, drawn for the scenes ``b[idx]`` (a scene may come more than once); with
                ``images`` also the drawn images."""
                o = render_latents(model, p, out.latents.bg_color[idx], b.K[idx], b.T_world_cam[idx], b.ground_z[idx], H, W)
                sc = fit_score(o.composite.image, o.composite.depth, b.rgb[idx], b.depth[idx])
                return (sc, o.composite.image) if images else sc

            pe = out.latents.params
            pt, _ = posed_at_truth(pe, b, periods)
            base = fit_score(out.composite.image, out.composite.depth, b.rgb, b.depth)
            z_cat, z_all = pt.z_sh.clone(), pt.z_sh.clone()
            Kslots = pe.scale.shape[1]
            for i in range(len(b)):
                slots, objs = match_slots(pe.position[i], b.obj_position[i], torch.arange(Kslots), torch.arange(int(b.obj_count[i])))
                for k, g in zip(slots.tolist(), objs.tolist()):
                    sid = int(b.obj_shape[i, g])
                    z_all[i, k] = codes[sid]
                    if args.best_code:  # every code of the prior on this object, every object at its true pose
                        idx = torch.full((len(codes),), i)
                        q = SceneParams(*(None if t is None else t[idx].clone() for t in
                                          (pt.z_sh, pe.z_tex, pt.position, pt.cos_sin, pt.scale, pe.axis, pt.active)))
                        q.z_sh[:, k] = codes
                        c = int(score(q, idx).argmin())
                        best[int(cats[sid])].append((int(cats[c]) == int(cats[sid]), c == sid))
                    if int(cats[sid]) != args.category:
                        continue
                    same = torch.nonzero(cats == args.category)[:, 0]
                    own_nearest.append(int(same[(codes[same] - pe.z_sh[i, k]).norm(dim=1).argmin()]) == sid)
                    z_cat[i, k] = codes[sid]
                    ratio.append(float(pt.scale[i, k] / pe.scale[i, k]))
                    # the six variants of scene i, drawn as one batch of six copies of it
                    idx = torch.full((len(PARTS),), i)
                    q = SceneParams(*(None if t is None else t[idx].clone() for t in
                                      (pe.z_sh, pe.z_tex, pe.position, pe.cos_sin, pe.scale, pe.axis, pe.active)))
                    q.z_sh[:, k] = codes[sid]
                    for v, on in enumerate(((0, 0, 0), (1, 0, 0), (0, 1, 0), (0, 0, 1), (1, 1, 0), (1, 1, 1))):
                        for flag, name in zip(on, ("cos_sin", "scale", "position")):
                            if flag:
                                getattr(q, name)[v, k] = getattr(pt, name)[i, k]
                    sc, drawn = score(q, idx, images=True)
                    rows.append((sc - base[i]).tolist())
                    if args.figure and len(figure) < args.figure_rows:
                        figure.append((b.rgb[i], out.composite.image[i], float(base[i]), drawn, sc.tolist()))
            scenes["encoder"].append(base)
            found = search_latents(model, out, b, SearchConfig())
            scenes["search (R = 3)"].append(fit_score(found.composite.image, found.composite.depth, b.rgb, b.depth))
            scenes["true poses, encoder codes"].append(score(pt))
            scenes["true poses, true codes for the category"].append(score(replace(pt, z_sh=z_cat)))
            scenes["true poses, every object's code"].append(score(replace(pt, z_sh=z_all)))
    if args.figure and figure:
        print(f"wrote {_figure(figure, args.figure)}")
    a = np.array(rows).reshape(-1, len(PARTS))
    print(f"{n} scenes of {args.data} [{args.split}], {args.run}: {len(a)} objects of category {args.category}; "
          f"true / predicted scale, median {np.median(ratio) if ratio else float('nan'):.3f}")
    print("\nThe true code with the encoder's pose and parts of the true pose: share of objects it fits better than the encoder's slot")
    print("| " + " | ".join(PARTS) + " |")
    print("|" + "---|" * len(PARTS))
    print("| " + " | ".join(f"{np.mean(a[:, j] < 0):.3f}" for j in range(len(PARTS))) + " |")
    print("| " + " | ".join(f"median {np.median(a[:, j]):+.4f}" for j in range(len(PARTS))) + " |")
    sc = {k: torch.cat(v).numpy() for k, v in scenes.items()}
    print(f"\nThe category's code nearest to the slot's latent is the object's own code: {np.mean(own_nearest):.3f} "
          f"(of {len(own_nearest)}; the code a shape trial tries)")
    if args.best_code:
        print("\nAt the true poses, the prior's code that fits each object best: share of the right category, and the object's own code")
        print("| category | objects | right category | own code |")
        print("|---|---|---|---|")
        for c, v in best.items():
            if v:
                a_ = np.array(v)
                print(f"| {c} | {len(a_)} | {a_[:, 0].mean():.3f} | {a_[:, 1].mean():.3f} |")
    print("\nWhole scenes: mean fit score (lower is better), and the share of scenes below the search's")
    print("| " + " | ".join(sc) + " |")
    print("|" + "---|" * len(sc))
    print("| " + " | ".join(f"{v.mean():.4f}" for v in sc.values()) + " |")
    print("| " + " | ".join(f"{np.mean(v < sc['search (R = 3)']):.3f}" for v in sc.values()) + " |")
    return 0


def _figure(figure, path: str):
    """One row per object: the input, the encoder's render and three of the variants, each labelled with its fit score."""
    from prismonet.files import write_image
    from prismonet.viz.decomposition import labelled_panel
    from prismonet.viz.mask_comparison import chw_to_u8, panel_grid

    size, shown = (128, 128), (0, 4, 5)  # the true code at the encoder's pose, + true yaw and scale, all true
    names = ("true code", "+ true yaw, scale", "all true")
    grid = []
    for rgb, enc, enc_score, drawn, scores in figure:
        tiles = [labelled_panel(chw_to_u8(rgb.numpy()), "input", size), labelled_panel(chw_to_u8(enc.numpy()), f"encoder {enc_score:.4f}", size)]
        tiles += [labelled_panel(chw_to_u8(drawn[v].numpy()), f"{name} {scores[v]:.4f}", size) for v, name in zip(shown, names)]
        grid.append(tiles)
    return write_image(Path(path), panel_grid(grid)[..., ::-1])  # RGB -> OpenCV's BGR


if __name__ == "__main__":
    raise SystemExit(main())
