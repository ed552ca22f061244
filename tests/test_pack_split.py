"""``scripts/pack_split.py``: a split (or its first N scenes) carried to a machine that cannot make it, and back."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np

from prismonet.assets import asset_path
from prismonet.data.dataset import SceneDataset
from prismonet.data.packed import open_split

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "pack_split.py"


def _run(*args):
    subprocess.run([sys.executable, str(SCRIPT), *map(str, args)], check=True)


def test_the_first_scenes_of_a_split_unpack_into_a_dataset_that_opens(tmp_path):
    """The first 5 of the shipped 16 car scenes: meta.json's entries for the split are made to fit them (a copy of the
    full split's meta.json would fail its size check, as it did on the GPU machine in session 94), the arrays are equal
    bit for bit and their SHA-256 checks; another split already in the destination's meta.json is kept."""
    src = asset_path("samples/cars")
    _run("pack", src / "test", tmp_path / "pack", 5)
    dst = tmp_path / "cars"
    dst.mkdir()
    other = json.loads((src / "meta.json").read_text())
    other["splits"] = {"val": other["splits"]["test"]}
    other["counts"] = {"val": 16}
    (dst / "meta.json").write_text(json.dumps(other))
    _run("unpack", tmp_path / "pack", dst / "test")
    meta = json.loads((dst / "meta.json").read_text())
    assert meta["counts"] == {"val": 16, "test": 5} and set(meta["splits"]) == {"val", "test"}
    arrays = open_split(dst, "test", verify=True)
    full = open_split(src, "test")
    assert set(arrays) == set(full)
    for k, a in arrays.items():
        assert a.shape[0] == 5 and np.array_equal(a, full[k][:5]), k
    assert len(SceneDataset(dst, split="test")) == 5
