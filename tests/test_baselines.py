"""The 2-D baselines: shapes, masks that partition the image, finite losses that fall on a few scenes."""

import math

import pytest
import torch

from prismonet.assets import shipped_samples
from prismonet.baselines.slot_attention import SlotAttention, SlotAttentionAutoEncoder, SlotAttentionConfig, position_grid
from prismonet.data.dataset import SceneDataset


def test_position_grid_corners():
    g = position_grid(3, 5)
    assert g.shape == (3, 5, 4) and torch.equal(g[0, 0], torch.tensor([0.0, 0.0, 1.0, 1.0])) and torch.equal(g[2, 4], torch.tensor([1.0, 1.0, 0.0, 0.0]))


def test_slot_attention_shapes_and_competition():
    cfg = SlotAttentionConfig(num_slots=5, slot_dim=16)
    sa = SlotAttention(cfg, in_dim=8)
    slots, attn = sa(torch.randn(2, 30, 8), torch.Generator().manual_seed(0))
    assert slots.shape == (2, 5, 16) and attn.shape == (2, 5, 30)
    assert torch.allclose(attn.sum(1), torch.ones(2, 30) + 5 * cfg.eps, atol=1e-5)  # softmax over slots: they compete


def test_autoencoder_output_and_bad_config():
    model = SlotAttentionAutoEncoder(SlotAttentionConfig(num_slots=4))
    out = model(torch.rand(2, 3, 64, 64), torch.Generator().manual_seed(0))
    assert out.image.shape == (2, 3, 64, 64) and out.masks.shape == (2, 4, 64, 64) and out.colors.shape == (2, 4, 3, 64, 64)
    assert torch.allclose(out.masks.sum(1), torch.ones(2, 64, 64), atol=1e-5)
    with pytest.raises(ValueError, match="image_size"):
        SlotAttentionConfig(image_size=60)


def test_loss_falls_on_a_few_scenes():
    torch.manual_seed(0)
    rgb = SceneDataset(shipped_samples(), "test").batch([0, 1, 2, 3]).rgb
    model = SlotAttentionAutoEncoder(SlotAttentionConfig(num_slots=4, hidden=32, slot_dim=32))
    opt = torch.optim.Adam(model.parameters(), lr=4e-4)
    losses = []
    for step in range(25):
        loss = model.loss(rgb, torch.Generator().manual_seed(step))
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    # measured 0.0901 -> 0.0847 (means of the first and last 5 steps): the grey ground is learnt first
    assert all(torch.isfinite(torch.tensor(losses))) and sum(losses[-5:]) / 5 < 0.97 * sum(losses[:5]) / 5, losses


def test_instances_from_masks_background_is_the_ground_slot():
    import numpy as np

    from prismonet.baselines.train import instances_from_masks

    masks = np.zeros((1, 3, 2, 3))
    masks[0, 1] = 1.0  # slot 1 covers everything but two pixels
    masks[0, 0, 0, 0] = masks[0, 2, 1, 2] = 2.0
    gt = np.array([[[1, 0, 0], [0, 0, 2]]])
    assert instances_from_masks(masks, gt).tolist() == [[[1, 0, 0], [0, 0, 2]]]  # slot 0 -> 1, slot 1 -> 0, slot 2 -> 2


def test_train_resume_and_evaluate_commands(tmp_path, capsys):
    import json

    from prismonet.cli import main

    samples = str(shipped_samples())
    small = ["--set", f"data={samples}", "--set", "split=test", "--set", "batch_size=2", "--set", "log_every=1",
             "--set", "slot_attention.hidden=16", "--set", "slot_attention.slot_dim=16", "--set", "checkpoint_every=2"]
    run = str(tmp_path / "sa")
    assert main(["baselines", "train", "slot_attention", "--out", run, "--set", "steps=2", *small, "--quiet"]) == 0
    assert main(["baselines", "train", "slot_attention", "--out", run, "--set", "steps=2", *small, "--set", "lr=1e-3",
                 "--quiet"]) != 0  # another config
    assert "another config" in capsys.readouterr().err
    assert main(["baselines", "train", "slot_attention", "--out", run, "--set", "steps=3", *small, "--quiet"]) == 0  # longer
    rows = [json.loads(line) for line in (tmp_path / "sa" / "log.jsonl").read_text().splitlines()]
    assert [r["step"] for r in rows] == [1, 2, 3]
    assert main(["baselines", "evaluate", run, samples, "--limit", "4", "--json", str(tmp_path / "r.json")]) == 0
    r = json.loads((tmp_path / "r.json").read_text())
    assert r["scenes"] == 4 and 0 <= r["AP0.5"] <= 1 and 0 <= r["img_RMSE"] <= 1


def test_monet_masks_partition_the_image_by_stick_breaking():
    from prismonet.baselines.monet import MONet, MONetConfig

    torch.manual_seed(0)
    model = MONet(MONetConfig(num_slots=3, blocks=3, unet_channels=8, vae_channels=(8, 8), decoder_channels=8, image_size=16))
    rgb = torch.rand(2, 3, 16, 16)
    log_m = model.attention_masks(rgb)
    assert log_m.shape == (2, 3, 16, 16)
    assert torch.allclose(torch.logsumexp(log_m, 1), torch.zeros(2, 16, 16), atol=1e-5)  # the masks sum to 1
    # the first mask is alpha_1 itself: sigmoid of the attention net's logits on an empty (log 1 = 0) scope
    a = model.attention(rgb, torch.zeros(2, 1, 16, 16))
    assert torch.allclose(log_m[:, :1], torch.nn.functional.logsigmoid(a), atol=1e-6)
    model.eval()
    out = model(rgb)
    assert out.image.shape == (2, 3, 16, 16) and out.colors.shape == (2, 3, 3, 16, 16) and out.latents.shape == (2, 3, 16)
    assert torch.allclose(out.image, (out.masks[:, :, None] * out.colors).sum(1))
    with pytest.raises(ValueError, match="divisible"):
        MONetConfig(image_size=60)


def test_monet_loss_falls_on_a_few_scenes():
    from prismonet.baselines.monet import MONet, MONetConfig

    torch.manual_seed(0)
    rgb = SceneDataset(shipped_samples(), "test").batch([0, 1, 2, 3]).rgb
    model = MONet(MONetConfig(num_slots=4, unet_channels=8, vae_channels=(16, 16, 16, 16), decoder_channels=16))
    opt = torch.optim.Adam(model.parameters(), lr=1e-3)
    losses = []
    for step in range(20):
        loss = model.loss(rgb, torch.Generator().manual_seed(step))
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert all(torch.isfinite(torch.tensor(losses))) and sum(losses[-5:]) / 5 < 0.9 * sum(losses[:5]) / 5, losses


@pytest.mark.parametrize("name, sizes", [
    ("monet", ["monet.unet_channels=8", "monet.vae_channels=[8,8,8,8]", "monet.decoder_channels=8"]),
    ("genesis", ["genesis.latent_dim=8", "genesis.enc_channels=[8,8,8,8]", "genesis.dec_channels=8", "genesis.lstm=16"]),
])
def test_baseline_trains_and_evaluates_from_the_command_line(tmp_path, name, sizes):
    import json

    from prismonet.cli import main

    samples = str(shipped_samples())
    small = [f"data={samples}", "split=test", "batch_size=2", "lr=1e-4", *sizes]
    run = str(tmp_path / name)
    assert main(["baselines", "train", name, "--out", run, "--set", "steps=2", *[a for kv in small for a in ("--set", kv)], "--quiet"]) == 0
    assert main(["baselines", "evaluate", run, samples, "--limit", "4", "--json", str(tmp_path / "r.json")]) == 0
    r = json.loads((tmp_path / "r.json").read_text())
    assert r["baseline"] == name and r["scenes"] == 4 and 0 <= r["ARI"] <= 1


def _small_genesis(**kw):
    from prismonet.baselines.genesis import Genesis, GenesisConfig

    return Genesis(GenesisConfig(num_slots=3, latent_dim=8, image_size=16, enc_channels=(8, 8), dec_channels=8, lstm=16, **kw))


def test_genesis_masks_kl_and_geco():
    from prismonet.baselines.genesis import _kl, stick_breaking

    torch.manual_seed(0)
    logits = torch.randn(2, 3, 5, 5)
    log_pi = stick_breaking(logits)
    assert torch.allclose(torch.logsumexp(log_pi, 1), torch.zeros(2, 5, 5), atol=1e-6)
    assert torch.allclose(log_pi[:, 0], torch.nn.functional.logsigmoid(logits[:, 0]))
    # the closed-form KL against torch.distributions
    mq, sq, mp, sp = torch.randn(4, 6), torch.rand(4, 6) + 0.1, torch.randn(4, 6), torch.rand(4, 6) + 0.1
    ref = torch.distributions.kl_divergence(torch.distributions.Normal(mq, sq), torch.distributions.Normal(mp, sp)).sum(-1)
    assert torch.allclose(_kl(mq, sq, mp, sp), ref, atol=1e-5)
    model = _small_genesis()
    rgb = torch.rand(2, 3, 16, 16)
    out = model.eval()(rgb)
    assert out.masks.shape == (2, 3, 16, 16) and torch.allclose(out.masks.sum(1), torch.ones(2, 16, 16), atol=1e-5)
    # GECO: an untrained model reconstructs worse than the goal, so lambda grows; it is a checkpointed buffer
    model.train()
    model.loss(rgb, torch.Generator().manual_seed(0))
    assert float(model.geco_lambda) > 1.0 and "geco_lambda" in model.state_dict()
    easy = _small_genesis(geco_goal=100.0)  # a goal any reconstruction meets: lambda stays at its floor, 1
    easy.loss(rgb, torch.Generator().manual_seed(0))
    assert float(easy.geco_lambda) == 1.0


def test_genesis_loss_falls_on_a_few_scenes():
    from prismonet.baselines.genesis import Genesis, GenesisConfig

    torch.manual_seed(0)
    rgb = SceneDataset(shipped_samples(), "test").batch([0, 1, 2, 3]).rgb
    model = Genesis(GenesisConfig(num_slots=4, latent_dim=16, enc_channels=(16, 16, 16, 16), dec_channels=16, lstm=32, geco_lr=0.0))
    opt = torch.optim.Adam(model.parameters(), lr=3e-3)
    # with sigma_x = 0.7 a perfect fit still costs 0.5622 nats per value: compare what is above that floor
    floor = 3 * 64 * 64 * (math.log(0.7) + 0.5 * math.log(2 * math.pi))
    excess = []
    for step in range(20):
        loss = model.loss(rgb, torch.Generator().manual_seed(step))
        opt.zero_grad()
        loss.backward()
        opt.step()
        excess.append(loss.item() - floor)
    # measured: 1376 -> 1317 (sums of the first and last 5 steps above the floor)
    assert all(map(math.isfinite, excess)) and sum(excess[-5:]) < 0.97 * sum(excess[:5]), excess


def test_mask_figure_has_a_labelled_column_per_model(tmp_path):
    import cv2

    from prismonet.cli import main

    samples = str(shipped_samples())
    small = ["--set", f"data={samples}", "--set", "split=test", "--set", "batch_size=2",
             "--set", "slot_attention.hidden=16", "--set", "slot_attention.slot_dim=16"]
    run = str(tmp_path / "sa")
    assert main(["baselines", "train", "slot_attention", "--out", run, "--set", "steps=1", *small, "--quiet"]) == 0
    assert main(["baselines", "figure", run, run, "--data", samples, "--scenes", "3", "--out", str(tmp_path / "f.png")]) == 0
    img = cv2.imread(str(tmp_path / "f.png"))
    # 3 rows of (18-px label + 128-px panel), 4-px gaps; input, truth, PriSMONet and two baselines
    assert img.shape[:2] == (3 * 146 + 2 * 4, 5 * 128 + 4 * 4)


def test_broadcast_decoder_without_tiling_is_the_tiled_convolution():
    from prismonet.baselines.blocks import BroadcastDecoder

    torch.manual_seed(0)
    dec = BroadcastDecoder(latent_dim=5, channels=4, out=2, image_size=8).double()
    z = torch.randn(3, 5, dtype=torch.float64, requires_grad=True)
    assert torch.allclose(dec(z), dec.tiled(z), atol=1e-12)
    g_fast = torch.autograd.grad(dec(z).square().sum(), [z, dec.net[0].weight])
    g_ref = torch.autograd.grad(dec.tiled(z).square().sum(), [z, dec.net[0].weight])
    assert all(torch.allclose(a, b, atol=1e-10) for a, b in zip(g_fast, g_ref))
    assert torch.autograd.gradcheck(lambda x: dec(x), (z,))
