"""The shipped stacked-blocks model (``blocks``: 8 anchored slots, the ``blocks`` prior of boxes, hexagonal prisms and
wedges, poses in the camera's frame) on its 16 shipped test scenes of ``data/stacks_v2``, against its measured
feed-forward figures with a margin (``python3 -m prismonet evaluate blocks prismonet/assets/samples/stacks [--gray]``:
AP0.5 0.567, AR0.5 0.617, depth RMSE 0.493; grey input 0.551 / 0.539)."""

from dataclasses import replace

import pytest

from prismonet.assets import asset_path, model_names, samples_for
from prismonet.data.dataset import SceneDataset
from prismonet.evaluation.evaluate import check_compatible, evaluate_model
from prismonet.model.io import load_model


@pytest.fixture(scope="module")
def model_and_data():
    model, info = load_model("blocks")
    ds = SceneDataset(samples_for("blocks"), split="test")
    check_compatible(model, info, ds)
    return model, ds


def test_the_blocks_model_ships_with_its_prior_configs_and_logs():
    assert "blocks" in model_names()
    for name in ("blocks_model.safetensors", "blocks_model.json", "blocks_train_config.json", "blocks_train_log.jsonl",
                 "blocks_stage1_config.json", "blocks_stage1_log.jsonl", "blocks_prior.json", "blocks_prior.safetensors",
                 "blocks_prior_SOURCES.md"):
        assert asset_path(name).is_file(), name


def test_the_blocks_model_finds_its_blocks(model_and_data):
    model, ds = model_and_data
    assert model.cfg.num_slots == 8 and model.cfg.pose_frame == "camera" and len(model.prior.shape_names) == 19
    r = evaluate_model(model, ds, batch_size=16, progress=False)
    assert r["scenes"] == 16
    assert r["AP0.5"] >= 0.567 - 0.05 and r["AR0.5"] >= 0.617 - 0.05
    assert r["depth_RMSE"] <= 0.493 * 1.10


def test_the_blocks_model_reads_grey_scenes_by_luminance(model_and_data):
    """A block photo is often greyscale (``blox.jpg``); the grey rule (``anchor_gray_tol`` 0.1) reads it by luminance."""
    from prismonet.data.gray import GrayScenes
    from prismonet.model.prismonet import PriSMONet

    model, ds = model_and_data
    assert model.cfg.anchor_gray_tol == 0.1
    grey = evaluate_model(model, GrayScenes(ds), batch_size=16, progress=False)
    off = PriSMONet(replace(model.cfg, anchor_gray_tol=None), prior=model.prior)
    off.load_state_dict(model.state_dict())
    without = evaluate_model(off.eval(), GrayScenes(ds), batch_size=16, progress=False)
    assert grey["AP0.5"] >= 0.551 - 0.05 and grey["AR0.5"] >= 0.539 - 0.05
    assert grey["AR0.5"] > without["AR0.5"] + 0.05  # measured 0.539 against 0.436 (AP0.5 0.551 against 0.501)


def test_the_blocks_keep_model_corrects_and_keeps_slots():
    """``blocks_keep``: ``blocks`` with a glimpse refiner that keeps or drops slots, fitted to its own search targets on
    4,096 training scenes, two passes, two re-anchoring steps. Its 16 shipped scenes: AP0.5 0.632, AR0.5 0.674, depth RMSE
    0.461 (``blocks``: 0.567, 0.617, 0.493)."""
    for name in ("blocks_keep_model.safetensors", "blocks_keep_model.json", "blocks_keep_fit_log.jsonl"):
        assert asset_path(name).is_file(), name
    model, info = load_model("blocks_keep")
    assert model.cfg.refine_passes == 2 and model.cfg.refiner_keep and model.cfg.reanchor_steps == 2
    ds = SceneDataset(samples_for("blocks_keep"), split="test")
    check_compatible(model, info, ds)
    r = evaluate_model(model, ds, batch_size=16, progress=False)
    assert r["AP0.5"] >= 0.632 - 0.05 and r["AR0.5"] >= 0.674 - 0.05
    assert r["depth_RMSE"] <= 0.461 * 1.10
