"""The shipped 2-, 4- and 5-object models (issue 23). Since session 106 each is the default ``clevr3_sharp`` decoded with
N slots: a model file alone that names the default's weights and their SHA-256 (``"weights_of"``), no second copy of
them. Checked here: that they load as that (N slots, the default's weights bit for bit), that a model file naming weights
shipped again is refused in one line, and each on its 16 shipped test scenes against its measured feed-forward figures
with a margin of 0.05 AP and 10 % depth RMSE (``python3 -m prismonet evaluate clevrN prismonet/assets/samples/clevrN``)."""

import json

import pytest
import torch

from prismonet.assets import asset_path, model_names
from prismonet.data.dataset import SceneDataset
from prismonet.evaluation.evaluate import check_compatible, evaluate_model
from prismonet.model.io import CheckpointError, load_model

MEASURED = {2: {"AP0.5": 1.000, "depth_RMSE": 0.119}, 4: {"AP0.5": 0.953, "depth_RMSE": 0.174},
            5: {"AP0.5": 0.947, "depth_RMSE": 0.199}}


@pytest.fixture(scope="module")
def default_weights():
    model, _ = load_model("shipped")
    return model.state_dict()


@pytest.mark.parametrize("n", [2, 4, 5])
def test_count_model_is_the_default_with_n_slots(n, default_weights):
    name = f"clevr{n}"
    assert name in model_names()
    assert asset_path(f"{name}_model.json").is_file() and not asset_path(f"{name}_model.safetensors").exists()
    model, info = load_model(name)
    assert model.cfg.num_slots == n and info["weights_of"]["model"] == "clevr3_sharp"
    got = model.state_dict()
    assert got.keys() == default_weights.keys()
    assert all(torch.equal(got[k], default_weights[k]) for k in got)


@pytest.mark.parametrize("n", [2, 4, 5])
def test_count_model_finds_its_objects(n):
    name = f"clevr{n}"
    model, info = load_model(name)
    ds = SceneDataset(asset_path(f"samples/{name}"), split="test")
    check_compatible(model, info, ds)
    r = evaluate_model(model, ds, batch_size=16, progress=False)
    assert r["scenes"] == 16 and int(ds.arrays["obj_count"].max()) == n
    assert r["AP0.5"] >= MEASURED[n]["AP0.5"] - 0.05
    assert r["depth_RMSE"] <= MEASURED[n]["depth_RMSE"] * 1.10


def test_a_model_file_whose_weights_were_shipped_again_is_refused(tmp_path):
    info = json.loads(asset_path("clevr4_model.json").read_text())
    info["weights_of"]["sha256"] = "0" * 64  # as if clevr3_sharp's file had changed since the figures were measured
    (tmp_path / "model.json").write_text(json.dumps(info))
    with pytest.raises(CheckpointError, match="shipped again"):
        load_model(tmp_path)
    info["weights_of"] = {"model": "no_such_model", "sha256": "0" * 64}
    (tmp_path / "model.json").write_text(json.dumps(info))
    with pytest.raises(CheckpointError, match="not installed"):
        load_model(tmp_path)
    info["weights_of"] = "clevr3_sharp"  # not a mapping
    (tmp_path / "model.json").write_text(json.dumps(info))
    with pytest.raises(CheckpointError, match="must name a shipped model"):
        load_model(tmp_path)


def test_model_variant_shared_writes_the_json_alone(script, tmp_path):
    """``scripts/model_variant.py --shared``: how these models were made; a run folder cannot be shared."""
    main = script("model_variant").main
    assert main(["--shared", "shipped", str(tmp_path / "v"), "num_slots=4"]) == 0
    assert sorted(p.name for p in (tmp_path / "v").iterdir()) == ["model.json"]
    model, info = load_model(tmp_path / "v")
    assert model.cfg.num_slots == 4 and info["weights_of"] == json.loads(asset_path("clevr4_model.json").read_text())["weights_of"]
    assert main(["--shared", str(tmp_path / "v"), str(tmp_path / "w"), "num_slots=5"]) == 2  # a run folder: no
    assert main([str(tmp_path / "v"), str(tmp_path / "w"), "num_slots=5"]) == 0  # a full copy: the weights file too
    assert sorted(p.name for p in (tmp_path / "w").iterdir()) == ["model.json", "model.safetensors"]
    assert "weights_of" not in json.loads((tmp_path / "w" / "model.json").read_text())
