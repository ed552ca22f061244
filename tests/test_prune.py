"""Pruning the slots that explain nothing, after the test-time steps."""

from dataclasses import replace

import pytest
import torch

from prismonet.assets import shipped_samples
from prismonet.data.dataset import SceneDataset
from prismonet.model.inference import InferenceConfig, infer
from prismonet.model.io import load_model
from prismonet.model.prune import PRUNE_RULE, prune, prune_keep
from prismonet.model.stopping import keep_slots
from prismonet.render import composite


@pytest.fixture(scope="module")
def decoded():
    torch.manual_seed(0)
    model, _ = load_model("shipped", num_slots=5)
    b = SceneDataset(shipped_samples(), split="test").batch(list(range(4)))
    with torch.no_grad():
        out = model(b.rgb, b.K, b.T_world_cam, b.ground_z)
    return model, b, out


def _planted(out):
    """``out`` with slots 0-2 painted pure red, green and blue, slot 3 a duplicate of slot 0, slot 4 a
    white copy of slot 1 just behind it (so hidden by it), and the input that slots 0-2 explain exactly (their own
    composition)."""
    d, m, c = out.obj_depth.clone(), out.obj_mask.clone(), out.obj_color.clone()
    for k in range(3):
        c[:, k] = 0.0
        c[:, k, k] = 1.0
    d[:, 3], m[:, 3], c[:, 3] = d[:, 0], m[:, 0], c[:, 0]
    d[:, 4], m[:, 4], c[:, 4] = d[:, 1] + 1e-3, m[:, 1], 1.0
    planted = replace(out, obj_depth=d, obj_mask=m, obj_color=c)
    first3 = torch.tensor([True, True, True, False, False]).expand(d.shape[0], 5)
    truth = keep_slots(planted, first3).composite
    return planted, truth.image, torch.minimum(truth.depth, out.bg_depth)


def test_hidden_and_duplicate_slots_are_dropped_and_the_others_kept(decoded):
    _, _, out = decoded
    planted, image, depth = _planted(out)
    # precondition: in the input each of slots 0-2 explains at least min_gain pixels alone
    inst = keep_slots(planted, torch.tensor([True] * 3 + [False] * 2).expand(4, 5)).composite.instance
    visible = torch.stack([(inst == k + 1).flatten(1).sum(1) for k in range(3)], 1)
    assert (visible >= PRUNE_RULE.min_gain).all(), visible
    keep = prune_keep(PRUNE_RULE, planted, image, depth)
    assert not keep[:, 4].any()  # hidden behind slot 1
    assert (keep[:, 0] ^ keep[:, 3]).all()  # exactly one of the two duplicates
    assert keep[:, 1:3].all()
    pruned = prune(planted, image, depth)
    assert torch.allclose(pruned.composite.image, image, atol=1e-6)
    assert not (pruned.obj_mask & ~keep[:, :, None, None]).any()
    assert torch.equal(pruned.latents.params.active, keep)


def test_colour_alone_and_an_input_nothing_explains(decoded):
    _, _, out = decoded
    planted, image, _ = _planted(out)
    keep = prune_keep(PRUNE_RULE, planted, image, None)
    assert keep.sum(1).tolist() == [3, 3, 3, 3]
    # an input far from every slot's colour and depth: no slot explains any pixel, so all go
    far = prune_keep(PRUNE_RULE, planted, 1.0 - image.clamp(0, 1) + 5.0, None)
    assert not far.any()


def test_prune_is_an_inference_step(decoded):
    model, b, _ = decoded
    cfg = InferenceConfig.of(prune=True)
    assert cfg.prune == PRUNE_RULE and not cfg.feed_forward
    assert cfg.describe() == "encoder, then pruning the slots that explain nothing"
    steps = []
    out = infer(model, b, cfg, on_step=lambda name, o: steps.append(name))
    assert steps == ["encoder", "pruned"]
    active = out.latents.params.active
    assert active is not None and active.sum(1).max() <= 5
    # the composition of what is kept is the z-buffer of the kept slots
    ref = composite(out.obj_depth, out.obj_mask, out.obj_color, out.latents.bg_color, out.bg_depth)
    assert torch.equal(ref.instance, out.composite.instance)
