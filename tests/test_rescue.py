"""Taking back the slots a keep output dropped (``prismonet.model.rescue``): hand-built renders with known pixel counts,
and the rule inside a shipped keep model (what it changes, and what it must not)."""

from dataclasses import replace

import pytest
import torch

from prismonet.model.rescue import rescue_keep
from prismonet.model.stopping import StopRule

GREY, RED, BLUE, GREEN = (0.5, 0.5, 0.5), (1.0, 0.0, 0.0), (0.0, 0.0, 1.0), (0.0, 1.0, 0.0)


def square(rows, cols, color, depth, H=8, W=8):
    """One slot's render: a square of one colour at one depth."""
    d = torch.full((H, W), 12.0)
    m = torch.zeros(H, W, dtype=torch.bool)
    m[rows, cols] = True
    d[m] = depth
    c = torch.zeros(3, H, W)
    c[:, m] = torch.tensor(color)[:, None]
    return d, m, c


def scene(slots):
    """An 8x8 grey image with a red square (rows 0-3, cols 0-3: 16 px) and a blue one (rows 4-7, cols 4-7: 16 px),
    and the slots' renders stacked as the model's ``obj_*``."""
    image = torch.tensor(GREY)[:, None, None].expand(3, 8, 8).clone()
    image[:, :4, :4] = torch.tensor(RED)[:, None, None]
    image[:, 4:, 4:] = torch.tensor(BLUE)[:, None, None]
    d, m, c = zip(*slots)
    return (torch.stack(d)[None], torch.stack(m)[None], torch.stack(c)[None], torch.tensor([GREY]),
            torch.full((1, 1, 8, 8), 12.0), image[None])


RED_SQ = (slice(0, 4), slice(0, 4))
BLUE_SQ = (slice(4, 8), slice(4, 8))


def test_a_dropped_slot_alone_on_its_object_comes_back_a_duplicate_does_not():
    """Slot 0 (kept) is on the red square; slot 1 (dropped) alone on the blue one covers its 16 open pixels; slot 2
    (dropped) repeats slot 0 in front of it and covers no open pixel. The bar is in pixels: 16 passes 10 and 16, not 17."""
    d, m, c, bg, bgd, image = scene([square(*RED_SQ, RED, 5.0), square(*BLUE_SQ, BLUE, 5.0), square(*RED_SQ, RED, 4.0)])
    keep = torch.tensor([[True, False, False]])
    dropped = ~keep
    for gain, want in ((10, [True, True, False]), (16, [True, True, False]), (17, [True, False, False])):
        got = rescue_keep(StopRule(min_gain=gain), d, m, c, bg, bgd, image, None, keep, dropped)
        assert got.tolist() == [want], gain
    assert keep.tolist() == [[True, False, False]]  # the input is left alone


def test_of_two_dropped_duplicates_one_comes_back():
    """Two dropped slots on the one missed object: the first taken back claims its pixels, the second then covers none
    (here it is in front of the first, so it would show all 16)."""
    d, m, c, bg, bgd, image = scene([square(*RED_SQ, RED, 5.0), square(*BLUE_SQ, BLUE, 5.0), square(*BLUE_SQ, BLUE, 4.0)])
    got = rescue_keep(StopRule(min_gain=10), d, m, c, bg, bgd, image, None, torch.tensor([[True, False, False]]),
                      torch.tensor([[False, True, True]]))
    assert got[0, 0] and int(got[0, 1:].sum()) == 1


def test_colour_is_not_read_hidden_slots_and_non_candidates_stay_out():
    """A dropped slot the wrong colour on the missed blue square still covers its 16 open pixels and comes back (its
    texture is not read); one behind a kept slot shows no pixel; a slot that was not dropped (here inactive from the
    start) is never a candidate, however much it would cover."""
    d, m, c, bg, bgd, image = scene([square(*RED_SQ, RED, 5.0), square(*BLUE_SQ, GREEN, 5.0), square(*RED_SQ, RED, 8.0)])
    keep = torch.tensor([[True, False, False]])
    got = rescue_keep(StopRule(min_gain=1), d, m, c, bg, bgd, image, None, keep, torch.tensor([[False, True, True]]))
    assert got.tolist() == [[True, True, False]]
    got = rescue_keep(StopRule(min_gain=1), d, m, c, bg, bgd, image, None, keep, torch.tensor([[False, False, True]]))
    assert got.tolist() == [[True, False, False]]


def test_the_share_of_open_pixels():
    """A dropped slot over rows 4-7 of every column shows 32 pixels: the blue square's 16 (open) and 16 of grey ground
    (explained by the background). Half its pixels are open: it comes back at a share of 0.5, not at 0.6."""
    d, m, c, bg, bgd, image = scene([square(*RED_SQ, RED, 5.0), square(slice(4, 8), slice(0, 8), BLUE, 5.0)])
    keep, dropped = torch.tensor([[True, False]]), torch.tensor([[False, True]])
    assert rescue_keep(StopRule(min_gain=16), d, m, c, bg, bgd, image, None, keep, dropped, share=0.5).tolist() == [[True, True]]
    assert rescue_keep(StopRule(min_gain=16), d, m, c, bg, bgd, image, None, keep, dropped, share=0.6).tolist() == [[True, False]]
    assert rescue_keep(StopRule(min_gain=17), d, m, c, bg, bgd, image, None, keep, dropped, share=0.5).tolist() == [[True, False]]


def test_depth_opens_pixels_colour_alone_does_not():
    """A grey object on the grey ground (rows 4-7, cols 0-3) is explained in colour by the background; with the input's
    depth (5 there, the ground 12) its 16 pixels are open, and the dropped slot on it comes back."""
    d, m, c, bg, bgd, image = scene([square(*RED_SQ, RED, 5.0), square(slice(4, 8), slice(0, 4), GREY, 5.0)])
    measured = torch.full((1, 1, 8, 8), 12.0)
    measured[0, 0, :4, :4] = 5.0
    measured[0, 0, 4:, :4] = 5.0
    measured[0, 0, 4:, 4:] = 5.0
    keep, dropped = torch.tensor([[True, False]]), torch.tensor([[False, True]])
    assert rescue_keep(StopRule(min_gain=10), d, m, c, bg, bgd, image, measured, keep, dropped).tolist() == [[True, True]]
    assert rescue_keep(StopRule(min_gain=10), d, m, c, bg, bgd, image, None, keep, dropped).tolist() == [[True, False]]


def test_bad_shapes_are_refused():
    d, m, c, bg, bgd, image = scene([square(*RED_SQ, RED, 5.0), square(*BLUE_SQ, BLUE, 5.0)])
    with pytest.raises(ValueError, match="rescue: keep"):
        rescue_keep(StopRule(), d, m, c, bg, bgd, image, None, torch.ones(1, 3, dtype=torch.bool), torch.zeros(1, 2, dtype=torch.bool))


@pytest.fixture(scope="module")
def cars_keep():
    from prismonet.assets import samples_for
    from prismonet.data.dataset import SceneDataset
    from prismonet.model.io import load_model

    model, _ = load_model("cars_keep")
    return model, SceneDataset(samples_for("cars_keep"), split="test").batch(list(range(8)))


def _run(model, b, **fields):
    from prismonet.model.prismonet import PriSMONet

    m = PriSMONet(replace(model.cfg, **fields), prior=model.prior)
    m.load_state_dict(model.state_dict())
    with torch.no_grad():
        return m.eval()(b.rgb, b.K, b.T_world_cam, b.ground_z)


def test_rescue_in_a_keep_model(cars_keep):
    """``refiner_rescue_px`` in the shipped ``cars_keep`` with a keep bar that drops every slot: the passes record what
    they dropped; rescue takes back a non-empty subset of it and moves no latent; an unreachable bar (a whole image of
    pixels) changes nothing; off, the model is as shipped. The colour step still runs on what was taken back."""
    model, b = cars_keep
    shipped = _run(model, b)
    assert shipped.dropped is not None and torch.equal(shipped.dropped, ~shipped.latents.params.active)
    none = _run(model, b, refiner_keep_logit=100.0)
    assert not bool(none.latents.params.active.any()) and bool(none.dropped.all())
    never = _run(model, b, refiner_keep_logit=100.0, refiner_rescue_px=64 * 64 + 1)
    assert torch.equal(never.composite.image, none.composite.image) and not bool(never.latents.params.active.any())
    back = _run(model, b, refiner_keep_logit=100.0, refiner_rescue_px=10)
    kept = back.latents.params.active
    assert bool(kept.any()) and int(kept.sum()) <= int(none.dropped.sum())
    assert torch.equal(back.dropped, ~kept)
    assert not bool(back.obj_mask[~kept].any()) and bool(back.obj_mask[kept].flatten(1).any(1).all())
    for name in ("position", "scale", "cos_sin", "z_sh"):
        assert torch.equal(getattr(back.latents.params, name), getattr(none.latents.params, name))
    assert not torch.equal(back.latents.params.z_tex[kept], none.latents.params.z_tex[kept])  # the colour step ran on them
    # each slot taken back shows at least 10 pixels of its own
    assert int(back.obj_mask.flatten(2).sum(2)[kept].min()) >= 10


def test_rescue_needs_a_keep_refiner_and_training_ignores_it(cars_keep):
    from prismonet.model.config import ModelConfig
    from prismonet.model.prismonet import PriSMONet

    for bad in ({"refiner_rescue_px": 5}, {"refiner_rescue_px": 5, "refine_passes": 1}, {"refiner_rescue_px": -1}):
        with pytest.raises(ValueError, match="refiner_rescue_px"):
            ModelConfig(**bad)
    model, b = cars_keep
    outs = []
    for px in (0, 10):
        m = PriSMONet(replace(model.cfg, refiner_keep_logit=100.0, refiner_rescue_px=px), prior=model.prior)
        m.load_state_dict(model.state_dict())
        with torch.no_grad():
            outs.append(m.train()(b.rgb[:2], b.K[:2], b.T_world_cam[:2], b.ground_z[:2]).latents.params.active)
    assert torch.equal(outs[0], outs[1])


def test_instance_figure_refuses_bad_flags_in_one_line(tmp_path):
    """``scripts/instance_figure.py``: as many labels as models, and scene indices inside the split; one line each, no
    figure written."""
    import subprocess
    import sys
    from pathlib import Path

    from prismonet.assets import samples_for

    script = Path(__file__).resolve().parents[1] / "scripts" / "instance_figure.py"
    data = str(samples_for("cars_keep"))
    out = tmp_path / "f.png"
    for extra, says in ((["--names", "a,b"], "--names: 2 labels for 1 models"),
                        (["--scenes", "0,x"], "--scenes: expected comma-separated scene indices"),
                        (["--scenes", "0,99"], "--scenes: indices must be within the 16 scenes")):
        r = subprocess.run([sys.executable, str(script), "cars_keep", "--data", data, "--split", "test", "--out", str(out), *extra],
                           capture_output=True, text=True)
        assert r.returncode != 0 and says in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
        assert not out.exists()
