"""Test-time refinement of the scene latents through the differentiable renderer."""

import torch

from prismonet.assets import shipped_samples
from prismonet.data.dataset import SceneDataset
from prismonet.model.io import load_model, training_loss_config
from prismonet.model.losses import compute_losses
from prismonet.model.refine import FINAL_STEP, RefineConfig, refine, render_latents


def test_render_latents_reproduces_the_forward_pass():
    model, _ = load_model("shipped")
    b = SceneDataset(shipped_samples(), split="test").batch([3])
    with torch.no_grad():
        out = model(b.rgb, b.K, b.T_world_cam, b.ground_z)
        again = render_latents(model, out.latents.params, out.latents.bg_color, b.K, b.T_world_cam, b.ground_z, 64, 64)
    assert torch.allclose(again.composite.image, out.composite.image, atol=1e-6)
    assert torch.equal(again.composite.instance, out.composite.instance)


def test_refinement_lowers_the_loss_and_keeps_the_weights():
    model, info = load_model("shipped")
    loss_cfg = training_loss_config(info)
    b = SceneDataset(shipped_samples(), split="test").batch([0, 1])
    before_w = {k: v.clone() for k, v in model.state_dict().items()}
    with torch.no_grad():
        out = model(b.rgb, b.K, b.T_world_cam, b.ground_z)
        l0 = float(compute_losses(model, out, b, loss_cfg, FINAL_STEP).total)
    ref = refine(model, out, b, loss_cfg, RefineConfig(steps=8))
    with torch.no_grad():
        l1 = float(compute_losses(model, ref, b, loss_cfg, FINAL_STEP).total)
    assert l1 < 0.9 * l0, (l0, l1)
    assert all(torch.equal(v, before_w[k]) for k, v in model.state_dict().items())
    lo, hi = model.cfg.scale_range
    s = ref.latents.params.scale
    assert bool(((s >= lo - 1e-6) & (s <= hi + 1e-6)).all())
    assert torch.allclose(ref.latents.params.cos_sin.norm(dim=-1), torch.ones(2, 3), atol=1e-5)
    assert refine(model, out, b, loss_cfg, RefineConfig(steps=0)) is out
