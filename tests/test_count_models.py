"""The shipped 2-, 4- and 5-object models (the 3-object model fine-tuned on each count, issue 23) on their
16 shipped test scenes each, against their measured feed-forward figures with a margin of 0.05 AP and 10 %
depth RMSE (``python3 -m prismonet evaluate clevrN prismonet/assets/samples/clevrN``)."""

import pytest

from prismonet.assets import asset_path, model_names
from prismonet.data.dataset import SceneDataset
from prismonet.evaluation.evaluate import check_compatible, evaluate_model
from prismonet.model.io import load_model

MEASURED = {2: {"AP0.5": 0.875, "depth_RMSE": 0.128}, 4: {"AP0.5": 0.760, "depth_RMSE": 0.202}, 5: {"AP0.5": 0.748, "depth_RMSE": 0.220}}


@pytest.mark.parametrize("n", [2, 4, 5])
def test_count_model_ships_and_finds_its_objects(n):
    name = f"clevr{n}"
    assert name in model_names()
    for f in (f"{name}_model.safetensors", f"{name}_model.json", f"{name}_train_config.json", f"{name}_train_log.jsonl"):
        assert asset_path(f).is_file(), f
    model, info = load_model(name)
    assert model.cfg.num_slots == n
    ds = SceneDataset(asset_path(f"samples/{name}"), split="test")
    check_compatible(model, info, ds)
    r = evaluate_model(model, ds, batch_size=16, progress=False)
    assert r["scenes"] == 16 and int(ds.arrays["obj_count"].max()) == n
    assert r["AP0.5"] >= MEASURED[n]["AP0.5"] - 0.05
    assert r["depth_RMSE"] <= MEASURED[n]["depth_RMSE"] * 1.10
