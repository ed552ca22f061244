"""The scene model and its losses: shapes, ablation switches doing what they claim, schedules."""

import math

import pytest
import torch

from prismonet.model.config import ModelConfig
from prismonet.model.losses import LossConfig, blur, blur_sigma, compute_losses, ground_loss, intersection_loss, mask_loss, outside_loss, pose_loss, shape_weight
from prismonet.model.prismonet import PriSMONet
from prismonet.render import SceneParams


@pytest.fixture(scope="module")
def batch(tmp_path_factory):
    from prismonet.data.clevr import ClevrConfig
    from prismonet.data.dataset import SceneDataset
    from prismonet.data.generate import generate_clevr

    root = tmp_path_factory.mktemp("ds") / "ds"
    generate_clevr(root, ClevrConfig(), split=(4, 0, 0), seed=1, workers=1, progress=False)
    return SceneDataset(root, "train").batch(range(4))


def run(model, batch):
    return model(batch.rgb, batch.K, batch.T_world_cam, batch.ground_z)


def test_forward_shapes_and_slot_count(batch):
    torch.manual_seed(0)
    model = PriSMONet(ModelConfig(num_slots=3))
    out = run(model, batch)
    assert out.composite.image.shape == (4, 3, 64, 64) and out.composite.depth.shape == (4, 1, 64, 64)
    assert out.obj_depth.shape == (4, 3, 64, 64) and out.latents.params.z_sh.shape == (4, 3, 8)
    assert out.latents.params.z_tex.shape == (4, 3, 7) and out.latents.bg_color.shape == (4, 3)
    s = out.latents.params.scale
    assert (s >= 0.25).all() and (s <= 0.9).all()
    five = model(batch.rgb, batch.K, batch.T_world_cam, batch.ground_z, num_slots=5)
    assert five.obj_depth.shape[1] == 5
    with pytest.raises(ValueError, match=r"image: expected shape \(B, 3, 64, 64\)"):
        model(batch.rgb[:, :, :32], batch.K, batch.T_world_cam, batch.ground_z)


@pytest.mark.parametrize("inputs, channels, sees_partials", [("I", 3, False), ("I+dI", 6, True), ("I+M", 4, True), ("I+dI+M", 7, True)])
def test_input_ablation(inputs, channels, sees_partials):
    model = PriSMONet(ModelConfig(inputs=inputs))
    assert model.encoder.trunk[0].in_channels == channels
    img = torch.rand(2, 3, 64, 64)
    a = model.encoder_input(img, torch.zeros(2, 3, 64, 64), torch.zeros(2, 1, 64, 64))
    b = model.encoder_input(img, torch.rand(2, 3, 64, 64), torch.ones(2, 1, 64, 64))
    assert a.shape[1] == channels and torch.equal(a[:, :3], img)
    assert (not torch.equal(a, b)) == sees_partials


@pytest.mark.parametrize("switch, term", [("use_image", "image"), ("use_depth", "depth"), ("use_ground", "ground"), ("use_shape", "shape")])
def test_loss_switches_remove_their_term(batch, switch, term):
    torch.manual_seed(0)
    model = PriSMONet()
    out = run(model, batch)
    on = compute_losses(model, out, batch, LossConfig(), 0)
    off = compute_losses(model, out, batch, LossConfig(**{switch: False}), 0)
    assert float(getattr(off, term).detach()) == 0.0
    others = [k for k in ("image", "depth", "ground", "shape") if k != term]
    assert all(float(getattr(on, k).detach()) == float(getattr(off, k).detach()) for k in others)


def test_without_image_loss_the_texture_field_gets_no_gradient(batch):
    """The image loss is what trains the texture: the paper's finding, as a property of the graph."""
    torch.manual_seed(0)
    model = PriSMONet()
    compute_losses(model, run(model, batch), batch, LossConfig(use_image=False), 0).total.backward()
    assert all(p.grad is None or p.grad.abs().sum() == 0 for p in model.texture.parameters())
    model.zero_grad()
    compute_losses(model, run(model, batch), batch, LossConfig(), 0).total.backward()
    assert sum(p.grad.abs().sum() for p in model.texture.parameters()) > 0


def test_blur_schedule_and_switch():
    cfg = LossConfig(blur_steps=100)
    assert blur_sigma(cfg, 0) == pytest.approx(16 / 3) and blur_sigma(cfg, 100) == 0.5 and blur_sigma(cfg, 500) == 0.5
    assert blur_sigma(cfg, 50) == pytest.approx((16 / 3 + 0.5) / 2)
    x = torch.zeros(1, 1, 32, 32)
    x[..., 16:, :] = 1.0
    assert not torch.allclose(blur(x, cfg, 0), x)
    assert torch.equal(blur(x, LossConfig(blur=False), 0), x)
    assert blur(x, cfg, 0)[0, 0, 15, 5] > blur(x, cfg, 100)[0, 0, 15, 5] > 0  # wide early, narrow late
    assert shape_weight(LossConfig(sh_steps=10), 0) == 0.025 and shape_weight(LossConfig(sh_steps=10), 10) == pytest.approx(0.0025)


def _params(pos, scale=0.5):
    pos = torch.tensor(pos, dtype=torch.float32)[None]
    K = pos.shape[1]
    return SceneParams(torch.zeros(1, K, 8), torch.zeros(1, K, 7), pos, torch.tensor([[1.0, 0.0]] * K)[None], torch.full((1, K), scale))


def test_ground_intersection_outside_and_pose_losses():
    model = PriSMONet()
    z0 = model.prior.latents[0]  # sphere, radius 1 in object units
    above = _params([[0.0, 0.0, 0.6]])
    above.z_sh = z0.expand(1, 1, 8).clone()
    below = _params([[0.0, 0.0, -0.3]])
    below.z_sh = above.z_sh.clone()
    g = torch.zeros(1)
    assert float(ground_loss(model, above, g)) == pytest.approx(0.0, abs=1e-4)
    # centre 0.3 below the ground: height term 0.3, plus the ground point lying inside the shape.
    # It is 0.2 (world) deep; the prior is only trained to be exact within its clamp (0.1 object
    # units = 0.05 world), so the penetration term is positive and at most the true depth.
    loss = float(ground_loss(model, below, g))
    assert 0.3 + 0.05 < loss <= 0.3 + 0.2 + 0.02
    far = _params([[-1.0, 0.0, 0.5], [1.0, 0.0, 0.5]])
    far.z_sh = z0.expand(1, 2, 8).clone()
    near = _params([[-0.2, 0.0, 0.5], [0.2, 0.0, 0.5]])
    near.z_sh = far.z_sh.clone()
    assert float(intersection_loss(model, far, 16)) == 0.0
    assert float(intersection_loss(model, near, 16)) > 0.1
    from prismonet.data.clevr import ClevrConfig, clevr_camera

    cam = clevr_camera(ClevrConfig())
    K, T = cam.K[None], cam.T_world_cam[None]
    assert float(outside_loss(_params([[0.0, 0.0, 0.5]]), K, T, 64, 64)) == 0.0
    assert float(outside_loss(_params([[0.0, 30.0, 0.5]]), K, T, 64, 64)) > 1.0
    p = _params([[1.0, 0.0, 0.5], [-1.0, 0.0, 0.5]])
    gt_pos = torch.tensor([[[-1.0, 0.0, 0.5], [1.0, 0.0, 0.5]]])
    assert float(pose_loss(p, gt_pos, torch.zeros(1, 2), torch.full((1, 2), 0.5), torch.tensor([2]))) == pytest.approx(0.0, abs=1e-6)


def test_noisy_depth_switch(batch):
    from prismonet.model.trainer import TrainConfig, make_inputs

    clean_img, clean = make_inputs(batch, TrainConfig(), torch.Generator().manual_seed(0))
    _, noisy = make_inputs(batch, TrainConfig(depth_noise_eta=1e-3), torch.Generator().manual_seed(0))
    d = clean.double()
    keep = d < 11
    z = (noisy.double() - d)[keep] / (1e-3 * d[keep] ** 2)
    assert abs(z.std().item() - 1.0) < 0.05 and abs(z.mean().item()) < 0.05
    assert not torch.equal(clean_img, batch.rgb)  # input noise is on
    assert torch.equal(make_inputs(batch, TrainConfig(input_noise=0.0), torch.Generator().manual_seed(0))[0], batch.rgb)


def test_mask_loss_has_a_gradient_through_soft_silhouettes(batch):
    """L_mask on binary masks alone would train nothing; with soft silhouettes it moves the pose."""
    torch.manual_seed(0)
    model = PriSMONet(ModelConfig(soft_mask_tau=0.05))
    out = run(model, batch)
    hard = out.obj_mask.float()
    soft = out.obj_soft_mask
    assert torch.equal(soft[hard.bool()], torch.ones_like(soft[hard.bool()]))  # 1 on hits
    missed = (soft > 0) & ~hard.bool()
    assert missed.any() and (soft[missed] < 0.5).all()  # in the box, outside the shape
    terms = compute_losses(model, out, batch, LossConfig(w_mask=1.0, use_image=False, use_depth=False, use_ground=False, use_shape=False), 0)
    assert float(terms.mask.detach()) > 0
    terms.total.backward()
    g = sum(p.grad.abs().sum() for p in model.encoder.parameters() if p.grad is not None)
    assert g > 0
    with pytest.raises(ValueError, match="needs soft silhouettes"):
        compute_losses(PriSMONet(), run(PriSMONet(), batch), batch, LossConfig(w_mask=1.0), 0)


def test_seek_term_pulls_hidden_slots_through_the_encoder(batch):
    """With ``w_seek``: an untrained model hides most slots, so some seek; the term is positive and its
    gradient reaches the encoder; with weight 0 it is exactly 0."""
    torch.manual_seed(0)
    model = PriSMONet(ModelConfig(num_slots=3))
    out = run(model, batch)
    off = compute_losses(model, out, batch, LossConfig(), 0)
    assert float(off.seek) == 0.0
    terms = compute_losses(model, out, batch, LossConfig(w_seek=1.0, use_image=False, use_depth=False, use_ground=False, use_shape=False), 0)
    assert float(terms.seek.detach()) > 0 and "seek" in terms.scalars()
    terms.total.backward()
    assert sum(p.grad.abs().sum() for p in model.encoder.parameters() if p.grad is not None) > 0


def test_mask_from_depth_matches_the_instance_mask(batch):
    """The foreground implied by depth and the known ground plane is the true instance mask, except
    where depth cannot tell: beyond the far clip (12, where the ground is clipped too) and where
    an object meets the ground within the margin."""
    from prismonet.model.losses import LossConfig as LC
    from prismonet.render.background import plane_depth

    bg = plane_depth(batch.K, batch.T_world_cam, 64, 64, batch.ground_z)
    fg = (batch.depth < bg - LC().mask_depth_margin)[:, 0]
    truth = batch.instance > 0
    assert (fg & ~truth).sum() == 0  # never foreground where there is no object
    seen = (bg[:, 0] < 12.0 - 1e-3)  # ground not clipped: depth can show what stands on it
    assert (fg == truth)[seen].float().mean() > 0.99


def test_input_blur_and_noise_ranges(batch):
    """The encoder input's augmentation (sensor blur and noise): defaults keep the old stream exactly; blur
    spreads a point by the drawn sigma; the noise std varies per image within the asked range."""
    from dataclasses import replace

    from prismonet.model.trainer import TrainConfig, make_inputs

    g = lambda: torch.Generator().manual_seed(3)
    img, _ = make_inputs(batch, TrainConfig(), g())
    torch.testing.assert_close(img, batch.rgb + torch.randn(batch.rgb.shape, generator=g()) * 0.02, rtol=0, atol=0)
    point = replace(batch, rgb=torch.zeros_like(batch.rgb))
    point.rgb[:, :, 32, 32] = 1.0
    blurred, _ = make_inputs(point, TrainConfig(input_noise=0.0, input_blur=3.0), g())
    sigma = (torch.rand(len(batch), generator=g()) * 3.0).clamp_min(1e-3).double()  # the draw make_inputs makes
    k = torch.arange(-9, 10, dtype=torch.float64)  # the 19 taps for input_blur = 3
    for b in range(len(batch)):  # a separable, normalised Gaussian's peak: (1 / sum_k exp(-k^2 / 2 sigma^2))^2
        expect = (1.0 / torch.exp(-(k**2) / (2 * sigma[b] ** 2)).sum()) ** 2
        assert blurred[b, 0, 32, 32].item() == pytest.approx(expect.item(), rel=1e-4)
        assert blurred[b, 0].sum().item() == pytest.approx(1.0, rel=1e-4)
    assert (sigma > 0.6).any() and (blurred[:, 0, 32, 32] < 0.5).any()  # some image is blurred for real
    noisy, _ = make_inputs(replace(batch, rgb=torch.zeros(8, 3, 64, 64)), TrainConfig(input_noise=0.01, input_noise_max=0.05), g())
    stds = noisy.flatten(1).std(1)
    assert stds.min() >= 0.009 and stds.max() <= 0.051 and stds.max() - stds.min() > 0.01


def test_gray_share_makes_chosen_images_grey_input_and_target(batch):
    """``gray_share``: the drawn images carry their Rec. 601 luma in all three channels (hand-computed on pure
    red, green and blue), the others are untouched, the background targets of the grey scenes turn grey too,
    and 0 draws nothing, so older runs keep their random stream."""
    from dataclasses import replace

    from prismonet.model.losses import LossConfig
    from prismonet.data.gray import LUMA, to_gray
    from prismonet.model.trainer import TrainConfig, gray_batch

    rgb = torch.zeros(3, 3, 2, 2)
    for c in range(3):
        rgb[c, c] = 1.0  # image c is pure red, green or blue
    out = to_gray(rgb, torch.tensor([True, True, False]))
    for c in range(2):
        torch.testing.assert_close(out[c], torch.full((3, 2, 2), LUMA[c]), rtol=0, atol=1e-7)
    torch.testing.assert_close(out[2], rgb[2], rtol=0, atol=0)
    assert LUMA == (0.299, 0.587, 0.114)

    g = torch.Generator().manual_seed(5)
    same, none, which = gray_batch(batch, None, TrainConfig(), g)
    assert same is batch and none is None and which is None and torch.equal(g.get_state(), torch.Generator().manual_seed(5).get_state())
    colourful = replace(batch, rgb=torch.rand(8, 3, 16, 16, generator=torch.Generator().manual_seed(0)))
    bg = torch.tensor([[1.0, 0.0, 0.0]]).expand(8, 3)
    got, (t, mask), drawn = gray_batch(colourful, ({"bg_color": bg}, torch.ones(8)), TrainConfig(gray_share=0.5), torch.Generator().manual_seed(1))
    which = torch.rand(8, generator=torch.Generator().manual_seed(1)) < 0.5  # the draw gray_batch makes
    assert 0 < int(which.sum()) < 8 and torch.equal(drawn, which)
    for b in range(8):
        grey = bool((got.rgb[b] == got.rgb[b, :1]).all())
        assert grey == bool(which[b])
        torch.testing.assert_close(t["bg_color"][b], torch.full((3,), LUMA[0]) if which[b] else bg[b], rtol=0, atol=1e-7)
        if not which[b]:
            assert torch.equal(got.rgb[b], colourful.rgb[b])
    with pytest.raises(ValueError, match="gray_share"):
        TrainConfig(gray_share=1.5)
    with pytest.raises(ValueError, match="distill_texture"):
        TrainConfig(gray_share=0.5, loss=LossConfig(w_distill=0.5))


def test_mask_loss_leaves_out_the_far_clip_when_asked():
    """With ``far_clip``, pixels whose depth reads the far clip add nothing to L_mask (there depth cannot
    tell an object from the ground); the other pixels' BCE is unchanged. By hand, blur off."""
    from types import SimpleNamespace

    soft = torch.full((1, 1, 1, 4, 4), 0.25)[:, :, 0]  # (B, N=1, H, W)
    depth = torch.full((1, 1, 4, 4), 5.0)
    depth[..., 0, :2] = 3.0  # an object in front of the ground (at 5)
    depth[..., 3, :] = 12.0  # the far clip
    out = SimpleNamespace(obj_soft_mask=soft, bg_depth=torch.full((1, 1, 4, 4), 5.0))
    batch = SimpleNamespace(depth=depth)
    bce_fg, bce_bg = -math.log(0.25), -math.log(0.75)
    cfg = LossConfig(w_mask=1.0, mask_from_depth=True, blur=False)
    every = float(mask_loss(out, batch, cfg, 0, far_depth=12.0))
    assert every == pytest.approx((2 * bce_fg + 14 * bce_bg) / 16, rel=1e-6)
    skip = float(mask_loss(out, batch, LossConfig(w_mask=1.0, mask_from_depth=True, blur=False, far_clip=True), 0, far_depth=12.0))
    assert skip == pytest.approx((2 * bce_fg + 10 * bce_bg) / 16, rel=1e-6)


def test_depth_loss_sees_the_render_through_the_far_clip_when_asked():
    """With ``far_clip``, an object rendered beyond the clip (13 against the input's clipped 12) costs
    nothing in L_D; without it, it costs its excess. By hand, blur off."""
    from types import SimpleNamespace

    rendered = torch.full((1, 1, 4, 4), 5.0)
    rendered[..., 0, :2] = 13.0  # a far object, correctly placed
    target = rendered.clamp(max=12.0)
    out = SimpleNamespace(composite=SimpleNamespace(image=torch.zeros(1, 3, 4, 4), depth=rendered), presence=None,
                          latents=SimpleNamespace(params=None, bg_color=torch.zeros(1, 3)))
    batch = SimpleNamespace(rgb=torch.zeros(1, 3, 4, 4), depth=target)
    model = SimpleNamespace(cfg=SimpleNamespace(far_depth=12.0))
    only_depth = dict(use_image=False, use_ground=False, use_shape=False, blur=False)
    assert float(compute_losses(model, out, batch, LossConfig(**only_depth), 0).depth) == pytest.approx(2 / 16)
    assert float(compute_losses(model, out, batch, LossConfig(far_clip=True, **only_depth), 0).depth) == 0.0


@pytest.mark.parametrize("override, message", [("loss.w_seek=-1", "w_seek must be non-negative"),
                                               ("loss.w_distill=-0.5", "w_distill must be non-negative"),
                                               ("loss.far_clip=maybe", "loss.far_clip: expected bool")])
def test_bad_seek_and_clip_settings_are_one_clear_error(override, message):
    from prismonet.config import load_config
    from prismonet.model.trainer import TrainConfig

    with pytest.raises(ValueError, match=message):
        load_config(TrainConfig, overrides=[override])


def test_pose_loss_yaw_up_to_symmetry():
    """Slot yaws 0 against true yaws 90 and 180 degrees, hand-computed: the paper's term 1 - cos(delta) gives 1 + 2;
    with periods (0: round, pi: a box) 0 + (1 - cos(2 pi / pi * pi)) = 0; with 2 pi (none) the paper's again."""
    p = _params([[1.0, 0.0, 0.5], [-1.0, 0.0, 0.5]])
    gt_pos = torch.tensor([[[1.0, 0.0, 0.5], [-1.0, 0.0, 0.5]]])
    gt_yaw = torch.tensor([[math.pi / 2, math.pi]])
    args = (p, gt_pos, gt_yaw, torch.full((1, 2), 0.5), torch.tensor([2]))
    assert float(pose_loss(*args)) == pytest.approx(3.0, abs=1e-5)
    assert float(pose_loss(*args, torch.tensor([[0.0, math.pi]]))) == pytest.approx(0.0, abs=1e-5)
    assert float(pose_loss(*args, torch.tensor([[2 * math.pi, 2 * math.pi]]))) == pytest.approx(3.0, abs=1e-5)
    # a square box (pi / 2) turned by 90 degrees costs nothing, by 45 the most
    assert float(pose_loss(*args, torch.tensor([[math.pi / 2, 2 * math.pi]]))) == pytest.approx(2.0, abs=1e-5)
    gt45 = torch.tensor([[math.pi / 4, 0.0]])
    assert float(pose_loss(p, gt_pos, gt45, torch.full((1, 2), 0.5), torch.tensor([2]), torch.tensor([[math.pi / 2, 0.0]]))) \
        == pytest.approx(2.0, abs=1e-5)


def test_pose_yaw_periods_are_checked():
    with pytest.raises(ValueError, match="pose_yaw_periods: expected periods in"):
        LossConfig(pose_yaw_periods=(0.0, 7.0))


def test_pose_yaw_periods_must_cover_the_data():
    from types import SimpleNamespace

    from prismonet.model.losses import _yaw_periods

    batch = SimpleNamespace(obj_shape=torch.tensor([[0, 2, -1]]), obj_yaw=torch.zeros(1, 3))
    assert _yaw_periods(LossConfig(), batch) is None
    assert _yaw_periods(LossConfig(pose_yaw_periods=(0.0, 1.0, math.pi)), batch)[0].tolist() == pytest.approx([0.0, math.pi, 0.0])
    with pytest.raises(ValueError, match="pose_yaw_periods: 2 periods, but the data has shape id 2"):
        _yaw_periods(LossConfig(pose_yaw_periods=(0.0, 1.0)), batch)
