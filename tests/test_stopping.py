"""Stopping the recurrent encoder once the slots found explain the input."""

import pytest
import torch

from prismonet.assets import shipped_samples
from prismonet.data.dataset import SceneDataset
from prismonet.evaluation.metrics import count_metrics
from prismonet.model.inference import InferenceConfig, infer
from prismonet.model.io import load_model
from prismonet.model.stopping import StopRule, erode, keep_first, stop_counts


@pytest.fixture(scope="module")
def shipped():
    torch.manual_seed(0)
    model, _ = load_model("clevr3_fc", num_slots=5)  # the encoder-only model: stopping is a rule on the encoder's steps
    b = SceneDataset(shipped_samples(), split="test").batch(list(range(6)))
    return model, b


def test_unexplained_pixels_by_hand():
    image = torch.zeros(1, 3, 6, 6)
    comp = image.clone()
    comp[0, 1, 1:4, 1:4] = 0.3  # a 3x3 block off by 0.3 in one channel
    comp[0, 0, 5, 5] = 0.2  # one pixel off by less than the tolerance
    depth = torch.ones(1, 1, 6, 6)
    comp_depth = depth.clone()
    comp_depth[0, 0, 0, 5] = 2.0  # one pixel off in depth
    depth[0, 0, 5, 0] = 0.0  # unknown input depth: never counts
    comp_depth[0, 0, 5, 0] = 7.0
    rule = StopRule(color_tol=0.25, depth_tol=0.5, erode=0)
    bad = rule.unexplained(image, depth, comp, comp_depth)
    assert int(bad.sum()) == 9 + 1
    assert bool(bad[0, 0, 5]) and not bool(bad[0, 5, 5]) and not bool(bad[0, 5, 0])
    assert int(rule.unexplained(image, None, comp, comp_depth).sum()) == 9  # colour alone
    # erosion by one pixel leaves the block's centre; the lone depth pixel goes
    assert erode(bad, 1)[0].nonzero().tolist() == [[2, 2]]
    # a block on the image border is not eroded from the border's side
    edge = torch.zeros(1, 4, 4, dtype=torch.bool)
    edge[0, :, :2] = True
    assert int(erode(edge, 1).sum()) == 4  # column 0 survives, column 1 touches false pixels


def test_bound_rule_counts_and_tests():
    image = torch.zeros(2, 3, 8, 8)
    comp = image.clone()
    comp[0, :, :5, :5] = 1.0  # 25 unexplained pixels
    comp[1, :, :4, :6] = 1.0  # 24
    bound = StopRule(erode=0, min_gain=5).bind(image, None)
    counts = bound.count(comp, torch.ones(2, 1, 8, 8))
    assert counts[:, 1].tolist() == [25, 24] and counts[:, 0].tolist() == [25, 24]
    assert bound.explained(counts).tolist() == [False, True]
    after = counts - torch.tensor([[5, 5], [4, 4]])
    assert bound.gained(counts, after).tolist() == [True, False]
    with pytest.raises(ValueError):
        StopRule(min_gain=0)
    with pytest.raises(ValueError):
        StopRule(depth_tol=-1.0)


def test_forward_with_stopping_equals_the_stop_read_off_a_full_decoding(shipped):
    model, b = shipped
    rule = StopRule()
    with torch.no_grad():
        full = model(b.rgb, b.K, b.T_world_cam, b.ground_z)
        stopped = model(b.rgb, b.K, b.T_world_cam, b.ground_z, stop=rule.bind(b.rgb, b.depth))
    kept = stop_counts(rule, full, b.rgb, b.depth)
    assert stopped.latents.params.active.sum(1).tolist() == kept.tolist()
    assert kept.sum() < 5 * len(kept)  # the 3-object scenes do not need all five slots each
    ref = keep_first(full, kept)
    assert torch.equal(ref.composite.instance, stopped.composite.instance)
    assert torch.allclose(ref.composite.image, stopped.composite.image, atol=1e-5)
    # the kept slots are the full decoding's first slots; the rest render nothing
    for j, k in enumerate(kept.tolist()):
        assert torch.allclose(stopped.latents.params.position[j, :k], full.latents.params.position[j, :k], atol=1e-5)
        assert not stopped.obj_mask[j, k:].any()


def _count_encoder_calls(model, monkeypatch) -> list:
    calls = []
    real = model.encoder.forward
    monkeypatch.setattr(model.encoder, "forward", lambda x: (calls.append(x.shape[0]), real(x))[1])
    return calls


def test_an_explained_scene_takes_no_encoder_step(shipped, monkeypatch):
    model, b = shipped
    calls = _count_encoder_calls(model, monkeypatch)
    everything = StopRule(color_tol=10.0, depth_tol=1e9)  # every pixel explained from the start
    with torch.no_grad():
        out = model(b.rgb, b.K, b.T_world_cam, b.ground_z, stop=everything.bind(b.rgb, b.depth))
    assert calls == []
    assert not out.latents.params.active.any() and not out.obj_mask.any()
    assert torch.equal(out.composite.instance, torch.zeros_like(out.composite.instance))


def test_a_slot_that_explains_too_little_is_dropped_and_the_scene_stops(shipped, monkeypatch):
    model, b = shipped
    calls = _count_encoder_calls(model, monkeypatch)
    greedy = StopRule(min_gain=64 * 64 + 1)  # no slot can ever gain that much
    with torch.no_grad():
        out = model(b.rgb, b.K, b.T_world_cam, b.ground_z, stop=greedy.bind(b.rgb, b.depth))
    assert len(calls) == 1  # one step, then every scene stopped
    assert not out.latents.params.active.any() and not out.obj_mask.any()


def test_test_time_steps_keep_stopped_slots_empty(shipped):
    model, b = shipped
    cfg = InferenceConfig.of(search=1, refine=1, fit_color=2, stop=True)
    assert cfg.stop == StopRule() and not cfg.feed_forward
    assert cfg.describe().startswith("encoder stopping when explained, then")
    out = infer(model, b, cfg)
    active = out.latents.params.active
    assert active is not None and not active.all()
    assert not (out.obj_mask & ~active[:, :, None, None]).any()


def test_count_metrics_by_hand():
    def scene(*sizes):
        inst = torch.zeros(16, 16, dtype=torch.long)
        for k, n in enumerate(sizes):
            inst.view(-1)[k * 50 : k * 50 + n] = k + 1
        return inst.numpy()

    import numpy as np

    pred = np.stack([scene(30, 30), scene(30, 10), scene(30, 30, 30)])
    gt = np.stack([scene(30, 30), scene(30, 30), scene(30)])
    m = count_metrics(pred, gt)  # differences 0, -1 (the 10-pixel object does not count), +2
    assert m["count_exact"] == pytest.approx(1 / 3)
    assert m["count_abs_err"] == pytest.approx(1.0)
    assert m["count_bias"] == pytest.approx(1 / 3)
