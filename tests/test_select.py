"""Over-complete decoding: choosing N of N + extra slots by how well they explain the input."""

import pytest
import torch

from prismonet.assets import shipped_samples
from prismonet.data.dataset import SceneDataset
from prismonet.model.io import load_model, training_loss_config
from prismonet.model.prismonet import ModelOutput, SceneLatents
from prismonet.model.refine import RefineConfig, refine
from prismonet.model.select import decode_overcomplete, gather_slots, select_slots, subset_scores
from prismonet.render import SceneParams, composite

H = W = 4
BG = torch.tensor([[0.5, 0.5, 0.5]])


def _synthetic(M: int = 3) -> ModelOutput:
    """One scene, M flat-coloured square objects: slot k covers column k at depth 1 + k, colour k / M
    (slot M-1 covers columns 0..1 at depth 0.5, in front of slot 0); the plane lies at depth 10."""
    depth = torch.full((1, M, H, W), float("inf"))
    mask = torch.zeros(1, M, H, W, dtype=torch.bool)
    color = torch.zeros(1, M, 3, H, W)
    for k in range(M):
        cols = slice(0, 2) if k == M - 1 else slice(k, k + 1)
        mask[0, k, :, cols] = True
        depth[0, k, :, cols] = 0.5 if k == M - 1 else 1.0 + k
        color[0, k] = k / M
    params = SceneParams(torch.arange(M, dtype=torch.float32).view(1, M, 1).repeat(1, 1, 2), torch.zeros(1, M, 3),
                         torch.zeros(1, M, 3), torch.tensor([[[1.0, 0.0]]]).repeat(1, M, 1), torch.full((1, M), 0.5))
    bg_depth = torch.full((1, 1, H, W), 10.0)
    comp = composite(depth, mask, color, BG, bg_depth)
    return ModelOutput(SceneLatents(params, BG), comp, depth, mask, color, bg_depth)


def test_gather_with_all_slots_in_order_is_the_identity():
    out = _synthetic()
    same = gather_slots(out, torch.tensor([[0, 1, 2]]))
    assert torch.equal(same.composite.image, out.composite.image)
    assert torch.equal(same.composite.instance, out.composite.instance)
    assert torch.equal(same.latents.params.z_sh, out.latents.params.z_sh)
    assert torch.equal(same.slot_steps, torch.tensor([[0, 1, 2]]))


def test_gather_keeps_the_chosen_slots_and_their_encoder_steps():
    out = _synthetic()
    kept = gather_slots(out, torch.tensor([[0, 2]]))
    assert torch.equal(kept.latents.params.z_sh[0, :, 0], torch.tensor([0.0, 2.0]))
    assert torch.equal(kept.slot_steps, torch.tensor([[0, 2]]))
    # slot 2 (now id 2) is in front of slot 0 on columns 0-1; column 2 (old slot 1) is background now
    assert kept.composite.instance[0, 0].tolist() == [2, 2, 0, 0]
    assert torch.equal(kept.composite.image[0, :, 0, 2], BG[0])
    # a second gather maps through the first: its steps stay the original encoder steps
    again = gather_slots(kept, torch.tensor([[1]]))
    assert torch.equal(again.slot_steps, torch.tensor([[2]]))


def test_subset_scores_by_hand():
    out = _synthetic()
    # target: exactly the composition of slots {0, 1}; its depth is that composition's depth
    target = composite(out.obj_depth[:, [0, 1]], out.obj_mask[:, [0, 1]], out.obj_color[:, [0, 1]], BG, out.bg_depth)
    scores, subsets = subset_scores(out, target.image, target.depth, 2, w_image=1.0, w_depth=0.1)
    assert subsets.tolist() == [[0, 1], [0, 2], [1, 2]]
    # {0, 2}: columns 0-1 show slot 2 (colour 2/3, depth 0.5) instead of slot 0 (0, 1) and slot 1 (1/3, 2);
    # column 1 loses slot 1. Per pixel over the 16: colour error summed over 3 channels, depth L1.
    col_err_02 = (4 * 3 * (2 / 3) ** 2 + 4 * 3 * (1 / 3) ** 2) / 16
    dep_err_02 = (4 * 0.5 + 4 * 1.5) / 16
    # {1, 2}: columns 0-1 show slot 2 (slot 0 is gone, column 1 loses slot 1 behind slot 2)
    assert torch.allclose(scores[0, 0], torch.tensor(0.0))
    assert torch.allclose(scores[0, 1], torch.tensor(col_err_02 + 0.1 * dep_err_02))
    assert torch.allclose(scores[0, 2], torch.tensor(col_err_02 + 0.1 * dep_err_02))
    only_colour, _ = subset_scores(out, target.image, None, 2, w_image=2.0)
    assert torch.allclose(only_colour[0], torch.tensor([0.0, 2 * col_err_02, 2 * col_err_02]))
    with pytest.raises(ValueError):
        subset_scores(out, target.image, None, 4)


def test_selection_finds_the_subset_that_made_the_image():
    out = _synthetic(4)
    # slot 3 hides slots 0 and 1 wherever they are, so {2, 3} is the only subset that composes this
    target = composite(out.obj_depth[:, [2, 3]], out.obj_mask[:, [2, 3]], out.obj_color[:, [2, 3]], BG, out.bg_depth)
    best = select_slots(out, target.image, target.depth, 2)
    assert torch.equal(best.slot_steps, torch.tensor([[2, 3]]))
    assert torch.allclose(best.composite.image, target.image)
    # with as many slots as objects, nothing changes, whatever the input
    same = select_slots(out, torch.rand(1, 3, H, W), None, 4)
    assert torch.equal(same.slot_steps, torch.tensor([[0, 1, 2, 3]]))
    assert torch.equal(same.composite.image, out.composite.image)


def test_overcomplete_decoding_of_the_shipped_model():
    model, info = load_model("clevr3_fc")  # the encoder-only model (with a refiner: tests/test_refiner.py)
    b = SceneDataset(shipped_samples(), split="test").batch([0, 1, 2, 3])
    with torch.no_grad():
        plain = model(b.rgb, b.K, b.T_world_cam, b.ground_z)
        four = model(b.rgb, b.K, b.T_world_cam, b.ground_z, num_slots=4)
        chosen = decode_overcomplete(model, b, extra=1)
    assert chosen.obj_depth.shape[1] == 3 and chosen.slot_steps.shape == (4, 3)
    # the first three encoder steps do not depend on how many follow
    assert torch.equal(four.obj_depth[:, :3], plain.obj_depth)
    # the choice never explains the input worse than the first three steps
    scores, _ = subset_scores(four, b.rgb, b.depth, 3)
    s_plain, s_chosen = scores[:, 0], scores.min(1).values
    assert bool((s_chosen <= s_plain).all())
    w = training_loss_config(info)
    again = subset_scores(chosen, b.rgb, b.depth, 3, w.w_image, w.w_depth)[0][:, 0]
    assert torch.allclose(again, s_chosen, atol=1e-6)
    # refinement carries the encoder steps through
    ref = refine(model, chosen, b, w, RefineConfig(steps=1))
    assert torch.equal(ref.slot_steps, chosen.slot_steps)
    assert decode_overcomplete(model, b, extra=0).slot_steps is None
    with pytest.raises(ValueError):
        decode_overcomplete(model, b, extra=-1)


def test_evaluation_with_an_extra_slot_reports_every_encoder_step():
    from prismonet.evaluation.evaluate import evaluate_model
    from prismonet.model.inference import InferenceConfig

    model, _ = load_model("shipped")
    ds = SceneDataset(shipped_samples(), split="test")
    r = evaluate_model(model, ds, batch_size=8, limit=8, progress=False, inference=InferenceConfig(extra_slots=1))
    assert r["num_slots"] == 3 and r["extra_slots"] == 1
    assert [s["step"] for s in r["per_step"]] == [1, 2, 3, 4]
    # at most three of the four steps are kept, so at most three are visible per scene
    assert sum(s["visible"] for s in r["per_step"]) <= 3 + 1e-9
    plain = evaluate_model(model, ds, batch_size=8, limit=8, progress=False)
    assert [s["step"] for s in plain["per_step"]] == [1, 2, 3]
    with pytest.raises(ValueError):
        InferenceConfig(extra_slots=-1)


def test_cli_extra_slots(tmp_path, capsys):
    import json

    from prismonet.cli import main

    data = str(shipped_samples())
    assert main(["reconstruct", "shipped", data, "--count", "1", "--extra-slots", "2", "--out", str(tmp_path / "e2")]) == 0
    assert len(json.loads((tmp_path / "e2" / "0.json").read_text())["objects"]) == 3
    assert main(["reconstruct", "shipped", data, "--extra-slots", "-1", "--out", str(tmp_path / "bad")]) != 0
    assert main(["evaluate", "shipped", data, "--extra-slots", "-1", "--quiet"]) != 0
    assert "non-negative" in capsys.readouterr().err


def test_gather_rejects_a_badly_shaped_index():
    out = _synthetic()
    for bad in (torch.tensor([0, 1]), torch.tensor([[0, 1], [1, 2]])):
        with pytest.raises(ValueError, match="expected shape"):
            gather_slots(out, bad)
