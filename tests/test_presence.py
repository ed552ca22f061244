"""The explicit presence output (issue 21): slots composed as layers of opacity p in training, dropped
below p = 0.5 at inference, the encoder stopping at the first absent slot with ``stop``."""

import pytest
import torch

from prismonet.assets import shipped_samples
from prismonet.data.dataset import SceneDataset
from prismonet.model.config import ModelConfig
from prismonet.model.io import HEAD, load_model, transfer_weights
from prismonet.model.losses import LossConfig, compute_losses
from prismonet.model.prismonet import PRESENCE_INIT_LOGIT, PriSMONet
from prismonet.model.stopping import BoundStop, StopRule
from prismonet.render.composite import composite, presence_composite


def _layers(gen, B=2, K=4, H=5, W=6, dtype=torch.float64):
    depth = torch.rand(B, K, H, W, generator=gen, dtype=dtype) * 5 + 1
    mask = torch.rand(B, K, H, W, generator=gen) < 0.6
    color = torch.rand(B, K, 3, H, W, generator=gen, dtype=dtype)
    return depth, mask, color, torch.rand(B, 3, generator=gen, dtype=dtype), torch.full((B, 1, H, W), 9.0, dtype=dtype)


def test_presence_zero_or_one_is_the_zbuffer_of_the_present_slots(gen):
    depth, mask, color, bg, bg_depth = _layers(gen)
    presence = torch.tensor([[1.0, 0.0, 1.0, 1.0], [0.0, 1.0, 0.0, 1.0]], dtype=torch.float64)
    soft = presence_composite(depth, mask, color, presence, bg, bg_depth)
    hard = composite(depth, mask & (presence > 0.5)[:, :, None, None], color, bg, bg_depth)
    assert torch.equal(soft.instance, hard.instance) and torch.equal(soft.mask, hard.mask)
    assert torch.allclose(soft.image, hard.image, rtol=0, atol=1e-15)
    assert torch.allclose(soft.depth, hard.depth, rtol=0, atol=1e-15)


def test_presence_layers_by_hand():
    """One pixel, a half-present red slot at depth 2 in front of a fully present blue one at depth 3,
    listed back first: half red, half blue, nothing of the grey ground; depth 2.5."""
    depth = torch.tensor([3.0, 2.0]).reshape(1, 2, 1, 1)
    mask = torch.ones(1, 2, 1, 1, dtype=torch.bool)
    color = torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]]).reshape(1, 2, 3, 1, 1)
    c = presence_composite(depth, mask, color, torch.tensor([[1.0, 0.5]]), torch.tensor([[0.5, 0.5, 0.5]]),
                           torch.full((1, 1, 1, 1), 9.0))
    assert c.image.flatten().tolist() == [0.5, 0.0, 0.5]
    assert float(c.depth) == 2.5 and int(c.instance) == 2  # red (slot 2, 1-based) counts as present at 0.5
    c2 = presence_composite(depth, mask, color, torch.tensor([[0.25, 0.25]]), torch.tensor([[0.5, 0.5, 0.5]]),
                            torch.full((1, 1, 1, 1), 9.0))
    # red 0.25, blue 0.75 * 0.25, ground 0.75 * 0.75
    assert torch.allclose(c2.image.flatten(), torch.tensor([0.25 + 0.28125, 0.28125, 0.1875 + 0.28125]))
    assert float(c2.depth) == pytest.approx(0.25 * 2 + 0.1875 * 3 + 0.5625 * 9) and int(c2.instance) == 0


def test_presence_composite_gradcheck(gen):
    depth, mask, color, bg, bg_depth = _layers(gen, B=1, K=3, H=3, W=3)
    presence = (torch.rand(1, 3, generator=gen, dtype=torch.float64) * 0.8 + 0.1).requires_grad_()
    color.requires_grad_()
    depth.requires_grad_()
    bg.requires_grad_()
    f = lambda p, c, d, b: tuple(getattr(presence_composite(d, mask, c, p, b, bg_depth), k) for k in ("image", "depth"))
    assert torch.autograd.gradcheck(f, (presence, color, depth, bg))


@pytest.fixture(scope="module")
def batch():
    return SceneDataset(shipped_samples(), split="test").batch([0, 1])


@pytest.fixture(scope="module")
def presence_model():
    """The shipped model's weights in a model with a presence output (``init_transfer``)."""
    shipped, _ = load_model("clevr3_fc")  # no refiner: one may not be combined with a presence output
    model = PriSMONet(ModelConfig(**{**shipped.cfg.__dict__, "presence": True}))
    fresh = transfer_weights(model, shipped)
    assert fresh == [f"{HEAD} (presence rows)"]
    return shipped, model


def test_a_fresh_presence_output_starts_present_and_changes_nothing_else(presence_model, batch):
    shipped, model = presence_model
    head = model.encoder.head[-1]
    assert float(head.bias[-1].detach()) == PRESENCE_INIT_LOGIT and float(head.weight[-1].detach().abs().max()) == 0.0
    shipped.eval(), model.eval()
    with torch.no_grad():
        a = shipped(batch.rgb, batch.K, batch.T_world_cam, batch.ground_z)
        b = model(batch.rgb, batch.K, batch.T_world_cam, batch.ground_z)
    assert torch.allclose(b.presence, torch.sigmoid(torch.tensor(PRESENCE_INIT_LOGIT)).expand(2, 3))
    assert torch.equal(a.composite.instance, b.composite.instance)
    assert torch.allclose(a.latents.params.position, b.latents.params.position)


def test_training_composes_by_presence_and_charges_it(presence_model, batch):
    _, model = presence_model
    model.train()
    out = model(batch.rgb, batch.K, batch.T_world_cam, batch.ground_z)
    p = out.presence
    expect = presence_composite(out.obj_depth, out.obj_mask, out.obj_color, p, out.latents.bg_color, out.bg_depth)
    assert torch.allclose(out.composite.image, expect.image)
    base = LossConfig(w_mask=0.1, mask_from_depth=True)
    with_cost = LossConfig(w_mask=0.1, mask_from_depth=True, w_presence=0.01)
    t0, t1 = compute_losses(model, out, batch, base, 0), compute_losses(model, out, batch, with_cost, 0)
    cost = float(p.detach().sum(1).mean())
    assert float(t1.presence.detach()) == pytest.approx(cost)
    assert float((t1.total - t0.total).detach()) == pytest.approx(0.01 * cost, rel=1e-5)
    t1.total.backward()
    g = model.encoder.head[-1].bias.grad[-1]
    assert torch.isfinite(g) and float(g) != 0.0  # the presence output learns from the losses
    model.zero_grad()
    model.eval()


def test_straight_through_composes_the_present_slots_and_still_learns_presence(presence_model, batch):
    """With ``presence_straight_through`` the training composite is the z-buffer of the slots with p >= 0.5
    (as at inference), and the presence output still gets a gradient from the image loss."""
    from dataclasses import replace

    _, soft_model = presence_model
    model = PriSMONet(replace(soft_model.cfg, presence_straight_through=True))
    model.load_state_dict(soft_model.state_dict())
    head = model.encoder.head[-1]
    with torch.no_grad():  # presences that differ from slot to slot, on both sides of 0.5
        head.bias[-1] = 0.0
        head.weight[-1] = torch.randn(head.weight.shape[1], generator=torch.Generator().manual_seed(3))
    model.train()
    out = model(batch.rgb, batch.K, batch.T_world_cam, batch.ground_z)
    p = out.presence.detach()
    assert (p < 0.5).any() and (p >= 0.5).any() and ((p - 0.5).abs() > 1e-3).all(), p
    present = (p >= 0.5)[:, :, None, None]
    hard = composite(out.obj_depth, out.obj_mask & present, out.obj_color, out.latents.bg_color, out.bg_depth)
    assert torch.allclose(out.composite.image, hard.image, atol=1e-6)
    assert torch.equal(out.composite.instance, hard.instance)
    t = compute_losses(model, out, batch, LossConfig(w_mask=0.1, mask_from_depth=True), 0)
    t.total.backward()
    g = head.bias.grad[-1]
    assert torch.isfinite(g) and float(g) != 0.0
    model.zero_grad()


def test_presence_can_be_kept_out_of_the_mask_loss(presence_model, batch):
    from dataclasses import replace

    _, soft_model = presence_model
    grads = []
    for seen in (True, False):
        model = PriSMONet(replace(soft_model.cfg, presence_straight_through=True, presence_in_mask_loss=seen))
        model.load_state_dict(soft_model.state_dict())
        model.train()
        out = model(batch.rgb, batch.K, batch.T_world_cam, batch.ground_z)
        t = compute_losses(model, out, batch, LossConfig(w_mask=0.1, mask_from_depth=True), 0)
        t.mask.backward()
        grads.append(float(model.encoder.head[-1].bias.grad[-1]))
    assert grads[0] != 0.0 and grads[1] == 0.0


def test_absent_slots_are_dropped_and_stop_the_encoder(presence_model, batch):
    _, model = presence_model
    head = model.encoder.head[-1]
    keep = head.bias[-1].item()
    try:
        with torch.no_grad():
            head.bias[-1] = -10.0  # every slot absent
            out = model(batch.rgb, batch.K, batch.T_world_cam, batch.ground_z)
            assert not out.latents.params.active.any() and not out.obj_mask.any()
            assert int(out.composite.instance.max()) == 0
            calls = []
            model.encoder.register_forward_hook(lambda *a: calls.append(1))
            model(batch.rgb, batch.K, batch.T_world_cam, batch.ground_z, stop=BoundStop(StopRule(), batch.rgb, batch.depth))
            assert len(calls) == 1  # the first slot is absent in both scenes: no second encoder step
    finally:
        with torch.no_grad():
            head.bias[-1] = keep
        model.encoder._forward_hooks.clear()


def test_a_presence_model_trains_resumes_and_evaluates(tmp_path):
    """From the shipped weights (``init_transfer``), a few steps with the presence cost; the run's model
    loads with its presence output and evaluates with and without stopping."""
    from prismonet.data.clevr import ClevrConfig
    from prismonet.data.generate import generate_clevr
    from prismonet.evaluation.evaluate import evaluate_model
    from prismonet.model.trainer import TrainConfig, train

    data = tmp_path / "d"
    generate_clevr(data, ClevrConfig(num_objects=3, min_objects=1), split=(8, 0, 4), seed=5, workers=1, progress=False)
    c = TrainConfig(data=str(data), steps=3, batch_size=2, log_every=1, checkpoint_every=2, image_every=1000,
                    init_from="shipped", init_transfer=True,
                    model=ModelConfig(num_slots=3, soft_mask_tau=0.05, presence=True),
                    loss=LossConfig(w_mask=0.1, mask_from_depth=True, w_presence=0.001))
    summary = train(c, tmp_path / "run", progress=False)
    assert summary["nonfinite"] == 0
    model, _ = load_model(tmp_path / "run")
    assert model.cfg.presence and model.out_dim == PriSMONet(ModelConfig()).out_dim + 1
    ds = SceneDataset(data, "test")
    for stop in (False, True):
        from prismonet.model.inference import InferenceConfig

        r = evaluate_model(model, ds, batch_size=4, progress=False, inference=InferenceConfig(stop=StopRule() if stop else None))
        assert 0.0 <= r["AP0.5"] <= 1.0
