"""The shipped block-tower model on its 16 shipped test scenes, against thresholds set from its
measured figures with a margin (``python3 -m prismonet evaluate blocktowers prismonet/assets/samples/towers``:
AP0.5 1.000, unfiltered 0.932, height error of stacked cubes 0.036; with ``--stop``: unfiltered 0.984,
2.94 slots kept for 2.9 cubes per scene)."""

import pytest

from prismonet.assets import asset_path, model_names
from prismonet.data.dataset import SceneDataset
from prismonet.evaluation.evaluate import check_compatible, evaluate_model
from prismonet.model.inference import InferenceConfig
from prismonet.model.io import load_model

SAMPLES = asset_path("samples/towers")


@pytest.fixture(scope="module")
def model_and_data():
    model, info = load_model("blocktowers")
    ds = SceneDataset(SAMPLES, split="test")
    check_compatible(model, info, ds)
    return model, ds


def test_the_tower_model_ships_with_its_config_and_log():
    assert "blocktowers" in model_names()
    for name in ("blocktowers_model.safetensors", "blocktowers_model.json", "blocktowers_train_config.json", "blocktowers_train_log.jsonl"):
        assert asset_path(name).is_file(), name


def test_the_tower_model_finds_the_cubes_and_their_heights(model_and_data):
    model, ds = model_and_data
    assert model.cfg.num_slots == 4
    r = evaluate_model(model, ds, batch_size=16, progress=False)
    assert r["AP0.5"] >= 0.95 and r["AR0.5"] >= 0.95
    assert r["matched_raised"] >= 20 and r["height_err_raised"] <= 0.1  # the bound is 0.2


def test_stopping_keeps_as_many_slots_as_cubes(model_and_data):
    model, ds = model_and_data
    r = evaluate_model(model, ds, batch_size=16, progress=False, inference=InferenceConfig.of(stop=True))
    assert r["count_exact"] >= 0.9 and r["slots_decoded"] < 3.5 and r["AP0.5_unfiltered"] >= 0.93


def test_the_demo_runs_a_named_model_on_its_own_scenes(tmp_path):
    """``demo --model blocktowers`` reads the tower scenes (its camera), not the 3-object Clevr ones."""
    import json

    from prismonet.cli import main

    out = tmp_path / "demo"
    assert main(["demo", "--model", "blocktowers", "--out", str(out), "--scenes", "1", "--search", "0", "--fit-color", "0", "--quiet"]) == 0
    m = json.loads((out / "metrics.json").read_text())
    assert m["mean"]["AP0.5"] >= 0.5 and len(m["scenes"]) == 1
