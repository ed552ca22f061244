"""Re-seeding idle slots: the placement on the ground (exact for a ball seen by a known camera), the
opening and the component choice, and on a shipped model: an emptied slot is put back on its object,
and no scene ever fits worse."""

import math
from dataclasses import replace

import pytest
import torch

from prismonet.assets import samples_for
from prismonet.data.dataset import SceneDataset
from prismonet.geometry.camera import intrinsics_matrix, look_at, project
from prismonet.model.fit_score import fit_score
from prismonet.model.inference import InferenceConfig, infer
from prismonet.model.io import load_model
from prismonet.model.reseed import (ReseedConfig, _fit_textures, least_useful, place_on_ground, ray_at_height, reseed,
                                    support_height)
from prismonet.model.unexplained import largest_components, opening
from prismonet.model.prune import prune_keep
from prismonet.model.stopping import StopRule, keep_slots


def camera(dtype=torch.float64):
    T = look_at(torch.tensor([7.0, -6.0, 5.0], dtype=dtype), torch.zeros(3, dtype=dtype))[None]
    return intrinsics_matrix(100.0, 100.0, 32.0, 32.0, dtype=dtype)[None], T


@pytest.mark.parametrize("centre,s", [((0.3, -0.2), 0.5), ((-1.0, 1.2), 0.3), ((1.5, 0.4), 0.8)])
def test_place_on_ground_recovers_a_ball(centre, s):
    """A ball of radius ``s`` resting on ``z = 0`` covers ``pi (f s / d)^2`` pixels around its centre's
    projection; from those two numbers the placement gives back its centre and radius."""
    K, T = camera()
    P = torch.tensor([[centre[0], centre[1], s]], dtype=torch.float64)
    x_cam = (P - T[0, :3, 3]) @ T[0, :3, :3]
    d = float(x_cam[0, 2])
    uv = project(x_cam, K[0])
    area = torch.tensor([math.pi * (100.0 * s / d) ** 2], dtype=torch.float64)
    pos, scale = place_on_ground(uv, area, K, T, torch.zeros(1, dtype=torch.float64), (0.25, 0.9))
    assert float(scale[0]) == pytest.approx(s, abs=1e-5)  # a fixed point after PLACE_ITERATIONS steps
    assert pos[0].tolist() == pytest.approx(P[0].tolist(), abs=1e-4)


def test_ray_at_height_lies_on_the_ray_and_the_plane():
    K, T = camera()
    uv = torch.tensor([[10.0, 50.0], [40.0, 20.0]], dtype=torch.float64)
    h = torch.tensor([0.25, -0.5], dtype=torch.float64)
    pts = ray_at_height(uv, K.expand(2, 3, 3), T.expand(2, 4, 4), h)
    assert pts[:, 2].tolist() == pytest.approx(h.tolist(), abs=1e-9)
    back = project((pts - T[0, :3, 3]) @ T[0, :3, :3], K[0])
    assert back.flatten().tolist() == pytest.approx(uv.flatten().tolist(), abs=1e-6)


def test_scale_stays_in_range():
    K, T = camera()
    uv = torch.tensor([[32.0, 32.0], [32.0, 32.0]], dtype=torch.float64)
    _, s = place_on_ground(uv, torch.tensor([1.0, 4000.0], dtype=torch.float64), K.expand(2, 3, 3), T.expand(2, 4, 4),
                           torch.zeros(2, dtype=torch.float64), (0.25, 0.9))
    assert s.tolist() == [0.25, 0.9]


def test_support_height_reads_the_surface_under_a_region():
    """A horizontal surface at world height 0.7 seen through the test camera: every pixel's camera depth is where
    its ray meets z = 0.7, so the median world height of the covered region's pixels is 0.7; a region covered
    less than ``min_share`` gives NaN."""
    K, T = camera()
    H = W = 64
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij")
    uv = torch.stack([u.flatten(), v.flatten()], -1)
    pts = ray_at_height(uv, K.expand(H * W, 3, 3), T.expand(H * W, 4, 4), torch.full((H * W,), 0.7, dtype=torch.float64))
    depth = ((pts - T[0, :3, 3]) @ T[0, :3, 2]).reshape(1, H, W)  # camera z
    region = torch.zeros(2, H, W, dtype=torch.bool)
    region[:, 20:40, 10:30] = True
    covered = torch.zeros(2, H, W, dtype=torch.bool)
    covered[0] = True
    covered[1, 20:24, 10:30] = True  # a fifth of the region
    h = support_height(depth.expand(2, H, W), covered, region, K.expand(2, 3, 3), T.expand(2, 4, 4))
    assert float(h[0]) == pytest.approx(0.7, abs=1e-9)
    assert math.isnan(float(h[1]))
    assert float(support_height(depth.expand(2, H, W), covered, region, K.expand(2, 3, 3), T.expand(2, 4, 4),
                                min_share=0.2)[1]) == pytest.approx(0.7, abs=1e-9)


def test_opening_drops_seams_and_keeps_blobs():
    m = torch.zeros(1, 16, 16, dtype=torch.bool)
    m[0, 2, :] = True  # a one-pixel seam
    m[0, 8:13, 4:9] = True  # a 5 x 5 blob
    o = opening(m, 1)
    assert not o[0, 2].any()
    assert torch.equal(o[0, 8:13, 4:9], torch.ones(5, 5, dtype=torch.bool)) and int(o.sum()) == 25
    assert torch.equal(opening(m, 0), m)


def test_largest_component():
    m = torch.zeros(2, 10, 10, dtype=torch.bool)
    m[0, 0:2, 0:2] = True  # 4 px
    m[0, 5:9, 5:9] = True  # 16 px
    m[1, 0:3, 0:3] = True  # 9 px, under the threshold
    a, b = largest_components(m, min_area=10)
    assert a is not None and int(a.sum()) == 16 and a[5:9, 5:9].all()
    assert b is None


def test_config_rejects_bad_values():
    with pytest.raises(ValueError, match="--reseed"):
        ReseedConfig(rounds=-1)
    with pytest.raises(ValueError, match="min_area"):
        ReseedConfig(min_area=0)
    with pytest.raises(ValueError, match="--reseed-cycles"):
        ReseedConfig(rounds=1, cycles=0)
    with pytest.raises(ValueError, match="--reseed-grow"):
        ReseedConfig(rounds=1, grow=-1)


@pytest.fixture(scope="module")
def decoded():
    model, _ = load_model("clevr3_fc")
    ds = SceneDataset(samples_for("clevr3"), split="test")
    batch = ds.batch(list(range(6)))
    return model, batch, infer(model, batch, InferenceConfig())


def test_emptied_slot_is_put_back_on_its_object(decoded):
    """Empty each scene's first slot: its object is then unexplained, and re-seeding puts the (only
    idle) slot back over it and lowers every such scene's fit score."""
    model, batch, out = decoded
    keep = torch.ones_like(out.obj_mask.flatten(2).any(2))
    keep[:, 0] = False
    emptied = keep_slots(out, keep)
    was = out.composite.instance == 1  # the pixels slot 0 drew
    moved = reseed(model, emptied, batch, ReseedConfig(rounds=1))
    before = fit_score(emptied.composite.image, emptied.composite.depth, batch.rgb, batch.depth)
    after = fit_score(moved.composite.image, moved.composite.depth, batch.rgb, batch.depth)
    big = was.flatten(1).sum(1) >= 60  # objects large enough to leave a component after the opening
    assert big.sum() >= 3
    assert bool((after[big] < before[big]).all())
    covered = ((moved.composite.instance == 1) & was).flatten(1).sum(1).float() / was.flatten(1).sum(1).clamp_min(1)
    assert bool((covered[big] > 0.5).all()), covered.tolist()
    assert bool(moved.latents.params.active[big, 0].all())


def test_reseed_never_fits_worse_and_zero_rounds_is_identity(decoded):
    model, batch, out = decoded
    assert reseed(model, out, batch, ReseedConfig(rounds=0)) is out
    more = reseed(model, out, batch, ReseedConfig(rounds=3))
    for depth in (batch.depth, None):  # colour alone scores by colour alone
        start = fit_score(out.composite.image, out.composite.depth, batch.rgb, depth)
        moved = more if depth is not None else reseed(model, out, batch, ReseedConfig(rounds=3), use_depth=False)
        end = fit_score(moved.composite.image, moved.composite.depth, batch.rgb, depth)
        assert bool((end <= start + 1e-7).all())


def test_on_objects_adds_trials_and_never_fits_worse(decoded):
    """With ``on_objects`` a round tries the ground placements and more, so after one round every scene fits at
    least as well as with the ground alone, and no worse than at the start."""
    model, batch, out = decoded
    keep = torch.ones_like(out.obj_mask.flatten(2).any(2))
    keep[:, 0] = False
    emptied = keep_slots(out, keep)
    start = fit_score(emptied.composite.image, emptied.composite.depth, batch.rgb, batch.depth)
    ground = reseed(model, emptied, batch, ReseedConfig(rounds=1))
    both = reseed(model, emptied, batch, ReseedConfig(rounds=1, on_objects=True))
    g = fit_score(ground.composite.image, ground.composite.depth, batch.rgb, batch.depth)
    b = fit_score(both.composite.image, both.composite.depth, batch.rgb, batch.depth)
    assert bool((b <= g + 1e-7).all()) and bool((b <= start + 1e-7).all())


def test_inference_config_runs_it():
    cfg = InferenceConfig.of(reseed=2)
    assert cfg.reseed.rounds == 2 and not cfg.feed_forward
    assert "2 re-seeding rounds" in cfg.describe()
    assert not cfg.reseed.on_objects
    assert "also on other objects" in InferenceConfig.of(reseed=2, reseed_on_objects=True).describe()
    with pytest.raises(ValueError, match="--reseed-on-objects needs"):
        InferenceConfig.of(reseed_on_objects=True)
    cycled = InferenceConfig.of(reseed=2, reseed_cycles=3, search=1)
    assert "then the search, 3 times" in cycled.describe()
    with pytest.raises(ValueError, match="--reseed-cycles"):
        InferenceConfig.of(reseed=2, reseed_cycles=0)


def test_cycles_alternate_with_the_search(decoded):
    """``cycles`` C with the search: re-seed, search, C times, reported in that order."""
    model, batch, _ = decoded
    steps = []
    infer(model, batch, InferenceConfig.of(reseed=1, reseed_cycles=2, search=1, search_scales=(1.1,)),
          on_step=lambda name, out: steps.append(name))
    assert steps == ["encoder", "reseeded", "searched", "reseeded", "searched"]


def _without_slot0(out):
    """``out`` as if the model had only its slots 1..N-1 (slot 0 and its pixels gone)."""
    from dataclasses import replace as dc_replace

    from prismonet.model.prismonet import ModelOutput, SceneLatents
    from prismonet.render import composite

    p = out.latents.params
    keep = lambda t: None if t is None else t[:, 1:]
    params = dc_replace(p, z_sh=keep(p.z_sh), z_tex=keep(p.z_tex), position=keep(p.position), cos_sin=keep(p.cos_sin),
                        scale=keep(p.scale), axis=keep(p.axis), active=keep(p.active))
    comp = composite(out.obj_depth[:, 1:], out.obj_mask[:, 1:], out.obj_color[:, 1:], out.latents.bg_color, out.bg_depth)
    return ModelOutput(SceneLatents(params, out.latents.bg_color), comp, out.obj_depth[:, 1:], out.obj_mask[:, 1:],
                       out.obj_color[:, 1:], out.bg_depth)


def test_grow_adds_empty_slots_and_leaves_the_composition():
    from prismonet.model.reseed import grow_slots

    model, _ = load_model("clevr3_fc")
    ds = SceneDataset(samples_for("clevr3"), split="test")
    out = infer(model, ds.batch([0, 1]), InferenceConfig())
    grown = grow_slots(out, 2, model.cfg.far_depth)
    assert grown.obj_depth.shape[1] == 5 and grown.latents.params.scale.shape == (2, 5)
    assert not grown.obj_mask[:, 3:].any() and not grown.latents.params.active[:, 3:].any()
    assert grown.latents.params.active[:, :3].all()
    assert grown.encoder_steps()[0].tolist() == [0, 1, 2, 3, 4]
    assert torch.equal(grown.composite.image, out.composite.image)
    assert grow_slots(out, 0, model.cfg.far_depth) is out


def test_grow_finds_an_object_the_model_has_no_slot_for(decoded):
    """With slot 0 cut from the model's output, both slots left are in use: nothing is idle, so
    re-seeding alone cannot help; with one slot added it covers slot 0's object again."""
    model, batch, out = decoded
    was = out.composite.instance == 1
    two = _without_slot0(out)
    same = reseed(model, two, batch, ReseedConfig(rounds=1))
    big = was.flatten(1).sum(1) >= 60
    assert same.obj_depth.shape[1] == 2
    grown = reseed(model, two, batch, ReseedConfig(rounds=1, grow=1))
    assert grown.obj_depth.shape[1] == 3
    share = lambda o: ((o.composite.instance > 0) & was).flatten(1).sum(1).float() / was.flatten(1).sum(1).clamp_min(1)
    assert bool((share(two)[big] < 0.5).all())  # slot 0's object is mostly uncovered without it
    assert bool((share(grown)[big] > 0.5).all()), share(grown).tolist()  # by the added slot, or an idle one moved
    assert bool(grown.latents.params.active[:, 2].any())
    start = fit_score(two.composite.image, two.composite.depth, batch.rgb, batch.depth)
    assert bool((fit_score(grown.composite.image, grown.composite.depth, batch.rgb, batch.depth)[big] < start[big]).all())


def test_least_useful_is_the_slot_that_explains_fewest_pixels(decoded):
    """Slots painted pure red, green and blue over an input that is exactly their composition: each explains
    its own visible pixels and nothing else, so the least useful slot is the one with the fewest visible pixels."""
    _, batch, out = decoded
    c = out.obj_color.clone()
    for k in range(3):
        c[:, k] = 0.0
        c[:, k, k] = 1.0
    planted = replace(out, obj_color=c)
    truth = keep_slots(planted, torch.ones_like(out.obj_mask.flatten(2).any(2))).composite
    visible = torch.stack([(truth.instance == k + 1).flatten(1).sum(1) for k in range(3)], 1)
    kept = torch.ones_like(visible, dtype=torch.bool)
    got = least_useful(StopRule(min_gain=10), planted, truth.image, torch.minimum(truth.depth, out.bg_depth), kept)
    unique = (visible == visible.min(1, keepdim=True).values).sum(1) == 1
    assert unique.sum() >= 3
    assert got[unique].tolist() == visible.argmin(1)[unique].tolist()
    # a slot not kept is never chosen
    kept[torch.arange(len(got)), got] = False
    again = least_useful(StopRule(min_gain=10), planted, truth.image, None, kept)
    assert not bool((again == got).any())


def test_replace_moves_a_used_slot_only_where_the_scene_then_fits_better():
    """Five-object scenes read by a three-slot model: every slot is in use, so plain re-seeding changes nothing;
    with ``replace_least`` a scene's least useful slot is moved onto an object no slot covers wherever that lowers
    its fit score, and no scene fits worse."""
    model, _ = load_model("clevr3_fc")
    batch = SceneDataset(samples_for("clevr5"), split="test").batch(list(range(6)))
    out = infer(model, batch, InferenceConfig())
    busy = prune_keep(ReseedConfig().rule, out, batch.rgb, batch.depth).all(1)  # no idle slot
    assert busy.sum() >= 2
    start = fit_score(out.composite.image, out.composite.depth, batch.rgb, batch.depth)
    plain = reseed(model, out, batch, ReseedConfig(rounds=1))
    assert torch.equal(plain.composite.image[busy], out.composite.image[busy])
    swapped = reseed(model, out, batch, ReseedConfig(rounds=2, replace_least=True))
    end = fit_score(swapped.composite.image, swapped.composite.depth, batch.rgb, batch.depth)
    assert bool((end <= start + 1e-7).all())
    assert bool((end < start - 1e-4)[busy].any()), (start - end).tolist()
    cfg = InferenceConfig.of(reseed=2, reseed_replace=True)
    assert cfg.reseed.replace_least and "replacing the least useful slot" in cfg.describe()
    with pytest.raises(ValueError, match="--reseed-replace needs"):
        InferenceConfig.of(reseed_replace=True)


def test_cast_shadows_are_not_proposed_for_a_model_that_reads_them(decoded):
    """An input that the composition explains but for a patch of ground darkened evenly to 0.45 (a cast shadow), and
    one empty slot: a model without a shadow rule re-seeds onto the patch in some scene; one whose anchors read
    shadows (``anchor_shade_min`` 0.3) proposes nothing there, and its output is the start's."""
    model, batch, out = decoded
    patch = torch.zeros_like(out.composite.instance, dtype=torch.bool)
    patch[:, 44:60, 2:22] = True
    patch &= out.composite.instance == 0  # on the ground only
    assert (patch.flatten(1).sum(1) >= 100).sum() >= 3
    shadowed = replace(batch, rgb=torch.where(patch[:, None], 0.45 * out.composite.image, out.composite.image))
    cfg = ReseedConfig(rounds=1, grow=1)
    plain = reseed(model, out, shadowed, cfg, use_depth=False)
    assert not torch.equal(plain.composite.image, out.composite.image)
    kept_cfg = model.cfg
    try:
        model.cfg = replace(kept_cfg, anchor_shade_min=0.3)
        ruled = reseed(model, out, shadowed, cfg, use_depth=False)
    finally:
        model.cfg = kept_cfg
    assert torch.equal(ruled.composite.image, out.composite.image)


def test_texture_trials_fitted_together_take_the_steps_each_takes_alone(decoded):
    """Re-seeding fits its trials' texture latents in one batch: each must come out as it does fitted alone (the same
    Adam steps on its own mean loss), a trial with no hit in the region must keep its latent exactly, and the fit must
    move the latents it can (else the comparison says nothing)."""
    from prismonet.render import SceneParams, render_objects

    model, batch, out = decoded
    p = out.latents.params
    B, _, H, W = batch.rgb.shape
    trials = []
    for k in range(2):
        sl = slice(k, k + 1)
        one = SceneParams(p.z_sh[:, sl], p.z_tex[:, sl] + 0.3, p.position[:, sl], p.cos_sin[:, sl], p.scale[:, sl],
                          None if p.axis is None else p.axis[:, sl], None if p.active is None else p.active[:, sl])
        trials.append((one, render_objects(model.sdf_fn, None, one, batch.K, batch.T_world_cam, H, W, model.render_settings())))
    region = torch.zeros(B, H, W, dtype=torch.bool)
    region[:, : H // 2] = True  # the upper half: some hits inside, some not
    together = _fit_textures(model, trials, batch.rgb, region)
    alone = [_fit_textures(model, [t], batch.rgb, region)[0] for t in trials]
    for (one, _), a, b in zip(trials, together, alone):
        assert a.shape == one.z_tex.shape
        assert torch.allclose(a, b, atol=1e-5), (a - b).abs().max()
        assert (a - one.z_tex).abs().amax() > 1e-2  # fitted
    nowhere = _fit_textures(model, trials, batch.rgb, torch.zeros_like(region))
    assert all(torch.equal(z, one.z_tex) for z, (one, _) in zip(nowhere, trials))
