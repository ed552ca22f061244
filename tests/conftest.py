import os

import numpy as np
import pytest
import torch

# A script a test starts in a subprocess (its one-line refusals) would add the adaptive thread count's line to stderr
# when other processes load the machine (prismonet.threads.use_free_cores); a fixed count keeps its stderr to what the
# test reads. The thread tests unset it where they test the adaptive count.
if not os.environ.get("PRISMONET_THREADS"):
    os.environ["PRISMONET_THREADS"] = str(torch.get_num_threads())


@pytest.fixture(scope="session")
def script():
    """``script(NAME)``: the module ``scripts/NAME.py``, imported from its file (the scripts folder is no package)."""
    import importlib.util
    from pathlib import Path

    def load(name: str):
        path = Path(__file__).resolve().parents[1] / "scripts" / f"{name}.py"
        spec = importlib.util.spec_from_file_location(name, path)
        mod = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(mod)
        return mod

    return load


@pytest.fixture
def rng():
    return np.random.default_rng(1234)


@pytest.fixture
def gen():
    return torch.Generator().manual_seed(1234)


def _on_samples(name: str):
    """Model ``name``, the first four shipped test scenes, and the model's output on them."""
    from prismonet.assets import shipped_samples
    from prismonet.data.dataset import SceneDataset
    from prismonet.model.io import load_model

    model, _ = load_model(name)
    model.eval()
    b = SceneDataset(shipped_samples(), split="test").batch([0, 1, 2, 3])
    with torch.no_grad():
        out = model(b.rgb, b.K, b.T_world_cam, b.ground_z)
    return model, b, out


@pytest.fixture(scope="module")
def shipped():
    """The default model (``clevr3_r4`` since session 108), the first four shipped test scenes, and the model's output on
    them."""
    return _on_samples("shipped")


@pytest.fixture(scope="module")
def sharp():
    """``clevr3_sharp`` (the default of sessions 92-107), the first four shipped test scenes, and its output on them: the
    poses that tests built on that model's decoding start from."""
    return _on_samples("clevr3_sharp")


@pytest.fixture(scope="module")
def clevr3():
    """``clevr3`` (the default model of sessions 56-91, whose refiner moves and keeps slots but leaves their shapes), the
    first four shipped test scenes, and its output on them: what the refiner-fit tests start from, since their targets
    carry no shapes for the default's shape refiner to learn."""
    return _on_samples("clevr3")
