"""``prismonet export``, ``prismonet edit`` and ``prismonet views``: a latent scene (inferred, or saved
by ``reconstruct``) as meshes and point clouds, edited, or rendered from new viewpoints."""

from __future__ import annotations

import argparse
from pathlib import Path

from prismonet.cli.common import floats
from prismonet.files import write_image


def _pair(text: str, what: str) -> tuple[int, int]:
    try:
        i, j = (int(v) for v in text.split(","))
    except ValueError:
        raise ValueError(f"{what}: expected two object indices like 0,2, got {text!r}") from None
    return i, j


def _obj_value(text: str, what: str) -> tuple[int, str]:
    """``K:VALUE`` -> (K, VALUE)."""
    k, sep, value = text.partition(":")
    if not sep or not k.strip().lstrip("-").isdigit():
        raise ValueError(f"{what}: expected OBJECT:VALUE like 1:0.5,0,0.35, got {text!r}")
    return int(k), value


def scene_from_args(args, model):
    """The latent scene of ``--scene FILE``, or inferred from ``--data DIR --index I``; plus the
    input RGB-D when there is one."""
    import torch

    from prismonet.model.io import prior_fingerprint
    from prismonet.scene import LatentScene

    if (args.scene is None) == (args.data is None):
        raise ValueError("give either --scene FILE or --data DIR (with --index)")
    if args.scene is not None:
        return LatentScene.load(args.scene), None
    from prismonet.data.dataset import SceneDataset

    ds = SceneDataset(args.data, split=args.split)
    if not 0 <= args.index < len(ds):
        raise ValueError(f"--index: {args.data} has scenes 0..{len(ds) - 1}, got {args.index}")
    b = ds.batch([args.index])
    with torch.no_grad():
        out = model(b.rgb, b.K, b.T_world_cam, b.ground_z, num_slots=args.objects)
    scene = LatentScene.from_output(out, b, 0, prior_fingerprint(model.prior))
    depth = b.depth[0] if bool((b.depth > 0).any()) else None
    return scene, (b.rgb[0], depth) if depth is not None else None


def cmd_export(args) -> int:
    from prismonet.model.io import load_model
    from prismonet.scene.export import export_scene

    model, _ = load_model(args.model, num_slots=args.objects)
    scene, rgbd = scene_from_args(args, model)
    written = export_scene(model, scene, args.out, args.format, args.resolution, rgbd)
    for name, path in written.items():
        print(f"  {name:16s} {path}")
    print(f"exported {scene.num_objects} objects to {args.out}")
    return 0


def apply_edits(scene, ops, load_scene):
    """Apply ``ops``, a list of ``(kind, text)`` from the command line, in order."""
    from prismonet.scene import edit

    for kind, text in ops:
        if kind == "remove":
            scene = edit.remove(scene, int(text))
        elif kind == "move":
            k, v = _obj_value(text, "--move")
            scene = edit.move(scene, k, position=floats(v, 3, "--move"))
        elif kind == "shift":
            k, v = _obj_value(text, "--shift")
            scene = edit.move(scene, k, delta=floats(v, 3, "--shift"))
        elif kind == "turn":
            k, v = _obj_value(text, "--turn")
            scene = edit.move(scene, k, yaw_deg=floats(v, 1, "--turn")[0])
        elif kind == "swap_places":
            scene = edit.swap_places(scene, *_pair(text, "--swap-places"))
        elif kind in ("swap_shape", "swap_texture"):
            scene = edit.swap_latents(scene, *_pair(text, f"--{kind.replace('_', '-')}"), which=kind.split("_")[1])
        elif kind == "add":
            path, sep, k = text.rpartition(":")
            if not sep or not k.isdigit():
                raise ValueError(f"--add: expected SCENE.json:OBJECT, got {text!r}")
            scene = edit.add(scene, load_scene(path), int(k))
        else:  # pragma: no cover - argparse limits the kinds
            raise ValueError(f"unknown edit {kind}")
    return scene


def cmd_edit(args) -> int:
    from prismonet.model.io import load_model
    from prismonet.scene import LatentScene, edit
    from prismonet.scene.novel_view import to_uint8

    if not args.ops:
        raise ValueError("no edit given (use --remove, --move, --shift, --turn, --swap-places, --swap-shape, --swap-texture, --add)")
    model, _ = load_model(args.model)
    scene = apply_edits(LatentScene.load(args.scene), args.ops, LatentScene.load)
    pairs = edit.intersection_pairs(model, scene)
    score = sum(pairs.values())
    print(f"L_int of the edited scene: {score:.5f}" + "".join(f"\n  objects {i}-{j}: {v:.5f}" for (i, j), v in pairs.items() if v > 0))
    if not args.allow_intersections:
        edit.checked(model, scene, args.tolerance)
    print(f"wrote {scene.save(args.out)} ({scene.num_objects} objects)")
    if args.render:
        img = to_uint8(scene.render(model)[0].image[0])
        Path(args.render).parent.mkdir(parents=True, exist_ok=True)
        write_image(args.render, img[..., ::-1])
        print(f"wrote {args.render}")
    return 0


def cmd_views(args) -> int:
    import torch

    from prismonet.geometry.camera import Camera, look_at
    from prismonet.model.io import load_model
    from prismonet.scene import LatentScene
    from prismonet.scene.novel_view import render_orbit, render_view, to_uint8

    model, _ = load_model(args.model)
    scene = LatentScene.load(args.scene)
    if args.eye is not None:
        eye = torch.tensor(floats(args.eye, 3, "--eye"))
        target = torch.tensor(floats(args.target, 3, "--target"))
        cam = scene.camera.resized(args.size, args.size)
        cam = Camera(cam.K, look_at(eye, target), cam.height, cam.width)
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        write_image(out / "view.png", to_uint8(render_view(model, scene, cam, args.supersample)[0])[..., ::-1])
        print(f"wrote {out / 'view.png'}")
        return 0
    pngs, gif = render_orbit(model, scene, args.out, args.frames, args.size, args.fps, progress=not args.quiet,
                             supersample=args.supersample)
    print(f"wrote {len(pngs)} views and {gif}")
    return 0


class _Op(argparse.Action):
    """Collect edits in command-line order as ``(kind, value)``."""

    def __call__(self, parser, namespace, values, option_string=None):
        ops = list(getattr(namespace, "ops", None) or [])
        ops.append((self.dest, values))
        namespace.ops = ops


def add_parsers(sub) -> None:
    from prismonet.assets import DEFAULT_NAME
    from prismonet.files import MAX_IMAGE_SIDE, MAX_MESH_RESOLUTION, arg_float, arg_int

    ex = sub.add_parser("export", help="meshes (PLY/OBJ/GLB) and point clouds of an inferred or saved scene")
    ex.add_argument("--model", default="shipped", help=f"run folder or model stem (default: shipped, {DEFAULT_NAME})")
    ex.add_argument("--scene", help="a latent-scene JSON (from reconstruct, export or edit)")
    ex.add_argument("--data", help="or infer the scene from this dataset")
    ex.add_argument("--index", type=int, default=0, help="scene index in --data")
    ex.add_argument("--split", default="test")
    ex.add_argument("--objects", type=int, help="recurrent steps (default: as trained)")
    ex.add_argument("--format", default="ply", choices=["ply", "obj", "glb"])
    ex.add_argument("--resolution", type=arg_int(8, MAX_MESH_RESOLUTION), default=48, help="marching-cubes grid per object")
    ex.add_argument("--out", required=True)
    ex.set_defaults(func=cmd_export, outputs=[("out", "dir")])

    ed = sub.add_parser("edit", help="edit a latent scene; edits whose objects intersect (L_int) are rejected")
    ed.add_argument("scene", help="latent-scene JSON")
    ed.add_argument("--out", required=True, help="the edited scene's JSON")
    ed.add_argument("--model", default="shipped")
    ed.set_defaults(ops=[])
    ed.add_argument("--remove", dest="remove", action=_Op, metavar="K")
    ed.add_argument("--move", dest="move", action=_Op, metavar="K:X,Y,Z", help="place object K at X,Y,Z")
    ed.add_argument("--shift", dest="shift", action=_Op, metavar="K:DX,DY,DZ")
    ed.add_argument("--turn", dest="turn", action=_Op, metavar="K:DEG", help="set object K's yaw in degrees")
    ed.add_argument("--swap-places", dest="swap_places", action=_Op, metavar="I,J")
    ed.add_argument("--swap-shape", dest="swap_shape", action=_Op, metavar="I,J")
    ed.add_argument("--swap-texture", dest="swap_texture", action=_Op, metavar="I,J")
    ed.add_argument("--add", dest="add", action=_Op, metavar="SCENE.json:K", help="copy object K of another scene")
    ed.add_argument("--allow-intersections", action="store_true", help="write the scene even if objects intersect")
    ed.add_argument("--tolerance", type=float, default=1e-3, help="L_int above this is an intersection")
    ed.add_argument("--render", help="also render the edited scene to this PNG")
    ed.set_defaults(func=cmd_edit, outputs=[("out", "file"), ("render", "image")])

    vw = sub.add_parser("views", help="render a latent scene from new viewpoints: an orbit (PNGs + GIF) or one pose")
    vw.add_argument("scene", help="latent-scene JSON")
    vw.add_argument("--out", required=True)
    vw.add_argument("--model", default="shipped")
    vw.add_argument("--frames", type=arg_int(1, 3600), default=24)
    vw.add_argument("--size", type=arg_int(8, MAX_IMAGE_SIDE), default=128, help="square image side")
    vw.add_argument("--fps", type=arg_float(0.1, 240), default=12.0)
    vw.add_argument("--eye", help="X,Y,Z: one view from here instead of the orbit")
    vw.add_argument("--target", default="0,0,0", help="X,Y,Z the --eye view looks at")
    vw.add_argument("--supersample", type=arg_int(1, 8), default=1, metavar="S",
                    help="anti-aliased images: S x S rays per pixel, averaged (default 1)")
    vw.add_argument("--quiet", action="store_true")
    vw.set_defaults(func=cmd_views, outputs=[("out", "dir")])
