"""``prismonet train`` (the scene model from RGB-D), ``prismonet distill`` (self-distillation
targets: the test-time steps run on training scenes, ``prismonet.model.distill``), ``prismonet
refiner`` (a learnt refinement pass trained on such targets, ``prismonet.model.refiner_fit``) and ``prismonet
color-step`` (a learnt colour step trained on training images, ``prismonet.model.color_step_fit``)."""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

from prismonet.cli.common import add_inference_args, inference_config, int_list


def cmd_train(args) -> int:
    from prismonet.config import load_config
    from prismonet.model.trainer import TrainConfig, train

    cfg = load_config(TrainConfig, args.config, args.set + ([f"device={args.device}"] if args.device else []))
    summary = train(cfg, Path(args.out), progress=not args.quiet)
    if summary.get("world_size", 1) == 1 or int(os.environ.get("RANK", "0")) == 0:
        print(json.dumps(summary))
        print(f"run folder: {args.out}  (model.safetensors + model.json, checkpoint.safetensors, tb/, images/, log.jsonl)")
    return 0


def _lane(text: str) -> tuple[int, int]:
    """``--lane I/N`` (1-based, as a person counts lanes) as ``fit_targets``'s 0-based ``(i, n)``."""
    try:
        i, n = (int(v) for v in text.split("/"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected I/N such as 1/2, got {text!r}") from None
    if not 1 <= i <= n:
        raise argparse.ArgumentTypeError(f"expected I/N with 1 <= I <= N, got {text!r}")
    return i - 1, n


def cmd_distill(args) -> int:
    from prismonet.data.dataset import SceneDataset
    from prismonet.evaluation.evaluate import check_compatible
    from prismonet.model.distill_fit import fit_targets, true_pose_search, weights_digest
    from prismonet.model.io import load_model, training_loss_config
    from prismonet.model.trainer import training_device

    if args.batch <= 0:
        raise ValueError(f"--batch must be positive, got {args.batch}")
    cfg = inference_config(args)  # validate first
    device = training_device(args.device)
    if args.true_poses:
        cfg = true_pose_search(cfg)
    model, info = load_model(args.checkpoint)
    ds = SceneDataset(args.data, split=args.split)
    check_compatible(model, info, ds)
    count = len(ds) if args.count is None else args.count
    meta = {"model": str(args.checkpoint), "model_digest": weights_digest(model), "data": str(args.data), "split": args.split}
    if args.gray:  # recorded only when on, so targets made before it still resume
        from prismonet.data.gray import GrayScenes

        ds, meta["gray"] = GrayScenes(ds), True
    s = fit_targets(model, ds, args.out, count, cfg, batch_size=args.batch, progress=not args.quiet, meta=meta,
                    loss_cfg=training_loss_config(info), true_poses=args.true_poses, device=device, lane=args.lane)
    extra = f"; fit score {s['score_before']:.4f} -> {s['score_after']:.4f} on the chunks made now" if "score_before" in s else ""
    print(f"distillation targets for {s['scenes']} scenes of {args.data} [{args.split}] in {args.out}{extra}")
    return 0


def cmd_refiner(args) -> int:
    from prismonet.data.dataset import SceneDataset
    from prismonet.evaluation.evaluate import check_compatible
    from prismonet.model.io import load_model
    from prismonet.model.refiner_fit import RefinerFitConfig, fit_refiner, with_refiner, with_shape_step
    from prismonet.model.trainer import training_device

    device = training_device(args.device)
    info_path = Path(args.targets) / "targets.json"  # without it fit_refiner says what is missing
    meta = json.loads(info_path.read_text()) if info_path.is_file() else {}
    gray = bool(meta.get("gray", False))  # targets fitted on grey scenes: every scene is shown grey
    if gray and args.gray_share not in (0.0, 1.0):
        raise ValueError(f"{args.targets}: fitted on grey scenes, so the refiner sees every scene grey; --gray-share "
                         f"{args.gray_share} cannot be used with them")
    cfg = RefinerFitConfig(steps=args.steps, batch_size=args.batch, lr=args.lr, holdout=args.holdout, seed=args.seed,
                           texture=args.texture, color=args.color, true_poses=args.true_poses, fill_hidden=args.fill_hidden,
                           recolor=args.recolor, gray_share=1.0 if gray else args.gray_share, gray_targets=gray,
                           reanchored=args.reanchored, second_pass=args.second_pass,
                           second_pass_shape=not args.second_pass_no_shape, keep_best=args.keep_best)  # validate first
    base, info = load_model(args.checkpoint)
    if args.fine_tune:  # the model's own refiner, trained on (with --shape: a shape step added to it)
        if not base.cfg.refine_passes or args.glimpse or args.coords or args.shape_codes or args.keep:
            raise ValueError(f"{args.checkpoint}: --fine-tune trains the model's own refiner (it has "
                             f"{base.cfg.refine_passes} passes); its refiner settings (--glimpse, --coords, "
                             "--shape-codes, --keep) stay as they are")
        model = with_shape_step(base) if args.shape else base
    elif base.cfg.refine_passes:
        raise ValueError(f"{args.checkpoint}: already has a refiner; start from its encoder's model, or --fine-tune it")
    else:
        model = with_refiner(base, refiner_glimpse=args.glimpse, refiner_coords=args.coords, refiner_shape=args.shape,
                             refiner_shape_codes=args.shape_codes, refiner_keep=args.keep)  # checks the refiner settings
    ds = SceneDataset(args.data, split=args.split)
    check_compatible(base, info, ds)
    from prismonet.model.distill_fit import weights_digest

    maker = base if args.targets_from is None else load_model(args.targets_from)[0]
    maker_name = args.checkpoint if args.targets_from is None else args.targets_from
    if meta and meta.get("model_digest") != weights_digest(maker) and not _made_by_refined(meta, weights_digest(maker)):
        raise ValueError(f"{args.targets}: targets made by other weights ({meta.get('model_digest')}), not {maker_name}'s"
                         + ("" if args.targets_from else " (--targets-from MODEL names the model that made them)"))
    s = fit_refiner(model, ds, args.targets, args.out, cfg, info={**info, "init_from": str(args.checkpoint)},
                    progress=not args.quiet, device=device)
    print(json.dumps(s))
    print(f"run folder: {args.out}  (model.safetensors + model.json with the refiner, checkpoint.safetensors, log.jsonl)")
    return 0


def cmd_color_step(args) -> int:
    from prismonet.data.dataset import SceneDataset
    from prismonet.evaluation.evaluate import check_compatible
    from prismonet.model.color_step_fit import ColorStepFitConfig, fit_color_step, with_color_step
    from prismonet.model.io import load_model

    cfg = ColorStepFitConfig(steps=args.steps, batch_size=args.batch, lr=args.lr, holdout=args.holdout, seed=args.seed)
    if args.count is not None and args.count <= 0:
        raise ValueError(f"--count must be positive, got {args.count}")
    if args.passes < 1:
        raise ValueError(f"--passes must be at least 1, got {args.passes}")
    channels, fc = tuple(int_list(args.channels, "--channels", 1)), tuple(int_list(args.fc, "--fc", 1))
    base, info = load_model(args.checkpoint)
    if base.cfg.color_step:
        raise ValueError(f"{args.checkpoint}: already has a colour step; start from the model without it "
                         "(color_step_fit.without_color_step)")
    model = with_color_step(base, channels, fc, args.passes)
    ds = SceneDataset(args.data, split=args.split)
    check_compatible(base, info, ds)
    s = fit_color_step(model, ds, len(ds) if args.count is None else args.count, args.out, cfg,
                       info={**info, "init_from": str(args.checkpoint)}, progress=not args.quiet)
    print(json.dumps(s))
    print(f"run folder: {args.out}  (model.safetensors + model.json with the colour step, checkpoint.safetensors, log.jsonl)")
    return 0


def _made_by_refined(meta: dict, base_digest: str) -> bool:
    """Whether targets were made by a model with a refinement pass on top of the encoder of digest ``base_digest``
    (a later round of self-distillation: the refined model's search gives the targets, its encoder is fitted again)."""
    from prismonet.files import InputError
    from prismonet.model.distill_fit import encoder_digest, weights_digest
    from prismonet.model.io import CheckpointError, load_model

    try:
        maker = load_model(meta["model"])[0]
    except (KeyError, OSError, ValueError, InputError, CheckpointError):
        return False
    return bool(maker.cfg.refine_passes) and weights_digest(maker) == meta.get("model_digest") and encoder_digest(maker) == base_digest


def add_parsers(sub) -> None:
    tr = sub.add_parser("train", help="train the scene model from RGB-D (resumable; works under torchrun)")
    tr.add_argument("config", help="JSON file of TrainConfig fields (e.g. configs/clevr3.json)")
    tr.add_argument("--out", required=True, help="run folder; rerunning resumes from its checkpoint")
    tr.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override, e.g. loss.blur=false")
    tr.add_argument("--device", help="cpu, cuda, cuda:N or auto (CUDA if there is one); default: the config's (cpu)")
    tr.add_argument("--quiet", action="store_true")
    tr.set_defaults(func=cmd_train, outputs=[("out", "dir")])

    p = sub.add_parser("distill", help="self-distillation targets: the test-time steps on training scenes (resumable)")
    p.add_argument("checkpoint", help="trained model: run folder, .safetensors, or 'shipped'")
    p.add_argument("data", help="dataset whose scenes to fit (RGB-D only is read)")
    p.add_argument("--out", required=True, help="folder of target chunks; rerun the same command to resume")
    p.add_argument("--split", default="train")
    p.add_argument("--count", type=int, default=None, help="fit the first N scenes of the split (default: all)")
    p.add_argument("--batch", type=int, default=16)
    p.add_argument("--true-poses", action="store_true",
                   help="+ 3D pose variant (supervised): start from the true poses and search only shapes (--search-shapes) and colours")
    p.add_argument("--device", default="cpu", help="cpu, cuda, cuda:N or auto (CUDA if there is one); a folder's chunks may come from either (same settings)")
    p.add_argument("--gray", action="store_true",
                   help="fit the scenes as a greyscale camera shows them (their luminance, depth as it is), so that the "
                        "targets follow the grey decoding's slots: for a refiner of grey photos (`refiner` reads this)")
    p.add_argument("--lane", type=_lane, default=(0, 1), metavar="I/N",
                   help="fit only every N-th chunk from the I-th (1 <= I <= N), so that N commands with the same "
                        "--out, each on one thread (PRISMONET_THREADS=1), fill one folder side by side (default 1/1)")
    p.add_argument("--quiet", action="store_true")
    add_inference_args(p, search=3, fit_color=50)
    p.set_defaults(func=cmd_distill, outputs=[("out", "dir")])
    _add_refiner_parser(sub)
    _add_color_step_parser(sub)


def _add_fine_tune_options(r) -> None:
    """The refiner command's options for training a refiner a model already has."""
    r.add_argument("--fine-tune", action="store_true",
                   help="train the refiner CHECKPOINT already has (its settings and passes kept; --shape may add a "
                        "shape step) instead of a fresh one")
    r.add_argument("--reanchored", type=float, default=0.0, metavar="W",
                   help="with --fine-tune on an anchored model with re-anchoring: also fit the refiner on the slots the "
                        "re-anchoring adds, with weight W, against targets `distill` made from CHECKPOINT itself (keep bars "
                        "off, so that no slot is dropped); 0: off")
    r.add_argument("--second-pass", type=float, default=0.0, metavar="W",
                   help="with --fine-tune on a model of two refinement passes or more: also fit the refiner on what its "
                        "second pass sees (the first pass's output), with weight W, against the same targets (in the "
                        "model's slot order: made by CHECKPOINT, or by its encoder where slots keep their order); 0: off")
    r.add_argument("--second-pass-no-shape", action="store_true",
                   help="with --second-pass and a refiner that corrects shapes: leave the shape latent out of that term")


def _add_refiner_parser(sub) -> None:
    r = sub.add_parser("refiner", help="train a learnt refinement pass on distillation targets, the encoder frozen (resumable)")
    r.add_argument("checkpoint", help="the trained model whose targets these are: run folder, .safetensors, or a shipped name")
    r.add_argument("data", help="the dataset the targets were made on")
    r.add_argument("--targets", required=True, help="a `prismonet distill` folder made by this model")
    r.add_argument("--out", required=True, help="run folder; rerun the same command to resume")
    r.add_argument("--split", default="train")
    r.add_argument("--steps", type=int, default=3000)
    r.add_argument("--batch", type=int, default=32, help="scenes per step")
    r.add_argument("--lr", type=float, default=3e-4)
    r.add_argument("--holdout", type=int, default=256, help="the last N scenes with targets, held out (logged)")
    r.add_argument("--texture", type=float, default=0.1, help="weight of the texture-latent term")
    r.add_argument("--color", type=float, default=0.0,
                   help="weight of the colour term: the texture field's colours under the corrected and the target "
                        "texture latents, at fixed points of the object frame (0: off)")
    r.add_argument("--seed", type=int, default=0)
    r.add_argument("--glimpse", type=float, default=0.0,
                   help="the refiner sees each slot through a window of this fraction of the image side around its "
                        "centre, zoomed to the image size (0: the whole image; 0.5 is the measured setting)")
    r.add_argument("--coords", action="store_true", help="the refiner also sees each pixel's image position")
    r.add_argument("--shape", action="store_true",
                   help="the refiner also corrects each slot's shape latent (targets with shapes: --search-shapes or "
                        "--shape-trials); with --fine-tune, a shape step added to a refiner without one")
    r.add_argument("--shape-codes", action="store_true",
                   help="with --shape: the refiner chooses each slot's shape among the prior's codes and the slot's own "
                        "latent (cross-entropy on the search's choice) instead of stepping the latent")
    r.add_argument("--keep", action="store_true",
                   help="the refiner also learns which slots to keep (those the search's fit shows); it drops the others")
    r.add_argument("--true-poses", action="store_true",
                   help="supervised (+ 3D pose): fit the slots the search shows to the true positions, scales and yaws "
                        "(up to each shape's symmetry) of the objects they match; shapes, textures and keeping stay the search's")
    r.add_argument("--fill-hidden", action="store_true",
                   help="with --true-poses: the objects no shown slot matches go to the hidden slots, which are then kept "
                        "(measured worse on tableware: off by default)")
    r.add_argument("--recolor", action="store_true",
                   help="the refiner sees every scene with new object colours, drawn once per scene from --seed, found "
                        "from depth alone (so it cannot tell a seen model by its colour); needs --texture 0")
    r.add_argument("--gray-share", type=float, default=0.0, metavar="S",
                   help="the refiner sees this share of the scenes grey (drawn once per scene from --seed), as a greyscale "
                        "photo shows them; the targets stay the search's fits to the colour scenes; needs --texture 0 (targets made by "
                        "`distill --gray` set it to 1 and allow a texture weight)")
    _add_fine_tune_options(r)
    r.add_argument("--keep-best", action="store_true",
                   help="save the refiner at its lowest held-out loss (logged every 250 steps, the start included) "
                        "rather than at the last step")
    r.add_argument("--targets-from", default=None, metavar="MODEL",
                   help="the targets were made by MODEL, not by CHECKPOINT (e.g. CHECKPOINT is an encoder fine-tuned on "
                        "them with distillation, in the same slot order); checked against MODEL's weights instead")
    r.add_argument("--device", default="cpu", help="cpu, cuda, cuda:N or auto (CUDA if there is one); a run may resume on another")
    r.add_argument("--quiet", action="store_true")
    r.set_defaults(func=cmd_refiner, outputs=[("out", "dir")])


def _add_color_step_parser(sub) -> None:
    c = sub.add_parser("color-step", help="train a learnt colour step on training images, the rest of the model frozen (resumable)")
    c.add_argument("checkpoint", help="the trained model: run folder, .safetensors, or a shipped name")
    c.add_argument("data", help="a dataset of training scenes (only the images are read)")
    c.add_argument("--out", required=True, help="run folder; rerun the same command to resume")
    c.add_argument("--split", default="train")
    c.add_argument("--count", type=int, default=None, help="the first N scenes of the split (default: all)")
    c.add_argument("--steps", type=int, default=3000)
    c.add_argument("--batch", type=int, default=32, help="scenes per step")
    c.add_argument("--lr", type=float, default=1e-3)
    c.add_argument("--holdout", type=int, default=256, help="the last N scenes, held out (their PSNR is logged)")
    c.add_argument("--channels", default="32,32,64,64", help="conv blocks of the colour step")
    c.add_argument("--fc", default="256", help="its fully connected layers")
    c.add_argument("--passes", type=int, default=1, help="looks per slot, each at the image the last one made")
    c.add_argument("--seed", type=int, default=0)
    c.add_argument("--quiet", action="store_true")
    c.set_defaults(func=cmd_color_step, outputs=[("out", "dir")])
