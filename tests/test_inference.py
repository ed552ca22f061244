"""The test-time steps as one configuration (``prismonet.model.inference``) and one set of flags that
every decoding command takes (``prismonet.cli.common``)."""

from dataclasses import replace

import pytest
import torch

from prismonet.assets import shipped_samples
from prismonet.data.dataset import SceneDataset
from prismonet.model.color_fit import ColorFitConfig
from prismonet.model.inference import InferenceConfig, infer
from prismonet.model.io import load_model, training_loss_config
from prismonet.model.refine import RefineConfig
from prismonet.model.search import SearchConfig


def test_config_defaults_describe_and_validate():
    cfg = InferenceConfig()
    assert cfg.feed_forward and cfg.describe() == "encoder only, as the paper"
    assert cfg.search.rounds == 0 and cfg.refine.steps == 0 and cfg.color_fit.steps == 0 and cfg.extra_slots == 0
    full = InferenceConfig.of(extra_slots=1, search=3, refine=2, fit_color=50, refine_lr=0.02)
    assert not full.feed_forward and full.refine.lr == 0.02 and full.refine.pose_lr_scale == RefineConfig().pose_lr_scale
    assert full.describe() == "encoder, then 1 extra slots, 3 pose-search rounds, 2 refinement steps, 50 colour-fit steps"
    assert full.without_depth().describe().endswith("(colour only)") and full.use_depth
    assert full.record()["search"]["rounds"] == 3
    for bad in (dict(extra_slots=-1), dict(search=-1), dict(refine=-1), dict(fit_color=-1), dict(refine_lr=0.0)):
        with pytest.raises(ValueError):
            InferenceConfig.of(**bad)


@pytest.fixture(scope="module")
def shipped():
    model, info = load_model("shipped")
    return model, training_loss_config(info), SceneDataset(shipped_samples(), split="test").batch([0, 1])


def test_infer_runs_the_steps_in_order_and_equals_them_by_hand(shipped):
    from prismonet.model.color_fit import fit_colors
    from prismonet.model.refine import refine
    from prismonet.model.search import search_latents
    from prismonet.model.select import decode_overcomplete

    model, loss_cfg, b = shipped
    cfg = InferenceConfig(1, SearchConfig(rounds=1), RefineConfig(steps=1), ColorFitConfig(steps=2))
    seen = []
    out = infer(model, b, cfg, loss_cfg, on_step=lambda name, o: seen.append(name))
    assert seen == ["encoder", "searched", "refined", "color_fit"]
    with torch.no_grad():
        ref = decode_overcomplete(model, b, None, 1, w_image=loss_cfg.w_image, w_depth=loss_cfg.w_depth)
        ref = search_latents(model, ref, b, cfg.search)
    ref = fit_colors(model, refine(model, ref, b, loss_cfg, cfg.refine), b, cfg.color_fit)
    assert torch.equal(out.composite.image, ref.composite.image) and torch.equal(out.latents.params.position, ref.latents.params.position)
    seen.clear()
    assert infer(model, b, InferenceConfig(), loss_cfg, on_step=lambda name, o: seen.append(name)) is not None and seen == ["encoder"]


def test_colour_only_never_reads_depth(shipped):
    """With ``use_depth=False`` every step gives the same result whatever the depth holds."""
    model, loss_cfg, b = shipped
    cfg = InferenceConfig.of(extra_slots=1, search=1, refine=1, fit_color=1, use_depth=False)
    a = infer(model, b, cfg, loss_cfg)
    garbled = replace(b, depth=torch.rand_like(b.depth) * 20)
    c = infer(model, garbled, cfg, loss_cfg)
    assert torch.equal(a.composite.image, c.composite.image) and torch.equal(a.latents.params.scale, c.latents.params.scale)
    d = infer(model, garbled, replace(cfg, use_depth=True), loss_cfg)  # and the switch matters: depth is read otherwise
    assert not torch.equal(a.latents.params.position, d.latents.params.position)


DECODING = {
    "demo": ["demo"],
    "evaluate": ["evaluate", "shipped", "DATA"],
    "reconstruct": ["reconstruct", "shipped", "DATA", "--out", "O"],
    "real reconstruct": ["real", "reconstruct", "photo.jpg", "--out", "O"],
    "distill": ["distill", "shipped", "DATA", "--out", "O"],
}


@pytest.mark.parametrize("command", sorted(DECODING))
def test_every_decoding_command_takes_the_same_flags(command):
    from prismonet.cli import build_parser
    from prismonet.cli.common import inference_config

    flags = ["--extra-slots", "1", "--search", "2", "--refine", "3", "--refine-lr", "0.02", "--refine-pose-lr-scale", "2", "--fit-color", "4"]
    args = build_parser().parse_args(DECODING[command] + flags)
    assert inference_config(args) == InferenceConfig.of(1, 2, 3, 4, refine_lr=0.02, refine_pose_lr_scale=2.0)
    assert not inference_config(args, has_depth=False).use_depth


def test_colour_only_flag_and_its_old_name():
    from prismonet.cli import build_parser
    from prismonet.cli.common import inference_config

    for flag in ("--color-only", "--search-color-only"):
        assert not inference_config(build_parser().parse_args(["evaluate", "shipped", "DATA", flag])).use_depth
    assert inference_config(build_parser().parse_args(["evaluate", "shipped", "DATA"])).use_depth


def test_command_line_functions_stay_short():
    """No function in the command-line modules is over 60 lines (each sub-parser is built by its stage's module)."""
    import ast
    from pathlib import Path

    import prismonet.cli

    long = []
    for path in Path(prismonet.cli.__file__).parent.glob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and node.end_lineno - node.lineno + 1 > 60:
                long.append(f"{path.name}:{node.name} ({node.end_lineno - node.lineno + 1} lines)")
    assert not long, long


def test_search_scales_reach_the_search_and_its_description():
    from prismonet.model.inference import InferenceConfig

    cfg = InferenceConfig.of(search=2, search_scales=(0.8, 1.25))
    assert cfg.search.scales == (0.8, 1.25) and cfg.search.rounds == 2
    assert cfg.describe() == "encoder, then 2 pose-search rounds (scales 0.8, 1.25)"
    assert InferenceConfig.of(search=2).describe() == "encoder, then 2 pose-search rounds"


def test_search_far_clip_reaches_the_search_from_the_command_line():
    import argparse

    from prismonet.cli.common import add_inference_args, inference_config

    p = argparse.ArgumentParser()
    add_inference_args(p)
    cfg = inference_config(p.parse_args(["--search", "3", "--search-far-clip"]))
    assert cfg.search.far_clip and cfg.search.rounds == 3
    assert cfg.describe() == "encoder, then 3 pose-search rounds, depth clipped"
    assert not inference_config(p.parse_args(["--search", "3"])).search.far_clip
