"""``prismonet demo``, ``prismonet evaluate`` and ``prismonet reconstruct``: a trained model decomposes
scenes, and the paper's measures. All three take the same test-time step flags
(``prismonet.cli.common.add_inference_args``)."""

from __future__ import annotations

import json
import time
from pathlib import Path

from prismonet.cli.common import add_inference_args, inference_config


def cmd_demo(args) -> int:
    from prismonet.assets import model_name
    from prismonet.demo import format_demo_table, run_demo

    t0 = time.perf_counter()
    cfg = inference_config(args)
    result = run_demo(args.out, args.scenes, args.model, args.data, cfg, progress=not args.quiet, shape_trials=args.shape_trials,
                      trial_grid=args.search_grid)
    print(format_demo_table(result))
    out = Path(args.out)
    print(f"\n{len(result['scenes'])} scenes decomposed by the {model_name(args.model)} model "
          f"in {time.perf_counter() - t0:.1f} s ({result['steps']}{refined_note(result['refine_passes'])})")
    print(f"figures:       {out}/scene_*.png  (input | reconstruction | depth target | depth | instances; each object alone)")
    print(f"latent scenes: {out}/scene_*.json  (prismonet export / edit / views take these)")
    print(f"metrics:       {out / 'metrics.json'}")
    return 0


def refined_note(passes: int) -> str:
    """What a model's own learnt refinement passes (``model.cfg.refine_passes``) add to a description of the
    test-time steps."""
    n = passes
    return f" (the encoder's slots corrected by the model's {n} learnt refinement pass{'es' if n > 1 else ''})" if n else ""


def cmd_evaluate(args) -> int:
    from prismonet.data.dataset import SceneDataset
    from prismonet.evaluation.evaluate import check_compatible, evaluate_model, format_counts, format_steps, format_table
    from prismonet.evaluation.metrics import MISS_KINDS
    from prismonet.model.io import load_model, training_loss_config
    from prismonet.model.trainer import training_device

    cfg = inference_config(args)  # validates every step's settings before any work
    device = training_device(args.device)
    model, info = load_model(args.checkpoint, num_slots=args.objects)
    ds = SceneDataset(args.data, split=args.split)
    check_compatible(model, info, ds, any_camera=args.any_camera)
    if args.gray:
        from prismonet.data.gray import GrayScenes

        ds = GrayScenes(ds)
    results = evaluate_model(model, ds, batch_size=args.batch, num_slots=args.objects, limit=args.limit, progress=not args.quiet,
                             inference=cfg, loss_cfg=training_loss_config(info), supersample=args.supersample,
                             device=device)
    trained = info.get("model", {}).get("num_slots", "?")
    aa_ms = 1000 * results["supersample_seconds_per_scene"]
    aa_note = f"image measures from {args.supersample}x{args.supersample} rays per pixel (+{aa_ms:.1f} ms per scene); " if args.supersample > 1 else ""
    print(format_table([(f"{trained}/{results['num_slots']}", results)]))
    print(f"({results['scenes']} scenes of {args.data} [{args.split}], {results['matched_objects']} matched objects; "
          f"{'grey input; ' if args.gray else ''}{aa_note}{cfg.describe()}{refined_note(model.cfg.refine_passes)}; "
          f"{1000 * results['seconds_per_scene']:.1f} ms per scene{'' if device.type == 'cpu' else f' on {device}'})")
    print(f"visible-object count right in {results['count_exact']:.3f} of scenes (mean |error| {results['count_abs_err']:.2f}); "
          f"{results['slots_decoded']:.2f} slots kept per scene; height error {results['height_err']:.3f}"
          + (f" ({results['height_err_raised']:.3f} over {results['matched_raised']} objects resting on others)" if results["matched_raised"] else "")
          + f"; depth RMSE of the empty ground {results['depth_RMSE_empty']:.3f}")
    far = results["by_depth_clip"]["beyond_clip"]
    if far["objects"]:
        near = results["by_depth_clip"]["near"]
        print(f"AR0.5 of objects within the depth range {near['AR0.5']:.3f} ({near['objects']}), beyond the depth clip "
              f"{far['AR0.5']:.3f} ({far['objects']}: there depth cannot tell them from the ground)")
    miss = results["misses"]
    print(f"of {miss['objects']} visible objects: found {miss['found']:.3f}; missed as " +
          ", ".join(f"{k} {miss[k]:.3f}" for k in MISS_KINDS) + " (prismonet.evaluation.metrics.miss_breakdown)")
    if "shape_category" in results:
        sc = results["shape_category"]
        print("matched objects drawn nearest a prior code of their own category: " +
              ", ".join(f"{k} {sc[k]:.3f} ({n})" for k, n in sc["objects"].items()) + f"; mean {sc['mean']:.3f}")
    print("\nper encoder step:\n" + format_steps(results))
    if len(results["by_count"]) > 1:
        print("\nper number of visible objects:\n" + format_counts(results))
    if args.json:
        from prismonet.files import write_atomic

        write_atomic(args.json, json.dumps(results, indent=2))
        print(f"wrote {args.json}")
    return 0


def cmd_reconstruct(args) -> int:
    import torch

    from prismonet.data.dataset import SceneDataset
    from prismonet.evaluation.evaluate import check_compatible
    from prismonet.model.inference import infer
    from prismonet.model.io import load_model, prior_fingerprint, training_loss_config
    from prismonet.scene import LatentScene
    from prismonet.viz.decomposition import decomposition_figure

    cfg = inference_config(args)  # validated before loading anything
    model, info = load_model(args.checkpoint, num_slots=args.objects)
    ds = SceneDataset(args.data, split=args.split)
    size = model.cfg.image_size
    if tuple(ds.arrays["rgb"].shape[1:3]) != (size, size):
        raise ValueError(f"{args.data}: images are {ds.arrays['rgb'].shape[2]}x{ds.arrays['rgb'].shape[1]} but the model expects {size}x{size}")
    check_compatible(model, info, ds, any_camera=args.any_camera)
    n = len(ds) if args.count is None else min(args.count, len(ds))
    has_depth = bool((ds.arrays["depth"][:n] > 0).any())
    cfg = cfg if has_depth else cfg.without_depth()
    loss_cfg, fp, out_dir = training_loss_config(info), prior_fingerprint(model.prior), Path(args.out)
    for s in range(0, n, 8):
        b = ds.batch(list(range(s, min(s + 8, n))))
        out = infer(model, b, cfg, loss_cfg, args.objects)
        with torch.no_grad():
            for j, i in enumerate(range(s, s + len(b))):
                name = ds.names[i]
                print(f"  {decomposition_figure(b.rgb, out, j, out_dir / f'{name}.png', b.depth if has_depth else None)}")
                LatentScene.from_output(out, b, j, fp).save(out_dir / f"{name}.json")
    print(f"wrote {n} figures and latent scenes to {out_dir} ({cfg.describe()})")
    return 0


def _add_evaluate(sub) -> None:
    from prismonet.files import arg_int

    ev = sub.add_parser("evaluate", help="the paper's measures for a trained model on a dataset split")
    ev.add_argument("checkpoint", help="run folder, or model.safetensors / model.json")
    ev.add_argument("data", help="packed or folder dataset")
    ev.add_argument("--split", default="test")
    ev.add_argument("--objects", type=arg_int(1, 64), help="recurrent steps (object-count generalisation); default: as trained")
    ev.add_argument("--batch", type=arg_int(1, 4096), default=16)
    ev.add_argument("--limit", type=arg_int(1), help="evaluate only the first N scenes")
    ev.add_argument("--any-camera", action="store_true", help="evaluate scenes whose camera differs from training (measures then mean little)")
    ev.add_argument("--gray", action="store_true", help="make every input image grey (its luminance), as a greyscale photo is")
    ev.add_argument("--supersample", type=arg_int(1, 8), default=1, metavar="S",
                    help="image measures (RMSE, PSNR, SSIM) on the decomposition rendered with S x S rays per pixel, "
                         "averaged (anti-aliased; beyond the paper, whose renderer casts one; default 1)")
    ev.add_argument("--json", help="also write the results here")
    ev.add_argument("--device", default="cpu", help="cpu, cuda, cuda:N or auto (CUDA if there is one): where the model "
                                                    "and its test-time steps run; the measures are the same either way")
    ev.add_argument("--quiet", action="store_true")
    add_inference_args(ev)
    ev.set_defaults(func=cmd_evaluate, outputs=[("json", "file")])


def add_parsers(sub) -> None:
    from prismonet.assets import model_name
    from prismonet.demo import DEMO_MODEL
    from prismonet.files import arg_int

    demo = sub.add_parser("demo", help="the main job: the shipped model decomposes the shipped test scenes")
    demo.add_argument("--out", default="outputs/demo", help="output folder (default: outputs/demo)")
    demo.add_argument("--scenes", type=arg_int(1), default=8, help="how many of the 16 shipped scenes")
    demo.add_argument("--model", default=DEMO_MODEL, help=f"run folder or model name (default: {DEMO_MODEL}, "
                                                          f"{model_name(DEMO_MODEL)})")
    demo.add_argument("--data", help="a packed dataset with a test split instead of the shipped scenes (default: those of --model's setting)")
    demo.add_argument("--quiet", action="store_true")
    add_inference_args(demo, search=3, fit_color=50, shape_trials=None)
    demo.set_defaults(func=cmd_demo, outputs=[("out", "dir")])

    _add_evaluate(sub)

    rc = sub.add_parser("reconstruct", help="decompose scenes (synthetic or prepared real photos): a figure and the latent scene each")
    rc.add_argument("checkpoint", help="run folder, or model.safetensors / model.json")
    rc.add_argument("data", help="packed or folder dataset (e.g. the output of 'real prepare')")
    rc.add_argument("--out", required=True)
    rc.add_argument("--split", default="test")
    rc.add_argument("--count", type=arg_int(1), help="only the first N scenes")
    rc.add_argument("--objects", type=arg_int(1, 64), help="recurrent steps (default: as trained)")
    rc.add_argument("--any-camera", action="store_true", help="allow a camera that differs from training (real photos)")
    add_inference_args(rc)
    rc.set_defaults(func=cmd_reconstruct, outputs=[("out", "dir")])
