"""Devices: the training path keeps every tensor on its inputs' device.

Without a GPU the placement is checked on the CPU: the model and the batch stay on the CPU while PyTorch's default
device is ``meta``, so any tensor made without ``device=`` lands on ``meta`` and the first operation that mixes it with
a CPU tensor raises. With CUDA (the lent GPU machine), a short training run on the GPU matches the CPU's."""

import dataclasses

import pytest
import torch

from prismonet.model.trainer import TrainConfig, TrainingError, training_device


@pytest.fixture(scope="module")
def scenes():
    """The shipped Clevr test scenes (packed, split ``test``): no renderer needed, so this runs where open3d is not."""
    from prismonet.assets import shipped_samples

    return shipped_samples()


VARIANTS = {
    "clevr": {},
    "refiner": {"refine_passes": 1, "refiner_glimpse": 0.375, "refiner_coords": True, "refiner_shape": True,
                "refiner_keep": True},
    "presence": {"num_slots": 4, "presence": True},
    "full_rotation": {"full_rotation": True, "pose_frame": "camera"},
}


@pytest.mark.parametrize("variant", list(VARIANTS))
def test_forward_and_backward_make_no_tensor_off_the_inputs_device(scenes, variant):
    from prismonet.data.dataset import SceneDataset
    from prismonet.model.config import ModelConfig
    from prismonet.model.losses import LossConfig, compute_losses
    from prismonet.model.prismonet import PriSMONet

    torch.manual_seed(0)
    model = PriSMONet(ModelConfig(soft_mask_tau=0.05, **VARIANTS[variant]))
    batch = SceneDataset(scenes, "test").batch(range(4))
    loss_cfg = LossConfig(w_mask=0.1, mask_from_depth=True, w_pose=0.1)
    for step in (0, 50_000):  # blurred, then sharp
        with torch.device("meta"):
            out = model(batch.rgb, batch.K, batch.T_world_cam, batch.ground_z)
            terms = compute_losses(model, out, batch, loss_cfg, step)
            terms.total.backward()
        assert terms.total.device.type == "cpu" and torch.isfinite(terms.total)


def test_the_probe_catches_a_tensor_made_without_a_device():
    x = torch.ones(3)
    with torch.device("meta"), pytest.raises(RuntimeError, match="device"):
        x + torch.zeros(3)


def test_asking_for_cuda_without_it_is_one_clear_error():
    if torch.cuda.is_available():
        pytest.skip("this machine has CUDA")
    with pytest.raises(TrainingError, match="no CUDA device"):
        training_device("cuda")
    assert training_device("auto") == torch.device("cpu")
    with pytest.raises(ValueError, match="device must be"):
        TrainConfig(device="gpu")


def test_the_prior_follows_the_model_and_is_never_moved_in_place():
    from prismonet.model.prismonet import PriSMONet

    model = PriSMONet()
    prior = model.prior
    assert model.to("cpu").prior is prior  # already there: no copy
    model.to("meta")
    assert model.prior.latents.device.type == "meta"
    assert next(model.prior.decoder.parameters()).device.type == "meta"
    assert prior.latents.device.type == "cpu" and next(prior.decoder.parameters()).device.type == "cpu"


def test_a_batch_moves_whole(scenes):
    from prismonet.data.dataset import SceneDataset

    batch = SceneDataset(scenes, "test").batch([0, 1])
    assert batch.to("cpu") is batch
    moved = batch.to("meta")
    assert all(getattr(moved, f.name).device.type == "meta" for f in dataclasses.fields(moved))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA (run on the lent GPU machine)")
def test_training_on_cuda_matches_the_cpu(scenes, tmp_path):
    import json

    from prismonet.model.trainer import train

    logs = {}
    for device in ("cpu", "cuda"):
        cfg = TrainConfig(data=str(scenes), split="test", steps=3, batch_size=4, lr=1e-3, log_every=1, checkpoint_every=3,
                          image_every=3, seed=3, threads=1, device=device)
        train(cfg, tmp_path / device, progress=False)
        logs[device] = [json.loads(line) for line in (tmp_path / device / "log.jsonl").read_text().splitlines()]
    for a, b in zip(logs["cpu"], logs["cuda"]):
        assert a["total"] == pytest.approx(b["total"], rel=2e-3, abs=1e-5), (a, b)
    assert (tmp_path / "cuda" / "model.safetensors").is_file() and (tmp_path / "cuda" / "images").is_dir()


def test_the_search_plan_by_device_and_that_it_finds_the_same_crossings():
    from prismonet.render.raymarch import ACCEL_BLOCK_POINTS, BLOCK_POINTS, SEARCH_CHUNK, find_crossings, search_plan

    assert search_plan(torch.device("cpu"), 32) == (BLOCK_POINTS, SEARCH_CHUNK) == (16384, 4)
    assert search_plan(torch.device("meta"), 32) == (ACCEL_BLOCK_POINTS, 32)  # any accelerator: all samples at once
    assert search_plan(torch.device("meta"), 12, 100, 40) == (100, 12)  # given values win; a chunk is at most the samples
    g = torch.Generator().manual_seed(0)
    R = 3000
    o = torch.randn(R, 3, generator=g) * 0.3 + torch.tensor([0.0, 0.0, -3.0])
    d = torch.nn.functional.normalize(torch.randn(R, 3, generator=g) * 0.25 + torch.tensor([0.0, 0.0, 1.0]), dim=-1)
    z = torch.zeros(R, 1)
    sphere = lambda z, x: x.norm(dim=-1) - 0.6  # noqa: E731
    t0, t1 = torch.full((R,), 1.0), torch.full((R,), 5.0)
    cpu = find_crossings(sphere, z, o, d, t0, t1, 32, track_min=True)
    accel = find_crossings(sphere, z, o, d, t0, t1, 32, block_points=ACCEL_BLOCK_POINTS, chunk=32, track_min=True)
    assert 0 < cpu.ray.numel() < R
    for a, b in ((cpu.ray, accel.ray), (cpu.t_a, accel.t_a), (cpu.t_b, accel.t_b), (cpu.miss_ray, accel.miss_ray), (cpu.t_min, accel.t_min)):
        assert torch.equal(a, b)


def test_the_distillation_search_makes_no_tensor_off_the_inputs_device(scenes):
    """``prismonet distill --device cuda`` runs the test-time steps on the GPU (session 76: 9,000 Clevr scenes in 4
    minutes on a lent H200). The same probe as above on that path: the search with footprint shape trials, the far clip
    and the colour fit, on the shipped model."""
    from prismonet.data.dataset import SceneDataset
    from prismonet.model.inference import InferenceConfig, infer
    from prismonet.model.io import load_model, training_loss_config

    model, info = load_model("clevr3_fc")
    batch = SceneDataset(scenes, "test").batch([0])
    cfg = InferenceConfig.of(search=1, fit_color=2, search_far_clip=True,
                             search_set=["shape_trials=true", "shape_footprint=true", "shape_yaws=[30]", "shape_polish=1"])
    with torch.device("meta"):
        out = infer(model.eval(), batch, cfg, training_loss_config(info))
    assert out.composite.image.device.type == "cpu" and torch.isfinite(out.composite.image).all()


def test_reseeding_texture_fits_make_no_tensor_off_the_inputs_device():
    """The same probe on re-seeding's texture fits (``reseed._fit_textures``: all of a round's trials in one batch), with a
    trial that hits nothing beside one that hits."""
    from prismonet.data.clevr import ClevrConfig, clevr_camera
    from prismonet.model.io import load_model
    from prismonet.model.reseed import _fit_textures
    from prismonet.render import SceneParams
    from prismonet.render.renderer import render_objects

    model = load_model("clevr3_fc")[0].eval()
    cam = clevr_camera(ClevrConfig(image_size=64))
    K, T = cam.K[None], cam.T_world_cam[None]
    one = lambda x: SceneParams(model.prior.latents[:1][None], torch.zeros(1, 1, model.cfg.tex_dim), torch.tensor([[[x, 0.0, 0.5]]]),  # noqa: E731
                                torch.tensor([[[1.0, 0.0]]]), torch.tensor([[0.5]]))
    trials = [(p, render_objects(model.sdf_fn, None, p, K, T, 64, 64)) for p in (one(0.0), one(40.0))]
    target, region = torch.rand(1, 3, 64, 64), torch.ones(1, 64, 64, dtype=torch.bool)
    with torch.device("meta"):
        fitted = _fit_textures(model, trials, target, region)
    assert [z.device.type for z in fitted] == ["cpu", "cpu"] and not torch.equal(fitted[0], trials[0][0].z_tex)
    assert torch.equal(fitted[1], trials[1][0].z_tex)  # nothing hit: kept


@pytest.mark.parametrize("command", [["distill"], ["refiner", "--targets", "t"]])
def test_distill_and_refiner_on_cuda_without_it_is_one_clear_line(command, tmp_path, capsys):
    if torch.cuda.is_available():
        pytest.skip("this machine has CUDA")
    from prismonet.cli import main

    argv = [command[0], "clevr3_fc", str(tmp_path / "nothing"), *command[1:], "--out", str(tmp_path / "o"), "--device", "cuda"]
    assert main(argv) != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no CUDA device" in err[0]


def test_the_refiner_fit_makes_no_tensor_off_the_inputs_device(scenes):
    """``prismonet refiner --device cuda``: the same probe on the refiner fit's encoder cache and its loss (keep, shape
    and colour terms), forward and backward, with targets that are the cache's own latents moved a little."""
    from prismonet.data.dataset import SceneDataset
    from prismonet.model.config import ModelConfig
    from prismonet.model.distill import DistillTargets, DistillWeights
    from prismonet.model.prismonet import PriSMONet
    from prismonet.model.refiner_fit import _held_out_loss, _loss, encoder_cache, with_refiner

    torch.manual_seed(0)
    model = with_refiner(PriSMONet(ModelConfig(soft_mask_tau=0.05)), refiner_glimpse=0.375, refiner_coords=True,
                         refiner_shape=True, refiner_keep=True)
    ds = SceneDataset(scenes, "test")
    targets = DistillTargets.__new__(DistillTargets)
    with torch.device("meta"):
        cache = encoder_cache(model, ds, 4, batch_size=2, progress=False)
        targets.t = {k: cache[k] + 0.05 for k in ("scale", "position", "cos_sin", "z_tex", "z_sh")}
        targets.t.update(bg_color=torch.full((4, 3), 0.5, device="cpu"), visible=torch.full((4, 3), 100.0, device="cpu"))
        targets.count = 4
        model.refiner.train()
        loss = _loss(model, cache, ds, targets, torch.arange(4, device="cpu"), DistillWeights(background=0.0, texture=0.1), 0.1)
        loss.backward()
        held = _held_out_loss(model, cache, ds, targets, torch.arange(2, 4, device="cpu"), DistillWeights(background=0.0, texture=0.1))
    assert loss.device.type == "cpu" and torch.isfinite(loss) and held == held
    assert all(p.grad is not None for p in model.refiner.parameters() if p.requires_grad)


@pytest.mark.parametrize("command", [["train", "configs/clevr3.json"], ["distill", "clevr3_fc", "DATA"],
                                     ["refiner", "clevr3_fc", "DATA", "--targets", "t"]])
def test_a_device_name_pytorch_does_not_know_is_one_clear_line(command, tmp_path, capsys):
    from prismonet.cli import main

    assert main([*command, "--out", str(tmp_path / "o"), "--device", "gpu"]) != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].endswith("device must be 'cpu', 'cuda', 'cuda:N' or 'auto', got 'gpu'") and "Traceback" not in "".join(err)


def test_evaluate_on_cuda_without_it_is_one_clear_line(tmp_path, capsys):
    if torch.cuda.is_available():
        pytest.skip("this machine has CUDA")
    from prismonet.cli import main

    assert main(["evaluate", "clevr3_fc", str(tmp_path / "nothing"), "--device", "cuda"]) != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no CUDA device" in err[0]


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA (run on the lent GPU machine)")
def test_evaluate_on_cuda_gives_the_cpus_measures(scenes):
    """``prismonet evaluate --device cuda``: the search and colour fit on the GPU, the measures on the CPU. Detections
    must agree with the CPU's (a float's last bits may move a boundary pixel, not a match)."""
    from prismonet.data.dataset import SceneDataset
    from prismonet.evaluation.evaluate import evaluate_model
    from prismonet.model.inference import InferenceConfig
    from prismonet.model.io import load_model, training_loss_config

    ds = SceneDataset(scenes, "test")
    cfg = InferenceConfig.of(search=1, fit_color=5)
    res = {}
    for device in ("cpu", "cuda"):
        model, info = load_model("clevr3_fc")
        res[device] = evaluate_model(model, ds, batch_size=4, limit=8, progress=False, inference=cfg,
                                     loss_cfg=training_loss_config(info), device=device)
    assert res["cuda"]["device"] == "cuda" and res["cpu"]["device"] == "cpu"
    for k in ("AP0.5", "AR0.5", "count_exact"):
        assert abs(res["cpu"][k] - res["cuda"][k]) <= 0.05, k
    assert abs(res["cpu"]["PSNR"] - res["cuda"]["PSNR"]) < 0.5


def test_evaluate_with_a_device_name_pytorch_does_not_know_is_one_clear_line(tmp_path, capsys):
    from prismonet.cli import main

    assert main(["evaluate", "clevr3_fc", str(tmp_path / "nothing"), "--device", "gpu"]) != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].endswith("device must be 'cpu', 'cuda', 'cuda:N' or 'auto', got 'gpu'")
