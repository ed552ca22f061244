"""The shipped 2-, 4- and 5-object models (issue 23). Since session 108 they are the default ``clevr3_r4`` (``clevr3_sharp``
with its refiner fine-tuned on 4-object targets in session 107, when it shipped as ``clevr4``) decoded with 2, 4 and 5
slots: each a model file alone that names the default's weights and their SHA-256 (``"weights_of"``), no second copy of
them. Since session 111 all of them take two plain encoder steps after refinement into the slots the keep output
dropped (``reanchor_steps`` 2; ``clevr5`` keeps a new slot above keep logit 1). Checked here: that they load as that,
that the default is ``clevr3_sharp`` bit for bit except its refiner, that a model file naming weights shipped again is
refused in one line, and each on its 16 shipped test scenes against its measured feed-forward figures with a margin of
0.05 AP and 10 % depth RMSE (``python3 -m prismonet evaluate clevrN prismonet/assets/samples/clevrN``)"""

import json

import pytest
import torch

from prismonet.assets import asset_path, model_names
from prismonet.data.dataset import SceneDataset
from prismonet.evaluation.evaluate import check_compatible, evaluate_model
from prismonet.model.io import CheckpointError, load_model, save_model

RESTEPS = {2: (2, 0.0), 4: (2, 0.0), 5: (2, 1.0)}  # session 111: (reanchor_steps, reanchor_keep_logit)
MEASURED = {2: {"AP0.5": 1.000, "depth_RMSE": 0.108}, 4: {"AP0.5": 0.953, "depth_RMSE": 0.170},
            5: {"AP0.5": 0.975, "depth_RMSE": 0.192}}


@pytest.fixture(scope="module")
def sharp_weights():
    model, _ = load_model("clevr3_sharp")
    return model.state_dict()


@pytest.mark.parametrize("n", [2, 4, 5])
def test_count_model_is_the_default_with_n_slots(n):
    name = f"clevr{n}"
    assert name in model_names()
    assert asset_path(f"{name}_model.json").is_file() and not asset_path(f"{name}_model.safetensors").exists()
    model, info = load_model(name)
    assert model.cfg.num_slots == n and info["weights_of"]["model"] == "clevr3_r4"
    assert (model.cfg.reanchor_steps, model.cfg.reanchor_keep_logit) == RESTEPS[n]
    got, want = model.state_dict(), load_model("shipped")[0].state_dict()
    assert got.keys() == want.keys()
    assert all(torch.equal(got[k], want[k]) for k in got)


def test_the_default_is_clevr3_sharp_with_its_refiner_fine_tuned(sharp_weights):
    """Only the refiner was fitted (``prismonet refiner --fine-tune``): every other weight is ``clevr3_sharp``'s bit for
    bit, and the refiner's are not; the record says on which targets, with the second-pass term and the held-out
    minimum."""
    assert asset_path("clevr3_r4_model.safetensors").is_file()
    model, info = load_model("shipped")
    assert model.cfg.num_slots == 3 and "weights_of" not in info
    assert model.cfg.reanchor_steps == 2  # session 111: plain encoder steps into dropped slots after refinement
    got = model.state_dict()
    assert got.keys() == sharp_weights.keys()
    other = [k for k in got if not k.startswith("refiner.")]
    assert len(other) > 0 and all(torch.equal(got[k], sharp_weights[k]) for k in other)
    assert not all(torch.equal(got[k], sharp_weights[k]) for k in got if k.startswith("refiner."))
    fit = info["refiner_fit"]
    assert fit["target_scenes"] == 9216 and fit["fit"]["second_pass"] == 1.0 and fit["fit"]["keep_best"]


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
    info = json.loads(asset_path("clevr5_model.json").read_text())
    info["weights_of"]["sha256"] = "0" * 64  # as if the default's file had changed since the figures were measured
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
    """``scripts/model_variant.py --shared``: how these models were made (from ``clevr4``, itself a shared file: the
    weights named are still the default's); a run folder cannot be shared."""
    main = script("model_variant").main
    assert main(["--shared", "clevr4", str(tmp_path / "v"), "num_slots=5"]) == 0
    assert sorted(p.name for p in (tmp_path / "v").iterdir()) == ["model.json"]
    model, info = load_model(tmp_path / "v")
    assert model.cfg.num_slots == 5 and info["weights_of"] == json.loads(asset_path("clevr5_model.json").read_text())["weights_of"]
    assert main(["--shared", str(tmp_path / "v"), str(tmp_path / "w"), "num_slots=5"]) == 2  # a run folder: no
    assert main([str(tmp_path / "v"), str(tmp_path / "w"), "num_slots=5"]) == 0  # a full copy: the weights file too
    assert sorted(p.name for p in (tmp_path / "w").iterdir()) == ["model.json", "model.safetensors"]
    assert "weights_of" not in json.loads((tmp_path / "w" / "model.json").read_text())


def test_a_model_saved_from_a_shared_file_loads_the_weights_written(tmp_path):
    """A fine-tune of ``clevr5`` (which ships as the default's weights) writes weights of its own; its model file must
    not carry over ``"weights_of"``, or loading it would read the default's weights and the fit would be silently lost
    (session 109 found this: a refit read exactly as its start); nor the start's description (``"note"``)."""
    model, info = load_model("clevr5")
    assert "weights_of" in info
    with torch.no_grad():
        next(p for n, p in model.named_parameters() if n.startswith("refiner.")).add_(0.5)
    save_model(model, tmp_path / "model", {**info, "init_from": "clevr5"})
    saved = json.loads((tmp_path / "model.json").read_text())
    assert "weights_of" not in saved and "note" not in saved and saved["init_from"] == "clevr5"  # the start's note: not this
    again, _ = load_model(tmp_path)
    got, want = again.state_dict(), model.state_dict()
    assert all(torch.equal(got[k], want[k]) for k in want)
