"""Anchored slots (``ModelConfig.anchor``, ``prismonet.model.unexplained``): the deepest pixel of hand-made
regions, anchors found on a hand-made image, the decoded centre seen exactly at its anchor pixel, a scene
with nothing left to explain stopping before its first step, and the start from an unanchored model."""

from dataclasses import replace

import numpy as np
import pytest
import torch

from prismonet.geometry.camera import intrinsics_matrix, look_at, project
from prismonet.model.config import ModelConfig
from prismonet.model.io import anchor_start, load_model, widen_weights
from prismonet.model.losses import ground_loss
from prismonet.model.prismonet import PriSMONet
from prismonet.model.unexplained import AnchorRule, deepest_pixel, find_anchors
from prismonet.render import SceneParams

GROUND = (0.6, 0.6, 0.6)


def _camera(B=1):
    K = intrinsics_matrix(80.0, 80.0, 31.5, 31.5)[None].expand(B, 3, 3)
    T = look_at(torch.tensor([7.0, -6.0, 5.0]), torch.zeros(3))[None].expand(B, 4, 4)
    return K, T


def test_deepest_pixel_of_a_square_and_of_two_touching_blobs():
    r = np.zeros((20, 20), bool)
    r[4:9, 10:15] = True  # 5 x 5: centre (12, 6)
    assert deepest_pixel(r) == (12.0, 6.0)
    r[6, 4:10] = True  # a one-pixel bar joins a smaller blob on the left
    r[5:9, 1:4] = True
    assert deepest_pixel(r) == (12.0, 6.0)  # still inside the larger square, not the joint centroid
    r = np.zeros((20, 20), bool)
    r[4:8, 4:8] = True  # 4 x 4: the four middle pixels tie, their mean is the square's centre
    assert deepest_pixel(r) == (5.5, 5.5)


def test_find_anchors_on_a_hand_made_image():
    image = torch.tensor(GROUND).view(1, 3, 1, 1).repeat(3, 1, 32, 32)
    image[0, :, 10:17, 20:27] = torch.tensor([0.9, 0.1, 0.1]).view(3, 1, 1)  # a 7 x 7 red square
    image[0, :, 2:4, 2:4] = torch.tensor([0.1, 0.1, 0.9]).view(3, 1, 1)  # 4 px: removed by the opening
    image[1, :, 0:3, 0:30] = torch.tensor([0.1, 0.9, 0.1]).view(3, 1, 1)  # 90 px
    image[1, :, 20:24, 20:24] = torch.tensor([0.9, 0.9, 0.1]).view(3, 1, 1)  # 16 px: smaller
    comp = torch.tensor(GROUND).view(1, 3, 1, 1).expand(3, 3, 32, 32)
    a = find_anchors(image, comp, AnchorRule(min_area=20))
    assert a.found.tolist() == [True, True, False]
    assert a.uv[0].tolist() == [23.0, 13.0] and int(a.region[0].sum()) == 49 and a.region[0, 10:17, 20:27].all()
    assert int(a.region[1].sum()) == 90 and a.region[1, 0:3, 0:30].all()
    assert a.uv[2].tolist() == [15.5, 15.5] and not a.region[2].any()  # nothing left: the image centre
    # the composition explains the square: nothing left in scene 0 either
    explained = comp.clone()
    explained[0] = image[0]
    assert find_anchors(image, explained).found.tolist() == [False, True, False]
    # colour within the tolerance counts as explained
    assert not find_anchors(image, image + 0.2, AnchorRule(color_tol=0.25)).found.any()


def test_a_shadow_counts_as_explained_with_shade_min():
    """``AnchorRule.shade_min``: ground darkened evenly (a shadow, k = 0.55) is explained; a red object, a grey patch
    darker than the least factor (k = 0.3) and a patch darkened unevenly are not. Off (the default): all four are
    unexplained."""
    ground = torch.tensor([0.6, 0.55, 0.5])
    comp = ground.view(1, 3, 1, 1).repeat(1, 1, 8, 8)
    image = comp.clone()
    image[0, :, 0:2, :] = (0.55 * ground).view(3, 1, 1)  # shadow
    image[0, :, 2:4, :] = torch.tensor([0.9, 0.1, 0.1]).view(3, 1, 1)  # red object
    image[0, :, 4:6, :] = (0.3 * ground).view(3, 1, 1)  # darker than any shadow allowed
    image[0, :, 6:8, :] = (ground * torch.tensor([0.6, 0.3, 0.3])).view(3, 1, 1)  # uneven: a reddish object
    rows = lambda m: [bool(m[0, 2 * i:2 * i + 2].all()) for i in range(4)]  # noqa: E731
    assert rows(AnchorRule().unexplained(image, comp)) == [True, True, True, True]
    assert rows(AnchorRule(shade_min=0.5, shade_tol=0.03).unexplained(image, comp)) == [False, True, True, True]
    assert rows(AnchorRule(shade_min=0.25).unexplained(image, comp)) == [False, True, False, True]
    with pytest.raises(ValueError, match="shade_min"):
        AnchorRule(shade_min=1.0)
    with pytest.raises(ValueError, match="anchor_shade_min"):
        ModelConfig(anchor=True, anchor_shade_min=0.0)
    model = PriSMONet(ModelConfig(anchor=True, anchor_shade_min=0.5))
    assert model.anchor_rule().shade_min == 0.5 and model.anchor_rule().shade_tol == 0.03


def test_shadows_are_none_in_a_grey_image_with_gray_tol():
    """``AnchorRule.shadows``, which re-seeding also reads: an even darkening to 0.6 of the ground is a shadow in a
    colour image; in a grey image it is one only without ``gray_tol`` (with it, every change there is an object)."""
    ground = torch.tensor([0.6, 0.55, 0.5])
    comp = ground.view(1, 3, 1, 1).repeat(2, 1, 4, 4)
    comp[1] = 0.55  # image 1: grey
    image = comp.clone()
    image[:, :, :2] *= 0.6
    colour_only = AnchorRule(shade_min=0.5)
    both = AnchorRule(shade_min=0.5, gray_tol=0.1)
    for rule, want in ((colour_only, [True, True]), (both, [True, False])):
        s = rule.shadows(image, comp)
        assert [bool(s[b, :2].all()) for b in range(2)] == want and not s[:, 2:].any()
    assert not AnchorRule().shadows(image, comp).any()


def test_grey_images_are_read_by_luminance_with_gray_tol():
    """``AnchorRule.gray_tol``: in a grey image, a patch 0.08 brighter than the grey ground is unexplained at 0.06 and
    at 0.15 would not be; a grey patch darkened to 0.7 of the ground is an object, not a shadow; a composition of another
    hue but the input's luminance explains it. A colour image in the same batch is read as without the setting."""
    from prismonet.data.gray import LUMA
    from prismonet.model.unexplained import is_gray, luma

    g = 0.5
    comp = torch.full((2, 3, 8, 8), g)
    image = comp.clone()
    image[:, :, 0:2, :] = g + 0.08  # a slightly brighter grey object
    image[:, :, 2:4, :] = 0.7 * g  # an even darkening: an object in a grey photo, a shadow in a colour one
    image[:, :, 4:6, :] = g + 0.03  # within any tolerance
    teal = torch.tensor([0.3, 0.6, 0.5])
    comp[:, :, 6:8, :] = teal.view(3, 1, 1)  # a render of another hue...
    image[:, :, 6:8, :] = float((teal * torch.tensor(LUMA)).sum())  # ...whose luminance the grey input records
    image[1, :, 0, 0] = torch.tensor([0.6, 0.5, 0.5])  # one coloured pixel: image 1 is a colour image
    assert is_gray(image).tolist() == [True, False]
    torch.testing.assert_close(luma(image[:1, :, 6:8]), torch.full((1, 2, 8), float((teal * torch.tensor(LUMA)).sum())))
    rows = lambda m, b: [bool(m[b, 2 * i + 1].all()) for i in range(4)]  # noqa: E731 (row 1 of each pair: no odd pixel)
    colour = AnchorRule(color_tol=0.15, shade_min=0.5)
    grey = AnchorRule(color_tol=0.15, shade_min=0.5, gray_tol=0.06)
    assert rows(colour.unexplained(image, comp), 0) == [False, False, False, True]
    assert rows(grey.unexplained(image, comp), 0) == [True, True, False, False]
    torch.testing.assert_close(grey.unexplained(image, comp)[1], colour.unexplained(image, comp)[1], rtol=0, atol=0)
    assert not AnchorRule(color_tol=0.15, gray_tol=0.1).unexplained(image, comp)[0, 0:2].any()
    with pytest.raises(ValueError, match="gray_tol"):
        AnchorRule(gray_tol=0.0)
    with pytest.raises(ValueError, match="anchor_gray_tol"):
        ModelConfig(anchor=True, anchor_gray_tol=-1.0)
    assert PriSMONet(ModelConfig(anchor=True, anchor_gray_tol=0.06)).anchor_rule().gray_tol == 0.06


def test_a_component_explained_in_vain_is_not_proposed_again():
    image = torch.tensor(GROUND).view(1, 3, 1, 1).repeat(2, 1, 32, 32)
    image[:, :, 4:12, 4:12] = torch.tensor([0.9, 0.1, 0.1]).view(3, 1, 1)  # 64 px, the largest
    image[:, :, 20:25, 20:25] = torch.tensor([0.1, 0.9, 0.1]).view(3, 1, 1)  # 25 px
    comp = torch.tensor(GROUND).view(1, 3, 1, 1).repeat(2, 1, 32, 32)
    rule = AnchorRule(min_gain=10)
    a = find_anchors(image, comp, rule)
    assert a.uv.tolist() == [[7.5, 7.5], [7.5, 7.5]]
    after = comp.clone()
    after[0, :, 4:7, 4:7] = image[0, :, 4:7, 4:7]  # scene 0: the new slot explains 9 px of 64 (fails)
    after[1, :, 4:8, 4:7] = image[1, :, 4:8, 4:7]  # scene 1: 12 px (does not)
    failed = rule.failed(a, image, after)
    assert int(failed[0].sum()) == 64 and not failed[1].any()
    b = find_anchors(image, after, rule, exclude=failed)
    assert b.uv[0].tolist() == [22.0, 22.0]  # scene 0 looks at the other part
    assert b.found.tolist() == [True, True] and b.region[1, 8:12, 4:12].all()


@pytest.fixture(scope="module")
def anchored():
    torch.manual_seed(0)
    return PriSMONet(ModelConfig(num_slots=3, anchor=True)).eval()


def test_zero_outputs_put_the_centre_on_the_anchor_ray(anchored):
    """With the position outputs at 0 the centre is seen exactly at the anchor pixel, at the height offset
    above the ground (a raised ground lifts it)."""
    K, T = _camera(2)
    raw = torch.zeros(2, anchored.out_dim)
    uv = torch.tensor([[12.0, 40.0], [50.5, 27.25]])
    ground = torch.tensor([0.0, -1.0])
    p = anchored.decode_latent(raw, K, T, ground, anchor_uv=uv)
    x = p.position[:, 0]
    torch.testing.assert_close(x[:, 2], ground + anchored.cfg.position_offset[2])
    x_cam = torch.einsum("bji,bj->bi", T[:, :3, :3], x - T[:, :3, 3])
    torch.testing.assert_close(torch.stack([project(x_cam[i:i + 1], K[i])[0] for i in range(2)]), uv, atol=1e-3, rtol=0)
    with pytest.raises(ValueError, match="anchored"):
        anchored.decode_latent(raw, anchor_uv=uv)


def test_the_encoder_sees_the_region_as_one_more_channel(anchored):
    assert anchored.cfg.in_channels == 8 and anchored.encoder.trunk[0].in_channels == 8
    x = anchored.encoder_input(torch.zeros(2, 3, 64, 64), torch.zeros(2, 3, 64, 64), torch.zeros(2, 1, 64, 64),
                               torch.ones(2, 64, 64, dtype=torch.bool))
    assert x.shape == (2, 8, 64, 64) and bool((x[:, 7] == 1).all())


def _fixed_background(model, color):
    head = model.bg_encoder.head[-1]
    with torch.no_grad():
        head.weight.zero_()
        head.bias.copy_(torch.logit(torch.tensor(color)))


def test_a_scene_with_nothing_unexplained_takes_no_step_and_another_is_anchored(anchored, monkeypatch):
    model = PriSMONet(ModelConfig(num_slots=3, anchor=True)).eval()
    model.load_state_dict(anchored.state_dict())
    _fixed_background(model, GROUND)
    calls = []
    real = model.encoder.forward
    monkeypatch.setattr(model.encoder, "forward", lambda x: (calls.append(x.shape[0]), real(x))[1])
    K, T = _camera(2)
    image = torch.tensor(GROUND).view(1, 3, 1, 1).repeat(2, 1, 64, 64)
    with torch.no_grad():
        out = model(image[:1], K[:1], T[:1], torch.zeros(1))
    assert calls == [] and not out.latents.params.active.any() and not out.obj_mask.any()
    image[1, :, 30:40, 20:30] = torch.tensor([0.1, 0.1, 0.9]).view(3, 1, 1)
    with torch.no_grad():
        out = model(image, K, T, torch.zeros(2))
    assert not out.latents.params.active[0].any()
    assert bool(out.latents.params.active[1, 0])


def test_the_start_from_an_unanchored_model_is_the_same_function_but_positions():
    torch.manual_seed(1)
    src = PriSMONet(ModelConfig(num_slots=3)).eval()
    dst = PriSMONet(replace(src.cfg, anchor=True)).eval()
    assert widen_weights(dst, src) == ["encoder.trunk.0.weight"]
    anchor_start(dst)
    x = torch.rand(2, 7, 64, 64)
    region = (torch.rand(2, 1, 64, 64) > 0.5).float()
    with torch.no_grad():
        a, b = src.encoder(x), dst.encoder(torch.cat([x, region], 1))
    pos = list(range(src.sh_dim + src.cfg.tex_dim, src.sh_dim + src.cfg.tex_dim + 3))
    rest = [i for i in range(src.out_dim) if i not in pos]
    torch.testing.assert_close(b[:, rest], a[:, rest])
    assert bool((b[:, pos] == 0).all())


def test_ground_loss_does_not_charge_inactive_slots(anchored):
    B, N = 1, 2
    params = SceneParams(torch.zeros(B, N, anchored.sh_dim), torch.zeros(B, N, 7), torch.tensor([[[0.0, 0.0, -1.0], [0.0, 0.0, -1.0]]]),
                         torch.tensor([[[1.0, 0.0], [1.0, 0.0]]]), torch.full((B, N), 0.5))
    both = ground_loss(anchored, params, torch.zeros(B))
    params.active = torch.tensor([[True, False]])
    one = ground_loss(anchored, params, torch.zeros(B))
    torch.testing.assert_close(one, both / 2)  # two identical slots below the ground: one is charged
    assert float(one) == pytest.approx(1.0)  # 1 unit below the ground; the ground point above it is outside the shape


def test_bad_anchor_settings_are_one_line():
    with pytest.raises(ValueError, match="choose one"):
        ModelConfig(anchor=True, presence=True)
    with pytest.raises(ValueError, match="anchor_min_area"):
        ModelConfig(anchor=True, anchor_min_area=0)
    with pytest.raises(ValueError, match="anchor rule"):
        AnchorRule(color_tol=0.0)
