"""Nothing partial left behind: stale partial dataset folders, stale checkpoint temp files, log lines
repeated after a resume, and run folders of runs that could not start."""

import json
import os

import torch

from prismonet.assets import shipped_samples
from prismonet.checkpoint import load_checkpoint, save_checkpoint
from prismonet.data.clevr import ClevrConfig
from prismonet.data.generate import generate_clevr
from prismonet.model.trainer import TrainConfig, train


def dead_pid() -> int:
    """A process id that no process has (a killed run's)."""
    pid = 4_000_000
    while True:
        try:
            os.kill(pid, 0)
            pid -= 1
        except ProcessLookupError:
            return pid
        except PermissionError:
            pid -= 1


def test_a_killed_generation_leaves_nothing_the_next_run_keeps(tmp_path):
    stale = tmp_path / f".ds.partial-{dead_pid()}"
    (stale / "train").mkdir(parents=True)
    (stale / "train" / "rgb.npy").write_bytes(b"half written")
    alive = tmp_path / f".ds.partial-{os.getpid()}-x"  # not a pid suffix of a dead run: left alone
    alive.mkdir()
    generate_clevr(tmp_path / "ds", ClevrConfig(num_objects=1), split=(2, 0, 0), workers=1, progress=False)
    assert not stale.exists() and alive.exists()
    assert (tmp_path / "ds" / "meta.json").is_file()


def test_checkpoint_temp_files_of_dead_writers_are_removed(tmp_path):
    path = tmp_path / "checkpoint.safetensors"
    stale = tmp_path / f".checkpoint.safetensors.tmp-{dead_pid()}"
    stale.write_bytes(b"cut short by a kill")
    save_checkpoint(path, {"w": torch.ones(2)}, {"step": 1})
    assert not stale.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["checkpoint.safetensors"]
    assert load_checkpoint(path)[1] == {"step": 1}


def test_resume_does_not_repeat_log_steps(tmp_path):
    data = str(shipped_samples())
    cfg = TrainConfig(data=data, split="test", steps=4, batch_size=2, log_every=1, image_every=1000, checkpoint_every=2, seed=3)
    run = tmp_path / "run"
    train(cfg, run, progress=False, stop_after=3)  # logged steps 1-3, checkpoint at 2 (as a kill after step 3)
    train(cfg, run, progress=False)  # resumes at 2
    steps = [json.loads(line)["step"] for line in (run / "log.jsonl").read_text().splitlines()]
    assert steps == [1, 2, 3, 4]


def test_a_run_that_cannot_start_leaves_no_folder(tmp_path):
    import pytest

    cfg = TrainConfig(data=str(tmp_path / "missing"), steps=2)
    with pytest.raises(ValueError):
        train(cfg, tmp_path / "run", progress=False)
    assert not (tmp_path / "run").exists()


def test_write_atomic_never_leaves_a_half_written_file(tmp_path, monkeypatch):
    import os

    import pytest

    from prismonet.files import write_atomic

    target = tmp_path / "models.json"
    write_atomic(target, '{"old": 1}')
    assert target.read_text() == '{"old": 1}' and sorted(p.name for p in tmp_path.iterdir()) == ["models.json"]

    def interrupted(src, dst):
        raise KeyboardInterrupt

    monkeypatch.setattr(os, "replace", interrupted)
    with pytest.raises(KeyboardInterrupt):
        write_atomic(target, '{"new": 2}')
    assert target.read_text() == '{"old": 1}'  # the old file stands, and no temporary is left
    assert sorted(p.name for p in tmp_path.iterdir()) == ["models.json"]


def test_write_image_never_leaves_a_half_written_image(tmp_path, monkeypatch):
    import os

    import numpy as np
    import pytest

    from prismonet.files import read_image, write_image

    target = tmp_path / "scene_000.png"
    old = np.full((4, 5, 3), 7, np.uint8)
    write_image(target, old)
    assert (read_image(target) == old).all() and sorted(p.name for p in tmp_path.iterdir()) == ["scene_000.png"]

    def interrupted(src, dst):
        raise KeyboardInterrupt

    monkeypatch.setattr(os, "replace", interrupted)
    with pytest.raises(KeyboardInterrupt):
        write_image(target, np.zeros((4, 5, 3), np.uint8))
    assert (read_image(target) == old).all()  # the old image stands, and no temporary is left
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene_000.png"]
