"""Training: loss goes down, exact resume, the non-finite guard, bad configs and checkpoints,
evaluation, and DDP with two CPU processes."""

import json
import math
import os
import subprocess
import sys

import pytest
import torch

from prismonet.config import ConfigError, load_config
from prismonet.model.io import CheckpointError, load_model
from prismonet.model.trainer import TrainConfig, TrainingError, train


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    from prismonet.data.clevr import ClevrConfig
    from prismonet.data.generate import generate_clevr

    root = tmp_path_factory.mktemp("data") / "clevr3"
    generate_clevr(root, ClevrConfig(), split=(32, 0, 8), seed=2, workers=1, progress=False)
    return root


def cfg(data, **kw):
    base = dict(data=str(data), steps=4, batch_size=4, lr=1e-3, log_every=1, image_every=1000, checkpoint_every=2, seed=3)
    base.update(kw)
    return TrainConfig(**base)


def test_short_training_reduces_loss_and_gives_finite_metrics(data, tmp_path):
    from prismonet.data.dataset import SceneDataset
    from prismonet.evaluation.evaluate import evaluate_model

    from prismonet.model.losses import compute_losses
    from prismonet.model.prismonet import PriSMONet

    run = tmp_path / "run"
    c = cfg(data, steps=60, batch_size=8, lr=2e-3, image_every=60)
    summary = train(c, run, progress=False)
    torch.manual_seed(c.seed)
    initial = PriSMONet(c.model)  # the trainer's initialisation
    trained, _ = load_model(run)
    batch = SceneDataset(data, "train").batch(range(16))

    def loss(m):
        with torch.no_grad():
            return float(compute_losses(m, m(batch.rgb, batch.K, batch.T_world_cam, batch.ground_z), batch, c.loss, 0).total)

    before, after = loss(initial), loss(trained)
    assert after < 0.8 * before, (before, after)
    assert summary["nonfinite"] == 0 and (run / "images" / "step_0000060.png").is_file()
    import cv2

    from prismonet.viz.decomposition import LABEL_HEIGHT

    grid = cv2.imread(str(run / "images" / "step_0000060.png"))  # 4 scenes x 5 labelled 128-px panels
    assert grid.shape == (4 * (LABEL_HEIGHT + 128), 5 * 128, 3) and (grid[0, :, :] == 255).all()  # white label strips
    assert any((run / "tb").iterdir())
    res = evaluate_model(trained, SceneDataset(data, "test"), batch_size=8, progress=False)
    assert all(math.isfinite(res[k]) for k in ("AP0.5", "AR0.5", "PSNR", "SSIM", "depth_RMSE", "ARI"))


def test_resume_after_kill_is_exact(data, tmp_path):
    a = train(cfg(data), tmp_path / "a", progress=False)
    train(cfg(data), tmp_path / "b", progress=False, stop_after=2)
    assert not (tmp_path / "b" / "model.safetensors").exists()
    b = train(cfg(data), tmp_path / "b", progress=False)
    ma, _ = load_model(tmp_path / "a")
    mb, _ = load_model(tmp_path / "b")
    for (k, v), (_, w) in zip(ma.state_dict().items(), mb.state_dict().items()):
        assert torch.equal(v, w), k
    assert a["last"] == b["last"]
    with pytest.raises(TrainingError, match="another config"):
        train(cfg(data, lr=5e-4), tmp_path / "b", progress=False)


def test_non_finite_losses_are_skipped_then_stop(data, tmp_path, monkeypatch):
    from prismonet.model import trainer

    real = trainer.compute_losses

    def nan_losses(*args, **kw):
        terms = real(*args, **kw)
        terms.total = terms.total * float("nan")
        return terms

    monkeypatch.setattr(trainer, "compute_losses", nan_losses)
    with pytest.raises(TrainingError, match=r"3 non-finite losses \(max_nonfinite=2\)"):
        train(cfg(data, steps=10, max_nonfinite=2), tmp_path / "nan", progress=False)


def test_bad_configs(tmp_path):
    with pytest.raises(ConfigError, match=r"unknown field\(s\) \['stepz'\]"):
        load_config(TrainConfig, overrides=["stepz=3"])
    with pytest.raises(ConfigError, match=r"model.: unknown field\(s\) \['slots'\]"):
        load_config(TrainConfig, overrides=["model.slots=3"])
    with pytest.raises(ValueError, match="steps, batch_size and lr must be positive"):
        load_config(TrainConfig, overrides=["lr=-1"])
    with pytest.raises(ValueError, match="inputs: expected one of"):
        load_config(TrainConfig, overrides=["model.inputs=depth"])
    (tmp_path / "bad.json").write_text("{oops")
    with pytest.raises(ConfigError, match="not valid JSON"):
        load_config(TrainConfig, tmp_path / "bad.json")


def test_every_training_config_in_the_repository_loads():
    """Each recorded recipe in ``configs/`` still parses into a ``TrainConfig`` (a renamed or removed field shows
    here, not hours into someone's rerun); ``ablation_5k.json`` is the ablation table's spec, not a recipe."""
    from pathlib import Path

    root = Path(__file__).resolve().parents[1] / "configs"
    recipes = [p for p in sorted(root.glob("*.json")) if "rows" not in json.loads(p.read_text())]
    assert len(recipes) >= 40
    for path in recipes:
        c = load_config(TrainConfig, path)
        assert c.steps > 0 and c.batch_size > 0, path.name
    wide = load_config(TrainConfig, root / "clevr3_wide_distill.json")
    assert wide.init_widen and wide.model.channels == (64, 64, 128, 128) and wide.model.fc == (512, 512)


def test_dataset_that_does_not_fit_the_model(data, tmp_path):
    with pytest.raises(ValueError, match="images are 64x64 but the model expects 32x32"):
        train(cfg(data, model=load_config(TrainConfig, overrides=["model.image_size=32", "model.channels=[16,16]"]).model), tmp_path / "r", progress=False)


def test_bad_checkpoints(data, tmp_path):
    from prismonet.data.dataset import SceneDataset
    from prismonet.evaluation.evaluate import check_compatible

    run = tmp_path / "run"
    train(cfg(data, steps=1), run, progress=False)
    with pytest.raises(CheckpointError, match="no such model config"):
        load_model(tmp_path / "nothing")
    # corrupted weights
    weights = (run / "model.safetensors").read_bytes()
    (run / "model.safetensors").write_bytes(weights[:100])
    with pytest.raises(CheckpointError, match="not a readable safetensors checkpoint"):
        load_model(run)
    (run / "model.safetensors").write_bytes(weights)
    # a checkpoint from a different configuration
    info = json.loads((run / "model.json").read_text())
    info["model"]["fc"] = [128, 128]
    (run / "model.json").write_text(json.dumps(info))
    with pytest.raises(CheckpointError, match="does not fit this configuration|has shape"):
        load_model(run)
    info["model"]["fc"] = [256, 256]
    info["prior_fingerprint"] = "0000"
    (run / "model.json").write_text(json.dumps(info))
    with pytest.raises(CheckpointError, match="another shape prior"):
        load_model(run)
    (run / "model.json").write_text("{")
    with pytest.raises(CheckpointError, match="corrupted or incompatible model config"):
        load_model(run)
    # a dataset with another camera
    train(cfg(data, steps=1), tmp_path / "ok", progress=False)
    model, info = load_model(tmp_path / "ok")
    info["camera_K"][0][0] *= 1.5
    with pytest.raises(ValueError, match="differs from the model's training camera"):
        check_compatible(model, info, SceneDataset(data, "test"))


def test_ddp_two_cpu_processes(data, tmp_path):
    """The same training under torchrun with 2 processes (gloo). Every rank draws the global batch's scene indices and
    noise and keeps its share, so DDP's average of the two half-batch gradients is the full-batch gradient: the result
    must equal a single-process run of the same config, input noise included; the logged losses are the whole batch's."""
    run = tmp_path / "ddp"
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    cmd = [sys.executable, "-m", "torch.distributed.run", "--nproc_per_node", "2", "--master_port", "29517",
           "-m", "prismonet", "train", "-", "--out", str(run), "--quiet",
           "--set", f"data={data}", "--set", "steps=3", "--set", "batch_size=4", "--set", "log_every=1", "--set", "checkpoint_every=3"]
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=240)
    assert proc.returncode == 0, proc.stderr[-3000:]
    summary = json.loads([line for line in proc.stdout.splitlines() if line.startswith("{")][0])
    assert summary["world_size"] == 2 and summary["steps"] == 3
    rows = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]
    assert len(rows) == 3 and all(math.isfinite(r["total"]) for r in rows)
    ddp, _ = load_model(run)  # rank 0 wrote a loadable model
    single = train(TrainConfig(data=str(data), steps=3, batch_size=4, log_every=1, checkpoint_every=3),
                   tmp_path / "single", progress=False)
    assert TrainConfig().input_noise > 0  # the noise is on: it is drawn for the global batch
    ref, _ = load_model(tmp_path / "single")
    for (k, v), (_, w) in zip(ddp.state_dict().items(), ref.state_dict().items()):
        assert torch.allclose(v, w, atol=1e-5, rtol=1e-4), k
    solo = [json.loads(line) for line in (tmp_path / "single" / "log.jsonl").read_text().splitlines()]
    for r, s in zip(rows, solo):  # the logged losses are the global batch's, not rank 0's half
        assert r["total"] == pytest.approx(s["total"], rel=1e-4), (r, s)
    assert single["last"]["total"] != 0


def _finite_rank(rank: int, port: int, queue) -> None:
    os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port))
    torch.distributed.init_process_group("gloo", rank=rank, world_size=2)
    from prismonet.model.trainer import _finite_everywhere

    try:
        nan_on_one = _finite_everywhere(torch.tensor(float("nan") if rank == 1 else 1.0), 2)
        finite = _finite_everywhere(torch.tensor(2.0), 2)
        queue.put((rank, nan_on_one, finite))
    finally:
        torch.distributed.destroy_process_group()


def test_a_non_finite_loss_on_one_rank_skips_the_step_on_every_rank():
    """Under DDP a rank that skipped its backward alone would leave the other waiting in the gradient all-reduce for
    good: the finite check is agreed over the ranks (a NaN on rank 1 reads as non-finite on rank 0 too)."""
    import torch.multiprocessing as mp

    queue = mp.get_context("spawn").SimpleQueue()
    mp.spawn(_finite_rank, args=(29523, queue), nprocs=2, join=True)
    got = sorted(queue.get() for _ in range(2))
    assert got == [(0, False, True), (1, False, True)]


def test_sigterm_saves_a_checkpoint_then_resumes(data, tmp_path):
    """``kill`` (SIGTERM) ends training like Ctrl-C: a checkpoint at the last completed step."""
    import signal
    import time

    run = tmp_path / "run"
    cmd = [sys.executable, "-m", "prismonet", "train", "-", "--out", str(run), "--quiet", "--set", f"data={data}",
           "--set", "steps=1000", "--set", "batch_size=2", "--set", "log_every=1", "--set", "checkpoint_every=1000"]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.time() + 120
    while time.time() < deadline and not ((run / "log.jsonl").is_file() and len((run / "log.jsonl").read_text().splitlines()) >= 3):
        time.sleep(0.2)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err[-2000:]
    from prismonet.checkpoint import load_checkpoint

    _, meta = load_checkpoint(run / "checkpoint.safetensors")
    logged = len((run / "log.jsonl").read_text().splitlines())
    assert meta["step"] >= 3 and meta["step"] in (logged, logged + 1)
    # and the run resumes from it
    same = TrainConfig(data=str(data), steps=meta["step"] + 1, batch_size=2, log_every=1, checkpoint_every=1000)
    summary = train(same, run, progress=False)
    assert summary["steps"] == meta["step"] + 1


def test_reconstruct_command_writes_figures_and_latent_scenes(data, tmp_path, capsys):
    import cv2

    from prismonet.cli import main

    train(cfg(data, steps=1), tmp_path / "run", progress=False)
    assert main(["reconstruct", str(tmp_path / "run"), str(data), "--count", "2", "--out", str(tmp_path / "rec")]) == 0
    fig = cv2.imread(str(tmp_path / "rec" / "0.png"))
    assert fig is not None and fig.shape[1] > fig.shape[0]  # two rows of panels, five wide
    scene = json.loads((tmp_path / "rec" / "0.json").read_text())
    assert len(scene["objects"]) == 3 and len(scene["objects"][0]["z_sh"]) == 8
    assert main(["reconstruct", str(tmp_path / "run"), str(data), "--count", "1", "--objects", "5", "--out", str(tmp_path / "rec5")]) == 0
    assert len(json.loads((tmp_path / "rec5" / "0.json").read_text())["objects"]) == 5


def test_checkpoint_from_before_a_new_config_field_still_resumes(data, tmp_path):
    from prismonet.checkpoint import load_checkpoint, save_checkpoint

    run = tmp_path / "run"
    train(cfg(data), run, progress=False, stop_after=2)
    tensors, meta = load_checkpoint(run / "checkpoint.safetensors")
    del meta["config"]["loss"]["mask_from_depth"]  # as written before that field existed
    save_checkpoint(run / "checkpoint.safetensors", tensors, meta)
    assert train(cfg(data), run, progress=False)["steps"] == 4


def test_learning_rate_schedule_is_constant_then_a_cosine_tail():
    from prismonet.model.trainer import learning_rate

    c = TrainConfig(steps=300, lr=2e-4, lr_decay_from=100, lr_final_ratio=0.01)
    lo = 2e-6
    assert learning_rate(c, 0) == learning_rate(c, 99) == learning_rate(c, 100) == 2e-4
    assert learning_rate(c, 200) == pytest.approx((2e-4 + lo) / 2, rel=1e-12)  # cos(pi/2) = 0
    assert learning_rate(c, 150) == pytest.approx(lo + (2e-4 - lo) * (1 + math.cos(math.pi / 4)) / 2, rel=1e-12)
    assert learning_rate(c, 300) == pytest.approx(lo, rel=1e-12)
    assert learning_rate(TrainConfig(steps=300, lr=2e-4), 299) == 2e-4  # no decay: constant
    with pytest.raises(ValueError, match="lr_decay_from"):
        TrainConfig(steps=300, lr_decay_from=300)
    with pytest.raises(ValueError, match="lr_final_ratio"):
        TrainConfig(steps=300, lr_decay_from=10, lr_final_ratio=1.5)


def test_a_decay_tail_added_on_resume_matches_a_run_with_it_from_the_start(data, tmp_path):
    # train 4 constant-lr steps, then resume for 8 with a tail from step 4: the same as 8 steps with the tail set up front
    train(cfg(data, steps=4), tmp_path / "a", progress=False)
    a = train(cfg(data, steps=8, lr_decay_from=4), tmp_path / "a", progress=False)
    b = train(cfg(data, steps=8, lr_decay_from=4), tmp_path / "b", progress=False)
    assert a["last"] == b["last"]
    lrs = [json.loads(line)["lr"] for line in (tmp_path / "a" / "log.jsonl").read_text().splitlines()]
    c8 = cfg(data, steps=8, lr_decay_from=4)
    from prismonet.model.trainer import learning_rate

    assert lrs == [learning_rate(c8, s) for s in range(8)]
    assert lrs[:5] == [1e-3] * 5 and lrs[-1] < lrs[5] < 1e-3


def test_warm_restarts_begin_a_new_cosine_and_leave_earlier_steps_unchanged():
    from prismonet.model.trainer import learning_rate

    lo = 2e-6
    tail = TrainConfig(steps=300, lr=2e-4, lr_decay_from=100)
    both = TrainConfig(steps=600, lr=2e-4, lr_decay_from=100, lr_restarts=(300, 400))
    # the steps before the first restart follow the finished run's schedule exactly
    assert [learning_rate(both, s) for s in range(300)] == [learning_rate(tail, s) for s in range(300)]
    assert learning_rate(both, 300) == learning_rate(both, 400) == 2e-4  # each restart is back at lr
    assert learning_rate(both, 350) == pytest.approx((2e-4 + lo) / 2, rel=1e-12)  # half of 300..400
    assert learning_rate(both, 500) == pytest.approx((2e-4 + lo) / 2, rel=1e-12)  # half of 400..600
    assert learning_rate(both, 600) == pytest.approx(lo, rel=1e-12)
    for bad in ((300,), (50,), (100,), (400, 300)):
        with pytest.raises(ValueError, match="lr_restarts"):
            TrainConfig(steps=300 if bad == (300,) else 600, lr_decay_from=100, lr_restarts=bad)
    with pytest.raises(ValueError, match="lr_restarts needs lr_decay_from"):
        TrainConfig(steps=600, lr_restarts=(300,))
    # JSON lists become the tuple the schedule reads
    assert load_config(TrainConfig, overrides=["lr_decay_from=100", "lr_restarts=[300]", "steps=600"]).lr_restarts == (300,)


def test_a_restart_added_to_a_finished_run_matches_a_run_with_it_from_the_start(data, tmp_path):
    # 6 steps with a tail from step 2, then extended to 10 with a restart at 6 = 10 steps with both set up front
    train(cfg(data, steps=6, lr_decay_from=2), tmp_path / "a", progress=False)
    a = train(cfg(data, steps=10, lr_decay_from=2, lr_restarts=(6,)), tmp_path / "a", progress=False)
    b = train(cfg(data, steps=10, lr_decay_from=2, lr_restarts=(6,)), tmp_path / "b", progress=False)
    assert a["last"] == b["last"]
    lrs = [json.loads(line)["lr"] for line in (tmp_path / "a" / "log.jsonl").read_text().splitlines()]
    assert lrs[6] == 1e-3 and lrs[5] < lrs[2] == 1e-3 and lrs[9] < lrs[6]


def test_init_from_starts_a_run_with_a_trained_models_weights_at_another_slot_count(data, tmp_path):
    from prismonet.model.config import ModelConfig
    from prismonet.model.prismonet import PriSMONet

    train(cfg(data, steps=2), tmp_path / "src", progress=False)
    src, _ = load_model(tmp_path / "src")
    # a 4-slot run from the 3-slot model; lr so small that one Adam step moves no weight by more than ~1e-9
    train(cfg(data, steps=1, lr=1e-12, init_from=str(tmp_path / "src"), model=ModelConfig(num_slots=4)), tmp_path / "ft", progress=False)
    ft, info = load_model(tmp_path / "ft")
    assert info["model"]["num_slots"] == 4
    fresh = PriSMONet(ModelConfig(num_slots=4)).state_dict()
    moved_from_fresh = 0.0
    for k, v in src.state_dict().items():
        assert torch.allclose(ft.state_dict()[k], v, atol=1e-8, rtol=0), k
        moved_from_fresh = max(moved_from_fresh, float((fresh[k] - v).abs().max()))
    assert moved_from_fresh > 1e-4  # the check could fail: training moved weights away from an initialisation
    with pytest.raises(CheckpointError):
        train(cfg(data, steps=1, init_from=str(tmp_path / "nowhere")), tmp_path / "bad", progress=False)


def test_init_keep_positions_remaps_the_position_rows_and_copies_them_without_it(data, tmp_path):
    from prismonet.model.config import ModelConfig
    from prismonet.model.io import HEAD

    train(cfg(data, steps=2), tmp_path / "src", progress=False)
    src, _ = load_model(tmp_path / "src")
    taller = ModelConfig(position_offset=(0.0, 0.0, 0.8), position_scale=(1.5, 1.5, 1.0))
    for keep in (False, True):  # lr so small that the one step moves nothing measurable
        train(cfg(data, steps=1, lr=1e-12, init_from=str(tmp_path / "src"), init_keep_positions=keep, model=taller),
              tmp_path / f"ft{keep}", progress=False)
    plain, kept = load_model(tmp_path / "ftFalse")[0], load_model(tmp_path / "ftTrue")[0]
    z = src.sh_dim + src.cfg.tex_dim + 2  # the height row of this world-frame model
    w, b = src.state_dict()[f"{HEAD}.weight"], src.state_dict()[f"{HEAD}.bias"]
    torch.testing.assert_close(plain.state_dict()[f"{HEAD}.bias"], b, atol=1e-8, rtol=0)  # copied as it was
    # 0.4 + 0.5 raw = 0.8 + 1.0 raw'  =>  raw' = 0.5 raw - 0.4
    torch.testing.assert_close(kept.state_dict()[f"{HEAD}.weight"][z], 0.5 * w[z], atol=1e-8, rtol=0)
    torch.testing.assert_close(kept.state_dict()[f"{HEAD}.bias"][z], 0.5 * b[z] - 0.4, atol=1e-7, rtol=0)
    torch.testing.assert_close(kept.state_dict()[f"{HEAD}.bias"][: z - 2], b[: z - 2], atol=1e-8, rtol=0)  # latents


def test_a_run_records_which_weights_it_started_from_across_a_resume(data, tmp_path):
    """``init_from`` names can move (``shipped`` is whichever model ships now): the run keeps the
    fingerprint of the weights it actually started from, also when it was interrupted and resumed."""
    from prismonet.model.io import weights_fingerprint

    train(cfg(data, steps=2), tmp_path / "src", progress=False)
    src, _ = load_model(tmp_path / "src")
    run = cfg(data, steps=3, init_from=str(tmp_path / "src"))
    train(run, tmp_path / "ft", progress=False, stop_after=1)
    summary = train(run, tmp_path / "ft", progress=False)  # resumed: the source is not loaded again
    _, info = load_model(tmp_path / "ft")
    assert summary["init_weights"] == info["summary"]["init_weights"] == weights_fingerprint(src)
    assert weights_fingerprint(src) != weights_fingerprint(load_model(tmp_path / "ft")[0])
    assert "init_weights" not in load_model(tmp_path / "src")[1]["summary"]  # a run from scratch has none


def test_init_from_a_model_of_another_architecture_is_a_clear_error(data, tmp_path):
    from prismonet.model.config import ModelConfig

    train(cfg(data, steps=1), tmp_path / "src", progress=False)
    wide = cfg(data, steps=1, init_from=str(tmp_path / "src"), model=ModelConfig(fc=(128, 128)))
    with pytest.raises(CheckpointError, match=r"init_from .*src: does not fit this configuration"):
        train(wide, tmp_path / "ft", progress=False)
    assert not (tmp_path / "ft" / "checkpoint.safetensors").exists()


def test_bench_ddp_times_the_trainer_step_and_refuses_bad_variants(script, data, monkeypatch, capsys):
    """``scripts/bench_ddp.py`` (BENCHMARKS.md, session 93): its step is the trainer's, timed per step after the warm-up
    ones (here one process of one thread on a tiny set); a variant it does not know ends in one line on stderr."""
    bench = script("bench_ddp")
    times = bench._steps(str(data), 0, bench.WARM + 2, 1)
    assert len(times) == 2 and all(t > 0 for t in times)
    monkeypatch.setattr(sys, "argv", ["bench_ddp.py", "--variants", "1x2,3x3"])
    assert bench.main() == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("bench_ddp: error: ") and "3x3" in err[0]
