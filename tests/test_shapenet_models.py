"""The shipped ShapeNet-style scene models on their shipped test scenes, against thresholds set from
their measured figures with a margin (``python3 -m prismonet evaluate cars prismonet/assets/samples/cars``:
AP0.5 0.844, AR0.5 0.667; on the unseen cars of ``samples/cars_novel``: 0.760, 0.531)."""

import pytest

from prismonet.assets import asset_path, model_names
from prismonet.data.dataset import SceneDataset
from prismonet.evaluation.evaluate import check_compatible, evaluate_model
from prismonet.model.io import load_model

SHIPPED = {  # name: (samples, AP0.5 floor, AR0.5 floor)
    "cars": [("samples/cars", 0.7, 0.5), ("samples/cars_novel", 0.6, 0.4)],
}


@pytest.mark.parametrize("name", sorted(SHIPPED))
def test_the_model_ships_with_its_prior_config_and_log(name):
    assert name in model_names()
    for suffix in ("_model.safetensors", "_model.json", "_train_config.json", "_train_log.jsonl"):
        assert asset_path(name + suffix).is_file(), name + suffix
    model, info = load_model(name)
    assert model.cfg.prior == name and model.prior.bounds is not None  # its own prior, with its render box


@pytest.mark.parametrize("name,samples,ap,ar", [(n, *s) for n in sorted(SHIPPED) for s in SHIPPED[n]])
def test_the_model_finds_its_objects(name, samples, ap, ar):
    model, info = load_model(name)
    ds = SceneDataset(asset_path(samples), split="test")
    check_compatible(model, info, ds)
    r = evaluate_model(model, ds, batch_size=16, progress=False)
    assert r["AP0.5"] >= ap and r["AR0.5"] >= ar
