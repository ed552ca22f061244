"""``prismonet shapes``: the DeepSDF shape prior: pre-train it, measure it, extract meshes."""

from __future__ import annotations

import json
from pathlib import Path


def quality_line(r: dict) -> str:
    return (
        f"Chamfer-L1 mean {r['mean_chamfer_l1']:.4f} (max {r['max_chamfer_l1']:.4f}) at marching-cubes resolution "
        f"{r['resolution']}; IoU mean {r['mean_iou']:.4f} (min {r['min_iou']:.4f}) on a {r['iou_resolution']}^3 grid; "
        f"non-empty interpolations {r['interpolation_nonempty']:.0%}"
    )


def cmd_pretrain(args) -> int:
    from prismonet.config import load_config
    from prismonet.shapes.evaluate import evaluate_prior
    from prismonet.shapes.pretrain import PretrainConfig, pretrain

    cfg = load_config(PretrainConfig, args.config, args.set)
    prior = pretrain(cfg, args.out, shape_set=args.shapes, progress=not args.quiet)
    print(f"prior: {Path(args.out) / 'prior.safetensors'} (+ prior.json), {prior.info['train_seconds']:.0f} s of training")
    if not args.no_eval:
        report = evaluate_prior(prior, shape_set=args.shapes, resolution=args.resolution, progress=not args.quiet)
        prior.info["quality"] = {k: v for k, v in report.items() if k != "per_shape"}
        prior.save(Path(args.out) / "prior")
        from prismonet.files import write_atomic

        write_atomic(Path(args.out) / "quality.json", json.dumps(report, indent=2))
        print(quality_line(report))
    return 0


def cmd_eval(args) -> int:
    from prismonet.shapes.evaluate import evaluate_prior
    from prismonet.shapes.prior import load_prior

    report = evaluate_prior(load_prior(args.prior), shape_set=args.shapes, resolution=args.resolution, iou_resolution=args.iou_resolution,
                            progress=not args.quiet)
    if args.json:
        from prismonet.files import write_atomic

        write_atomic(args.json, json.dumps(report, indent=2))
    for row in report["per_shape"]:
        print(f"  {row['shape']:<12} Chamfer-L1 {row['chamfer_l1']:.4f}  IoU {row['iou']:.4f}")
    print(quality_line(report))
    return 0


def cmd_mesh(args) -> int:
    import torch

    from prismonet.cli.common import floats
    from prismonet.shapes.mesh import extract_mesh
    from prismonet.shapes.prior import load_prior

    prior = load_prior(args.prior)
    if args.latent is not None:
        z = torch.tensor(floats(args.latent, prior.latents.shape[1], "--latent"))
    else:
        if not 0 <= args.shape < len(prior.latents):
            raise ValueError(f"--shape: expected 0..{len(prior.latents) - 1}, got {args.shape}")
        z = prior.latents[args.shape]
    mesh = extract_mesh(prior.decoder, z, args.resolution)
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    mesh.export(args.out)
    print(f"wrote {args.out} ({len(mesh.vertices)} vertices, {len(mesh.faces)} faces)")
    return 0


def cmd_import_furniture(args) -> int:
    from prismonet.shapes.furniture import import_setting

    r = import_setting(args.setting, args.out, args.source, args.max_faces, args.seed, progress=not args.quiet)
    print(f"imported {len(r['models'])} {args.setting} models into {args.out} ({r['counts']['seen']} seen, "
          f"{r['counts']['unseen']} unseen; models.json records each source, creator and licence)"
          + (f"; skipped {len(r['skipped'])}: " + "; ".join(f"{s['name']} ({s['reason']})" for s in r["skipped"]) if r["skipped"] else ""))
    return 0


def cmd_blocks(args) -> int:
    from prismonet.shapes.blocks import write_blocks

    r = write_blocks(args.out)
    cats = sorted({m["category"] for m in r["models"]})
    print(f"wrote {len(r['models'])} blocks ({', '.join(cats)}) to {args.out}")
    return 0


def add_parsers(sub) -> None:
    from prismonet.files import MAX_MESH_RESOLUTION, arg_int
    from prismonet.shapes.furniture import MIN_FACES as MIN_IMPORT_FACES

    shapes = sub.add_parser("shapes", help="the DeepSDF shape prior: pre-train, evaluate, extract meshes")
    ssub = shapes.add_subparsers(dest="shapes_command", required=True)
    imp = ssub.add_parser("import-furniture", help="import cars, chairs or a tabletop set from Sweet Home 3D's free furniture (opt-in)")
    imp.add_argument("setting", choices=("cars", "chairs", "tabletop"))
    imp.add_argument("--out", required=True, help="folder for the PLY meshes and models.json")
    imp.add_argument("--source", help="the sweethome3d-furniture .deb (apt-get download sweethome3d-furniture), a folder of "
                                      ".sh3f files, or default: the installed /usr/share/sweethome3d/furniture")
    imp.add_argument("--max-faces", type=arg_int(MIN_IMPORT_FACES), default=5000, help="decimate each mesh towards this many faces")
    imp.add_argument("--seed", type=int, default=0, help="seed of the seen / unseen split")
    imp.add_argument("--quiet", action="store_true")
    imp.set_defaults(func=cmd_import_furniture, outputs=[("out", "dir")])
    blk = ssub.add_parser("blocks", help="write the wooden-block shape set (boxes, hexagonal prisms, wedges) as an import folder")
    blk.add_argument("--out", required=True, help="new folder for the PLY meshes and models.json")
    blk.set_defaults(func=cmd_blocks, outputs=[("out", "new_dir")])
    pre = ssub.add_parser("pretrain", help="pre-train the auto-decoder on a shape set (resumable)")
    pre.add_argument("--out", required=True, help="run folder; rerunning resumes from its checkpoint")
    pre.add_argument("--config", help="JSON file with PretrainConfig fields")
    pre.add_argument("--shapes", default="clevr", help="'clevr' (default) or a folder made by 'shapes import-furniture' or 'shapes blocks' (its seen models)")
    pre.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a field, e.g. decoder.width=128")
    pre.add_argument("--resolution", type=arg_int(8, MAX_MESH_RESOLUTION), default=64, help="marching-cubes resolution of the quality check")
    pre.add_argument("--no-eval", action="store_true")
    pre.add_argument("--quiet", action="store_true")
    pre.set_defaults(func=cmd_pretrain, outputs=[("out", "dir")])

    ev = ssub.add_parser("eval", help="Chamfer-L1 and IoU of a prior on its training shapes")
    ev.add_argument("prior", nargs="?", help="prior path stem (default: the shipped Clevr prior)")
    ev.add_argument("--resolution", type=arg_int(8, MAX_MESH_RESOLUTION), default=64)
    ev.add_argument("--iou-resolution", type=arg_int(8, MAX_MESH_RESOLUTION), default=64,
                    help="grid of the IoU (meshes with holes take the winding number at every point: 32 is 8x cheaper)")
    ev.add_argument("--shapes", default="clevr", help="the prior's training set: 'clevr' (default) or an imported folder")
    ev.add_argument("--json", help="also write the full report here")
    ev.add_argument("--quiet", action="store_true")
    ev.set_defaults(func=cmd_eval, outputs=[("json", "file")])

    me = ssub.add_parser("mesh", help="extract a mesh (PLY/OBJ/GLB by extension) for a training shape or latent")
    me.add_argument("--prior", help="prior path stem (default: the shipped Clevr prior)")
    me.add_argument("--shape", type=int, default=0, help="training shape index")
    me.add_argument("--latent", help="comma-separated latent instead of --shape")
    me.add_argument("--resolution", type=arg_int(8, MAX_MESH_RESOLUTION), default=64)
    me.add_argument("--out", required=True)
    me.set_defaults(func=cmd_mesh, outputs=[("out", "file")])
