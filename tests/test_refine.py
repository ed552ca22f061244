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
    model, info = load_model("clevr3_fc")  # from the encoder's slots: the shipped refiner takes much of the gain first
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


def test_poses_take_a_larger_first_step():
    # Adam's first step moves every parameter with a non-zero gradient by exactly its lr (up to eps).
    model, info = load_model("shipped")
    b = SceneDataset(shipped_samples(), split="test").batch([0])
    with torch.no_grad():
        out = model(b.rgb, b.K, b.T_world_cam, b.ground_z)
    p0 = out.latents.params
    ref = refine(model, out, b, training_loss_config(info), RefineConfig(steps=1, lr=0.01, pose_lr_scale=3.0))
    p1 = ref.latents.params
    step_pos = (p1.position - p0.position).abs()
    step_sh = (p1.z_sh - p0.z_sh).abs()
    assert torch.allclose(step_pos.max(), torch.tensor(0.03), atol=1e-4), step_pos
    assert bool((step_pos <= 0.03 + 1e-4).all())
    assert torch.allclose(step_sh.max(), torch.tensor(0.01), atol=1e-4)
    assert bool((step_sh <= 0.01 + 1e-4).all())


def test_refine_config_rejects_bad_step_sizes():
    import pytest
    for kwargs in ({"lr": 0.0}, {"pose_lr_scale": 0.0}, {"pose_lr_scale": -1.0}, {"steps": -1}):
        with pytest.raises(ValueError):
            RefineConfig(**kwargs)


def test_reconstruct_cli_refines_the_written_latent_scene(tmp_path):
    import json

    from prismonet.cli import main

    data = str(shipped_samples())
    for k in (0, 3):
        assert main(["reconstruct", "shipped", data, "--count", "1", "--refine", str(k), "--out", str(tmp_path / f"k{k}")]) == 0
    s0, s3 = (json.loads((tmp_path / f"k{k}" / "0.json").read_text()) for k in (0, 3))
    moved = [torch.tensor(b["position"]) - torch.tensor(a["position"]) for a, b in zip(s0["objects"], s3["objects"])]
    assert max(float(m.abs().max()) for m in moved) > 1e-3
    assert main(["reconstruct", "shipped", data, "--refine", "-1", "--out", str(tmp_path / "bad")]) != 0


def test_evaluate_cli_rejects_a_bad_pose_step_even_without_refinement(capsys):
    from prismonet.cli import main

    assert main(["evaluate", "shipped", str(shipped_samples()), "--refine-pose-lr-scale", "-1", "--quiet"]) != 0
    assert "pose_lr_scale > 0" in capsys.readouterr().err


def test_refinement_reads_no_ground_truth_even_for_a_supervised_model():
    """A model trained with L_pose and L_mask on true masks: its test-time refinement must give the same
    result whatever the batch's poses and instance masks say (only the input RGB-D may enter)."""
    from dataclasses import replace

    model, info = load_model("shipped")
    loss_cfg = replace(training_loss_config(info), w_pose=1.0, w_mask=0.5, mask_from_depth=False, w_distill=1.0)
    b = SceneDataset(shipped_samples(), split="test").batch([0, 1])
    g = torch.Generator().manual_seed(0)
    lies = replace(b, instance=torch.randint(0, 4, b.instance.shape, generator=g),
                   obj_position=b.obj_position + torch.randn(b.obj_position.shape, generator=g),
                   obj_yaw=b.obj_yaw + 1.0, obj_scale=b.obj_scale * 1.5)
    with torch.no_grad():
        out = model(b.rgb, b.K, b.T_world_cam, b.ground_z)
    a = refine(model, out, b, loss_cfg, RefineConfig(steps=3))
    c = refine(model, out, lies, loss_cfg, RefineConfig(steps=3))
    for f in ("position", "scale", "cos_sin", "z_sh", "z_tex"):
        assert torch.equal(getattr(a.latents.params, f), getattr(c.latents.params, f)), f
