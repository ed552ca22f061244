"""Packed and folder formats: round trips, hand-made folders, corrupted and interrupted data."""

import json

import cv2
import numpy as np
import pytest

from prismonet.data.clevr import ClevrConfig
from prismonet.data.dataset import SceneDataset
from prismonet.data.errors import DatasetError, OutputDirError
from prismonet.data.folder import write_folder
from prismonet.data.generate import generate_clevr, render_range
from prismonet.data.scenes import SCENE_ARRAYS, SceneBatch

CFG = ClevrConfig()


@pytest.fixture(scope="module")
def packed(tmp_path_factory):
    root = tmp_path_factory.mktemp("packed") / "ds"
    generate_clevr(root, CFG, split=(5, 2, 3), seed=3, workers=1, progress=False)
    return root


def test_packed_round_trip_equals_rendered_scenes(packed):
    expected = render_range(CFG.to_dict(), 3, 5, 7)  # the val split is scenes 5 and 6
    ds = SceneDataset(packed, "val", verify=True)
    assert len(ds) == 2 and ds.format == "packed"
    for k in SCENE_ARRAYS:
        assert np.array_equal(np.asarray(ds.arrays[k]), expected[k]), k
    meta = ds.meta
    assert meta["counts"] == {"train": 5, "val": 2, "test": 3}
    assert meta["seed"] == 3 and meta["generator_version"] and meta["config"]["num_objects"] == 3


def test_packed_arrays_are_memory_mapped(packed):
    ds = SceneDataset(packed, "train")
    assert isinstance(ds.arrays["rgb"], np.memmap)


def test_scene_batch_shapes_and_collate(packed):
    ds = SceneDataset(packed, "train")
    b = ds.batch([0, 2, 4])
    assert b.rgb.shape == (3, 3, 64, 64) and b.depth.shape == (3, 1, 64, 64) and b.instance.shape == (3, 64, 64)
    assert b.obj_position.shape == (3, 3, 3) and b.obj_count.tolist() == [3, 3, 3]
    assert 0.0 <= b.rgb.min() and b.rgb.max() <= 1.0
    one = SceneBatch.collate([ds[0], ds[2], ds[4]])
    assert all(np.array_equal(getattr(one, k).numpy(), getattr(b, k).numpy()) for k in ("rgb", "obj_yaw", "K"))
    with pytest.raises(IndexError):
        ds[5]


def test_folder_round_trip(packed, tmp_path):
    src = SceneDataset(packed, "test")
    arrays = src.numpy(range(len(src)))
    write_folder(tmp_path / "f", arrays)
    back = SceneDataset(tmp_path / "f")
    assert back.format == "folder" and len(back) == 3
    for k in SCENE_ARRAYS:
        if k == "depth":
            assert np.abs(back.arrays[k] - arrays[k]).max() <= 0.5 / 1000 + 1e-6  # 16-bit mm quantisation
        else:
            assert np.allclose(back.arrays[k], arrays[k], atol=1e-6), k


def _hand_made(root, size=(48, 40), n=2, depth_scale=1000.0):
    """A folder dataset as a user would write it: PNGs plus JSON, some fields left out."""
    H, W = size
    for sub in ("rgb", "depth", "instance", "annotations"):
        (root / sub).mkdir(parents=True)
    K = [[50.0, 0.0, (W - 1) / 2], [0.0, 50.0, (H - 1) / 2], [0.0, 0.0, 1.0]]
    (root / "dataset.json").write_text(json.dumps({
        "format": "prismonet-folder", "version": 1, "depth_scale": depth_scale,
        "camera": {"K": K, "T_world_cam": np.eye(4).tolist(), "height": H, "width": W},
    }))
    for i in range(n):
        rgb = np.full((H, W, 3), 40 * i, np.uint8)
        cv2.imwrite(str(root / "rgb" / f"s{i}.png"), rgb)
        cv2.imwrite(str(root / "depth" / f"s{i}.png"), np.full((H, W), 2500 + i, np.uint16))
        inst = np.zeros((H, W), np.uint8)
        inst[5:10, 5:10] = 1
        cv2.imwrite(str(root / "instance" / f"s{i}.png"), inst)
    (root / "annotations" / "s0.json").write_text(json.dumps(
        {"objects": [{"category": "cube", "color": "red", "position": [0.1, 0.2, 0.3]}, {"scale": 0.4}]}
    ))
    return root


def test_hand_made_folder_loads(tmp_path):
    ds = SceneDataset(_hand_made(tmp_path / "h"))
    assert len(ds) == 2 and ds.names == ["s0", "s1"]
    b = ds.batch([0, 1])
    assert b.rgb.shape == (2, 3, 48, 40)
    assert b.depth[1, 0, 0, 0].item() == pytest.approx(2.501)
    assert b.obj_count.tolist() == [2, 0]
    assert b.obj_category[0].tolist() == [2, -1] and b.obj_color[0].tolist() == [1, -1]
    assert b.obj_position[0, 0].tolist() == pytest.approx([0.1, 0.2, 0.3])
    assert b.obj_scale[0, 1].item() == pytest.approx(0.4)
    assert b.K[0, 0, 2].item() == pytest.approx(19.5)


def test_hand_made_folder_with_mismatched_sizes(tmp_path):
    root = _hand_made(tmp_path / "h")
    cv2.imwrite(str(root / "depth" / "s1.png"), np.zeros((20, 20), np.uint16))
    with pytest.raises(DatasetError, match=r"scene 's1': depth is 20x20 but rgb is 40x48"):
        SceneDataset(root)
    cv2.imwrite(str(root / "rgb" / "s1.png"), np.zeros((10, 10, 3), np.uint8))
    with pytest.raises(DatasetError, match=r"scene 's1': rgb is 10x10, other scenes are 40x48"):
        SceneDataset(root)


def test_hand_made_folder_with_missing_files(tmp_path):
    root = _hand_made(tmp_path / "h")
    (root / "instance" / "s1.png").unlink()
    with pytest.raises(DatasetError, match=r"scene 's1': missing instance/s1.png"):
        SceneDataset(root)
    (root / "dataset.json").unlink()
    with pytest.raises(DatasetError, match="neither a packed dataset"):
        SceneDataset(root)
    with pytest.raises(DatasetError, match="no such dataset folder"):
        SceneDataset(tmp_path / "nowhere")


def test_hand_made_folder_with_bad_content(tmp_path):
    root = _hand_made(tmp_path / "h")
    (root / "annotations" / "s1.json").write_text(json.dumps({"objects": [{"category": "pyramid"}]}))
    with pytest.raises(DatasetError, match="unknown category 'pyramid'"):
        SceneDataset(root)
    (root / "annotations" / "s1.json").write_text("{not json")
    with pytest.raises(DatasetError, match="corrupted JSON"):
        SceneDataset(root)
    (root / "annotations" / "s1.json").unlink()
    cv2.imwrite(str(root / "depth" / "s1.png"), np.zeros((48, 40), np.uint8))
    with pytest.raises(DatasetError, match="depth must be a 16-bit PNG"):
        SceneDataset(root)
    (root / "rgb" / "s0.png").write_bytes(b"\x89PNG broken")
    with pytest.raises(DatasetError, match="cannot be read as an image"):
        SceneDataset(root)


def _copy(src, dst):
    import shutil

    shutil.copytree(src, dst)
    return dst


def test_truncated_packed_file(packed, tmp_path):
    root = _copy(packed, tmp_path / "t")
    path = root / "train" / "depth.npy"
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(DatasetError, match=r"depth.npy: truncated or altered"):
        SceneDataset(root, "train")
    SceneDataset(root, "val")  # other splits still load


def test_corrupted_packed_files(packed, tmp_path):
    root = _copy(packed, tmp_path / "c")
    # corrupted content of the same size: only the checksum sees it
    path = root / "train" / "rgb.npy"
    data = bytearray(path.read_bytes())
    data[-100] ^= 0xFF
    path.write_bytes(bytes(data))
    SceneDataset(root, "train")
    with pytest.raises(DatasetError, match=r"rgb.npy: corrupted: SHA-256"):
        SceneDataset(root, "train", verify=True)
    # corrupted header
    path = root / "val" / "instance.npy"
    data = bytearray(path.read_bytes())
    data[:6] = b"garbag"
    path.write_bytes(bytes(data))
    with pytest.raises(DatasetError, match=r"instance.npy: corrupted .npy file"):
        SceneDataset(root, "val")
    # corrupted meta
    (root / "meta.json").write_text('{"format": "prismonet-packed", "vers')
    with pytest.raises(DatasetError, match="meta.json: not valid JSON"):
        SceneDataset(root, "test")


def test_missing_split(packed):
    with pytest.raises(DatasetError, match=r"no split 'tset'"):
        SceneDataset(packed, "tset")


def test_joined_training_scenes_keep_their_indices(packed, tmp_path):
    from prismonet.data.packed import write_joined

    more = tmp_path / "more"
    generate_clevr(more, CFG, split=(4, 0, 0), seed=4, workers=1, progress=False)
    meta = write_joined(packed, more, tmp_path / "joined", count=3)
    train = SceneDataset(tmp_path / "joined", "train", verify=True)
    assert len(train) == 8 and meta["counts"] == {"train": 8, "val": 2, "test": 3}
    first, added = render_range(CFG.to_dict(), 3, 0, 5), render_range(CFG.to_dict(), 4, 0, 3)
    for k in SCENE_ARRAYS:  # scene i < 5 is still the first dataset's scene i; then the new seed's first three
        assert np.array_equal(np.asarray(train.arrays[k]), np.concatenate([first[k], added[k]])), k
    val = SceneDataset(tmp_path / "joined", "val")
    assert np.array_equal(np.asarray(val.arrays["rgb"]), render_range(CFG.to_dict(), 3, 5, 7)["rgb"])
    with pytest.raises(DatasetError, match="same seed"):
        write_joined(packed, packed, tmp_path / "again")
    with pytest.raises(DatasetError, match="count must be"):
        write_joined(packed, more, tmp_path / "too_many", count=5)


def test_interrupted_generation_leaves_nothing_that_loads(tmp_path, monkeypatch):
    from prismonet.data import generate

    calls = {"n": 0}
    real = generate.render_range

    def flaky(*args):
        calls["n"] += 1
        if calls["n"] == 2:
            raise KeyboardInterrupt
        return real(*args)

    monkeypatch.setattr(generate, "render_range", flaky)
    out = tmp_path / "ds"
    with pytest.raises(KeyboardInterrupt):
        generate.generate_clevr(out, CFG, split=(4, 0, 0), workers=1, progress=False, chunk=2)
    assert not out.exists()
    assert list(tmp_path.iterdir()) == []  # no partial folder left behind
    with pytest.raises(DatasetError):
        SceneDataset(out)


def test_output_folder_checks(tmp_path):
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "x").write_text("x")
    with pytest.raises(OutputDirError, match="output folder is not empty"):
        generate_clevr(tmp_path / "full", CFG, split=(1, 0, 0), progress=False)
    (tmp_path / "afile").write_text("x")
    with pytest.raises(OutputDirError, match="exists and is not a folder"):
        generate_clevr(tmp_path / "afile", CFG, split=(1, 0, 0), progress=False)
    with pytest.raises(OutputDirError, match="not writable"):
        generate_clevr(tmp_path / "afile" / "sub" / "ds", CFG, split=(1, 0, 0), progress=False)
    # an empty existing folder is fine
    (tmp_path / "empty").mkdir()
    generate_clevr(tmp_path / "empty", CFG, split=(1, 0, 0), progress=False, workers=1)
    assert len(SceneDataset(tmp_path / "empty", "train")) == 1


def test_read_only_output_folder(tmp_path):
    import os

    ro = tmp_path / "ro"
    ro.mkdir()
    os.chmod(ro, 0o500)
    try:
        if os.access(ro, os.W_OK) and os.geteuid() == 0:
            pytest.skip("root ignores directory permissions; covered by the not-a-folder case")
        with pytest.raises(OutputDirError, match="not writable"):
            generate_clevr(ro / "ds", CFG, split=(1, 0, 0), progress=False)
    finally:
        os.chmod(ro, 0o700)


@pytest.mark.parametrize("split", [(0, 0, 0), (-1, 2, 2), (1, 2)])
def test_bad_counts(tmp_path, split):
    with pytest.raises(ValueError, match="split"):
        generate_clevr(tmp_path / "ds", CFG, split=split, progress=False)
