"""The learnt refinement pass: its corrections (hand-computed), its inputs, a fresh refiner is the identity,
and its training on distillation targets (learns a known correction, resumes, saves a model that loads)."""

import json
import math
from pathlib import Path

import pytest
import torch

from prismonet.model.refiner import (IN_CHANNELS, MAX_LOG_SCALE, MAX_TURN, active_rows, apply_correction, centre_pixels,
                                     choose_shapes, glimpse, hold_cells, refiner_inputs, shape_labels, slot_latents,
                                     slot_views, snap_shapes, with_coords)
from prismonet.render import SceneParams


def two_slots(dtype=torch.float32):
    return SceneParams(torch.zeros(1, 2, 8, dtype=dtype), torch.zeros(1, 2, 7, dtype=dtype),
                       torch.tensor([[[0.0, 0.0, 0.5], [1.0, -1.0, 0.4]]], dtype=dtype),
                       torch.tensor([[[1.0, 0.0], [0.0, 1.0]]], dtype=dtype), torch.tensor([[0.5, 0.4]], dtype=dtype))


def test_correction_hand_computed():
    """Position moves by ``pos_scale`` times the output, the yaw turns by ``MAX_TURN tanh``, the scale
    takes the factor ``exp(MAX_LOG_SCALE tanh)``, the texture latent adds the rest; an inactive slot keeps all."""
    p = two_slots()
    d = torch.zeros(2, 12)
    d[0, :3] = torch.tensor([0.1, -0.2, 0.0])
    d[0, 3] = math.atanh(0.5)  # a turn of MAX_TURN / 2
    d[0, 4] = math.atanh(-0.25)
    d[0, 5:] = 1.0
    d[1] = 3.0
    pos_scale = torch.tensor([1.5, 1.5, 0.5])
    new = apply_correction(p, d, pos_scale, (0.25, 0.9))
    assert new.position[0, 0].tolist() == pytest.approx([0.15, -0.3, 0.5])
    turn = MAX_TURN / 2
    assert new.cos_sin[0, 0].tolist() == pytest.approx([math.cos(turn), math.sin(turn)], abs=1e-6)
    assert float(new.scale[0, 0]) == pytest.approx(0.5 * math.exp(-0.25 * MAX_LOG_SCALE), rel=1e-6)
    assert new.z_tex[0, 0].tolist() == pytest.approx([1.0] * 7)
    assert float(new.scale[0, 1]) == pytest.approx(0.4 * math.exp(MAX_LOG_SCALE * math.tanh(3.0)), rel=1e-6)
    assert float(apply_correction(p, d, pos_scale, (0.25, 0.5)).scale[0, 1]) == pytest.approx(0.5)  # kept in the range
    p.active = torch.tensor([[True, False]])
    kept = apply_correction(p, d, pos_scale, (0.25, 0.9))
    for name in ("position", "cos_sin", "scale", "z_tex"):
        assert torch.equal(getattr(kept, name)[0, 1], getattr(p, name)[0, 1])
    assert torch.equal(kept.position[0, 0], new.position[0, 0])
    # without the turn the yaw stays, and everything else moves as with it
    still = apply_correction(p, d, pos_scale, (0.25, 0.9), turn=False)
    assert torch.equal(still.cos_sin, p.cos_sin)
    for name in ("position", "scale", "z_tex", "z_sh"):
        assert torch.equal(getattr(still, name), getattr(kept, name))


def test_shape_correction_hand_computed():
    """With ``D_sh`` more outputs the shape latent adds them (the texture its own ``D_tex``); an inactive slot keeps
    its shape; an output of any other length is refused."""
    p = two_slots()
    d = torch.zeros(2, 5 + 7 + 8)
    d[:, 5:12] = 0.5
    d[0, 12:] = torch.arange(8.0)
    d[1, 12:] = -1.0
    new = apply_correction(p, d, torch.ones(3), (0.25, 0.9))
    assert new.z_tex[0].flatten().tolist() == pytest.approx([0.5] * 14)
    assert new.z_sh[0, 0].tolist() == pytest.approx(list(range(8)))
    assert new.z_sh[0, 1].tolist() == pytest.approx([-1.0] * 8)
    p.active = torch.tensor([[True, False]])
    kept = apply_correction(p, d, torch.ones(3), (0.25, 0.9))
    assert torch.equal(kept.z_sh[0, 1], p.z_sh[0, 1]) and torch.equal(kept.z_sh[0, 0], new.z_sh[0, 0])
    assert torch.equal(apply_correction(p, d[:, :12], torch.ones(3), (0.25, 0.9)).z_sh, p.z_sh)  # no shape outputs
    with pytest.raises(ValueError, match="refiner output"):
        apply_correction(p, d[:, :15], torch.ones(3), (0.25, 0.9))


def test_keep_logit_drops_slots():
    """With ``keep`` the last output is a keep logit: a slot whose logit is not positive becomes inactive (its latents
    still move), one already inactive stays inactive and keeps its latents."""
    p = two_slots()
    d = torch.zeros(2, 13)
    d[:, 0] = 0.1
    d[0, -1], d[1, -1] = 2.0, -0.5
    new = apply_correction(p, d, torch.ones(3), (0.25, 0.9), keep=True)
    assert new.active.tolist() == [[True, False]]
    assert new.position[0, :, 0].tolist() == pytest.approx([0.1, 1.1])  # the keep logit is not read as a latent
    assert torch.equal(new.z_tex, p.z_tex)
    p.active = torch.tensor([[False, True]])
    d[:, -1] = 1.0
    kept = apply_correction(p, d, torch.ones(3), (0.25, 0.9), keep=True)
    assert kept.active.tolist() == [[False, True]] and float(kept.position[0, 0, 0]) == 0.0


def test_keep_bar_moves():
    """``keep_above``: a slot is kept where its keep logit is above the bar (0 by default); ``None`` keeps every
    active slot. Latents move the same whatever the bar."""
    p = two_slots()
    p.active = torch.ones(1, 2, dtype=torch.bool)
    d = torch.zeros(2, 13)
    d[:, 0] = 0.1
    d[0, -1], d[1, -1] = -1.0, -3.0
    bars = {0.0: [False, False], -2.0: [True, False], -3.0: [True, False], -3.5: [True, True], None: [True, True]}
    for bar, want in bars.items():
        new = apply_correction(p, d, torch.ones(3), (0.25, 0.9), keep=True, keep_above=bar)
        assert new.active[0].tolist() == want, bar
        assert new.position[0, :, 0].tolist() == pytest.approx([0.1, 1.1])


def test_snap_shapes_hand_computed():
    """``snap_shapes``: each slot's shape latent becomes its nearest code (Euclidean), the rest of the slot as it was."""
    p = two_slots()
    p.z_sh = torch.zeros(1, 2, 2)
    p.z_sh[0, 0] = torch.tensor([0.9, 0.2])   # nearest (1, 0): distance 0.22 against 0.92 and 1.3
    p.z_sh[0, 1] = torch.tensor([-0.1, 0.6])  # nearest (0, 1): 0.41 against 1.28 and 1.22
    p.active = torch.tensor([[True, False]])
    codes = torch.tensor([[1.0, 0.0], [0.0, 1.0], [-1.0, -1.0]])
    new = snap_shapes(p, codes)
    assert new.z_sh.tolist() == [[[1.0, 0.0], [0.0, 1.0]]]
    assert new.z_sh.shape == p.z_sh.shape and p.z_sh[0, 0, 0].item() == pytest.approx(0.9)  # the input is left alone
    for name in ("z_tex", "position", "cos_sin", "scale", "active"):
        assert torch.equal(getattr(new, name), getattr(p, name))


def test_hold_cells_hand_computed():
    """``hold_cells``: a slot's stepped latent where its nearest code is the one nearest before the step, else the
    latent before it."""
    codes = torch.tensor([[1.0, 0.0], [0.0, 1.0], [-1.0, -1.0]])
    before = torch.tensor([[[0.9, 0.2], [0.9, 0.2], [-0.1, 0.6]]])  # nearest codes 0, 0, 1
    after = torch.tensor([[[0.6, 0.4], [0.3, 0.8], [-0.6, -0.5]]])  # nearest 0 (0.57 < 0.72), 1, 2
    got = hold_cells(before, after, codes)
    assert torch.equal(got, torch.tensor([[[0.6, 0.4], [0.9, 0.2], [-0.1, 0.6]]]))
    assert torch.equal(hold_cells(before, before, codes), before)


def test_hold_cells_in_the_later_passes_only(shipped):
    """``refiner_hold_cells_from``: a refiner whose shape step throws every slot far along one axis moves slots into
    other codes' cells in its first pass; held from the second pass, that pass takes no step that leaves a cell (each
    slot's nearest code is the first pass's), the positions are the unheld model's, and held from the first pass no
    slot leaves the encoder's cell. Out-of-range values are refused."""
    from dataclasses import replace

    from prismonet.model.config import ModelConfig
    from prismonet.model.prismonet import PriSMONet
    from prismonet.model.refiner_fit import with_refiner

    model, b, _ = shipped
    base = with_refiner(model, refiner_shape=True)
    codes = model.prior.latents
    tex_end = 5 + model.cfg.tex_dim
    def nearest(z):
        return torch.cdist(z.reshape(-1, z.shape[-1]), codes).argmin(1)

    got = {}
    for passes, hold in ((1, None), (2, None), (2, 1), (2, 0)):
        m = PriSMONet(replace(base.cfg, refine_passes=passes, refiner_hold_cells_from=hold), prior=model.prior)
        m.load_state_dict(base.state_dict())
        with torch.no_grad():
            m.refiner.head[-1].bias[0] = 0.05  # every slot moves in x
            m.refiner.head[-1].bias[tex_end] = 0.3  # the first shape value: a step that crosses cells
            got[passes, hold] = m.eval()(b.rgb, b.K, b.T_world_cam, b.ground_z, recolor=False, refine=True)
    enc = nearest(base.eval()(b.rgb, b.K, b.T_world_cam, b.ground_z, recolor=False, refine=False).latents.params.z_sh)
    one, free, held, held0 = (nearest(got[k].latents.params.z_sh) for k in ((1, None), (2, None), (2, 1), (2, 0)))
    assert not torch.equal(one, enc) and not torch.equal(free, one)  # the steps cross cells unheld
    assert torch.equal(held, one) and torch.equal(held0, enc)
    assert torch.equal(got[2, 1].latents.params.position, got[2, None].latents.params.position)
    for fields in ({"refine_passes": 2, "refiner_shape": True, "refiner_hold_cells_from": 2},
                   {"refine_passes": 2, "refiner_hold_cells_from": 1},
                   {"refine_passes": 2, "refiner_shape": True, "refiner_hold_cells_from": -1}):
        with pytest.raises(ValueError, match="refiner_hold_cells_from must index"):
            ModelConfig(**fields)


def test_choose_shapes_and_shape_labels_hand_computed():
    """``choose_shapes``: the slot's own latent where logit 0 is the largest, else the code of the largest logit (the
    first on a tie); ``shape_labels``: 0 where the target is the slot's own latent, else 1 + its nearest code."""
    codes = torch.tensor([[1.0, 0.0], [0.0, 1.0], [-1.0, 0.0]])
    own = torch.tensor([[[0.2, 0.3], [0.5, 0.5], [0.0, 0.0], [9.0, 9.0]]])
    logits = torch.tensor([[[5.0, 1.0, 2.0, 3.0], [0.0, 1.0, 4.0, 0.5], [0.0, 2.0, 0.0, 2.0], [1.0, 1.0, 0.0, 0.0]]])
    z = choose_shapes(own, logits, codes)
    assert torch.equal(z, torch.tensor([[[0.2, 0.3], [0.0, 1.0], [1.0, 0.0], [9.0, 9.0]]]))
    with pytest.raises(ValueError, match="1 \\+ 3"):
        choose_shapes(own, logits[..., :3], codes)
    target = torch.tensor([[[0.2, 0.3], [0.0, 1.0], [-0.9, 0.2], [9.0, 9.00005]]])
    assert shape_labels(own, target, codes).tolist() == [[0, 2, 3, 0]]
    # a target that is a code and is also the slot's own latent counts as kept
    assert shape_labels(codes[None, :1], codes[None, :1], codes).tolist() == [[0]]


def test_shape_codes_refiner_chooses_and_starts_as_the_identity(shipped):
    """A refiner with shape codes has ``1 + S`` shape logits; fresh, it keeps every slot's own shape (the identity);
    with a code's logit raised, every slot draws that code, the pose untouched."""
    from prismonet.model.config import ModelConfig
    from prismonet.model.refiner_fit import with_refiner

    model, b, _ = shipped
    ref = with_refiner(model, refiner_shape=True, refiner_shape_codes=True, refiner_keep=True).eval()
    S = model.prior.latents.shape[0]
    tex_end = 5 + model.cfg.tex_dim
    assert ref.refiner.head[-1].out_features == tex_end + 1 + S + 1
    with torch.no_grad():
        plain = ref(b.rgb, b.K, b.T_world_cam, b.ground_z, refine=False).latents.params
        fresh = ref(b.rgb, b.K, b.T_world_cam, b.ground_z, recolor=False).latents.params
        assert torch.equal(fresh.z_sh, plain.z_sh) and torch.allclose(fresh.position, plain.position, atol=1e-6)
        ref.refiner.head[-1].bias[tex_end + 1 + 5] = 10.0  # code 5
        chosen = ref(b.rgb, b.K, b.T_world_cam, b.ground_z, recolor=False).latents.params
    assert torch.equal(chosen.z_sh, model.prior.latents[5].expand_as(chosen.z_sh))
    assert torch.allclose(chosen.position, plain.position, atol=1e-6)
    with pytest.raises(ValueError, match="refiner_shape_codes"):
        ModelConfig(refine_passes=1, refiner_shape_codes=True)


def test_fit_refiner_learns_a_shape_choice(shipped, tmp_path):
    """Targets whose shape is prior code 7 for every slot: the shape-choice refiner learns to draw code 7 (held-out
    scenes too); its loss starts at the cross-entropy of a fresh refiner's logits."""
    import math as _m

    from prismonet.assets import shipped_samples
    from prismonet.data.dataset import SceneDataset
    from prismonet.model.io import load_model
    from prismonet.model.refiner import OWN_SHAPE_INIT
    from prismonet.model.refiner_fit import SHAPE_CODE_WEIGHT, RefinerFitConfig, fit_refiner, with_refiner

    model = shipped[0]
    ds = SceneDataset(shipped_samples(), split="test")
    _shifted_targets(model, ds, tmp_path / "t", 12, [0.0, 0.0, 0.0], shape_step=0.0)
    chunk = tmp_path / "t" / "chunk_00000.safetensors"
    from prismonet.checkpoint import load_checkpoint, save_checkpoint

    t, meta = load_checkpoint(chunk)
    t["z_sh"] = model.prior.latents[7].expand_as(t["z_sh"]).clone()
    save_checkpoint(chunk, t, meta)
    cfg = RefinerFitConfig(steps=60, batch_size=8, lr=2e-3, holdout=4, checkpoint_every=60)
    torch.manual_seed(0)
    s = fit_refiner(with_refiner(model, refiner_shape=True, refiner_shape_codes=True, refiner_keep=False), ds,
                    tmp_path / "t", tmp_path / "codes", cfg, progress=False)
    S = model.prior.latents.shape[0]
    start = SHAPE_CODE_WEIGHT * (_m.log(_m.exp(OWN_SHAPE_INIT) + S))  # -log softmax of a code's logit 0
    assert s["held_out_start"] == pytest.approx(start, rel=1e-4)
    assert s["held_out_end"] < 0.5 * start
    fitted = load_model(str(tmp_path / "codes"))[0]
    assert fitted.cfg.refiner_shape_codes
    b = ds.batch([10, 11])  # held out
    with torch.no_grad():
        z = fitted(b.rgb, b.K, b.T_world_cam, b.ground_z, recolor=False).latents.params.z_sh
    assert torch.equal(z, model.prior.latents[7].expand_as(z))


def test_with_shape_step_decodes_as_before_until_trained(clevr3):
    """``with_shape_step``: a refiner without a shape step gains one; the copy decodes bit for bit as the model (keep
    logits and all), its head's shape rows are zero and the keep row is the old last row; a raised shape bias then moves
    every refined slot's shape latent by it, and nothing else moves."""
    from prismonet.model.refiner_fit import with_shape_step

    model, b, _ = clevr3
    assert model.cfg.refine_passes and not model.cfg.refiner_shape and model.cfg.refiner_keep
    new = with_shape_step(model).eval()
    tex_end, sh = 5 + model.cfg.tex_dim, model.prior.latents.shape[1]
    w_old, w_new = model.refiner.head[-1].weight, new.refiner.head[-1].weight
    assert w_new.shape[0] == w_old.shape[0] + sh and not bool(w_new[tex_end:tex_end + sh].any())
    b_old, b_new = model.refiner.head[-1].bias, new.refiner.head[-1].bias
    assert torch.equal(w_new[-1], w_old[-1]) and torch.equal(b_new[-1], b_old[-1])
    with torch.no_grad():
        a = model.eval()(b.rgb, b.K, b.T_world_cam, b.ground_z)
        c = new(b.rgb, b.K, b.T_world_cam, b.ground_z)
        assert torch.equal(a.composite.image, c.composite.image) and torch.equal(a.keep_logit, c.keep_logit)
        new.refiner.head[-1].bias[tex_end] += 0.25
        d = new(b.rgb, b.K, b.T_world_cam, b.ground_z, refine=True, recolor=False)
        e = new(b.rgb, b.K, b.T_world_cam, b.ground_z, refine=False, recolor=False)
        one_old = model.refine_pass(e, b.rgb, b.K, b.T_world_cam, 0).latents.params  # one pass from the same slots
        one_new = new.refine_pass(e, b.rgb, b.K, b.T_world_cam, 0).latents.params
    pd, pe = d.latents.params, e.latents.params
    act = pd.active
    moved = pd.z_sh - pe.z_sh
    want = torch.full_like(moved[act][:, 0], 0.25 * model.cfg.refine_passes)
    assert torch.allclose(moved[act][:, 0], want, atol=1e-5)
    assert not bool(moved[act][:, 1:].any())
    assert torch.equal(one_new.position, one_old.position) and torch.equal(one_new.active, one_old.active)
    assert torch.allclose(one_new.z_sh - one_old.z_sh, torch.tensor(0.25) * (torch.arange(sh) == 0), atol=1e-6)
    with pytest.raises(ValueError, match="has one already"):
        with_shape_step(new)


def without_resteps(model):
    """``model`` (a copy) without ``reanchor_steps``: the refiner's passes alone."""
    from dataclasses import replace

    from prismonet.model.prismonet import PriSMONet

    m = PriSMONet(replace(model.cfg, reanchor_steps=0), prior=model.prior)
    m.load_state_dict(model.state_dict())
    return m.eval()


def test_refiner_snap_and_keep_bar_in_the_model(shipped):
    """``refiner_snap_shape``: after the pass every shape latent is a training code of the prior, and the positions are the
    plain pass's; ``refiner_keep_logit``: a slot whose logit (here 0.5 for all) is at or below the bar is dropped.
    Both need a refinement pass."""
    from prismonet.model.config import ModelConfig
    from prismonet.model.refiner_fit import with_refiner

    model, b, _ = shipped
    model = without_resteps(model)  # the steps after refinement would fill the slots the bar drops
    runs = {}
    for name, extra in (("plain", {}), ("snap", {"refiner_snap_shape": True}), ("bar", {"refiner_keep_logit": 0.5})):
        m = with_refiner(model, refiner_keep=True, refiner_shape=True, **extra).eval()
        with torch.no_grad():  # the last layer's weights are zero: the bias is every slot's output
            m.refiner.head[-1].bias[0] = 0.1  # every slot moves in x
            m.refiner.head[-1].bias[-1] = 0.5  # keep logit 0.5: kept at the default bar 0, dropped at a bar of 0.5
            runs[name] = m(b.rgb, b.K, b.T_world_cam, b.ground_z, recolor=False).latents.params
    codes = model.prior.latents
    plain, snap, bar = runs["plain"], runs["snap"], runs["bar"]
    def is_code(z):  # (B, N): the slot's latent equals a row of codes exactly
        return (z[..., None, :] == codes).all(-1).any(-1)

    assert not bool(is_code(plain.z_sh).all()) and bool(is_code(snap.z_sh).all())
    assert torch.equal(snap.position, plain.position) and torch.equal(snap.active, plain.active)
    assert bool(plain.active.any()) and not bool(bar.active.any())
    for fields in ({"refiner_snap_shape": True}, {"refiner_keep_logit": 1.0}):
        with pytest.raises(ValueError, match="need refine_passes"):
            ModelConfig(**fields)
    with pytest.raises(ValueError, match="refiner_keep_logit must be a finite"):
        ModelConfig(refine_passes=1, refiner_keep_logit=float("nan"))


def test_correction_gradcheck():
    p = two_slots(torch.float64)
    d = torch.randn(2, 12, dtype=torch.float64, generator=torch.Generator().manual_seed(0)) * 0.3
    d.requires_grad_(True)

    def f(x):
        n = apply_correction(p, x, torch.tensor([1.5, 1.5, 0.5], dtype=torch.float64), (0.1, 5.0))
        return n.position, n.cos_sin, n.scale, n.z_tex

    assert torch.autograd.gradcheck(f, (d,))
    d_sh = torch.randn(2, 20, dtype=torch.float64, generator=torch.Generator().manual_seed(1)).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda x: apply_correction(p, x, torch.ones(3, dtype=torch.float64), (0.1, 5.0)).z_sh, (d_sh,))


def test_slot_views_and_latents():
    B, N, H, W = 2, 3, 8, 8
    g = torch.Generator().manual_seed(1)
    image, comp = torch.rand(B, 3, H, W, generator=g), torch.rand(B, 3, H, W, generator=g)
    instance = torch.randint(0, N + 1, (B, H, W), generator=g)
    obj_mask = torch.rand(B, N, H, W, generator=g) > 0.5
    v = slot_views(image, comp, instance, obj_mask).reshape(B, N, IN_CHANNELS, H, W)
    assert torch.equal(v[1, 2, :3], image[1]) and torch.allclose(v[1, 2, 3:6], image[1] - comp[1])
    assert torch.equal(v[1, 2, 6], (instance[1] == 3).float()) and torch.equal(v[0, 1, 7], obj_mask[0, 1].float())
    p = two_slots()
    lat = slot_latents(p, torch.tensor([0.0, 0.0, 0.4]), torch.tensor([1.5, 1.5, 0.5])).reshape(2, -1)
    assert lat.shape == (2, 8 + 7 + 6)
    assert lat[1, 15:18].tolist() == pytest.approx([1 / 1.5, -1 / 1.5, 0.0], abs=1e-6)
    assert float(lat[1, 20]) == pytest.approx(math.log(0.4))


@pytest.mark.parametrize("glimpse_frac, coords", [(0.0, False), (0.0, True), (0.375, True)])
def test_inputs_of_some_slots_are_those_rows_of_every_slots_inputs(glimpse_frac, coords):
    """Built for the active rows alone, the refiner's inputs equal those rows of the inputs of every slot, exactly."""
    B, N, H, W = 3, 4, 16, 16
    g = torch.Generator().manual_seed(3)
    image, comp = torch.rand(B, 3, H, W, generator=g), torch.rand(B, 3, H, W, generator=g)
    instance = torch.randint(0, N + 1, (B, H, W), generator=g)
    obj_mask = torch.rand(B, N, H, W, generator=g) > 0.5
    p = SceneParams(torch.randn(B, N, 8, generator=g), torch.randn(B, N, 7, generator=g),
                    torch.randn(B, N, 3, generator=g) + torch.tensor([0.0, 0.0, 6.0]), torch.randn(B, N, 2, generator=g),
                    torch.rand(B, N, generator=g) + 0.2)
    K = torch.tensor([[20.0, 0.0, 7.5], [0.0, 20.0, 7.5], [0.0, 0.0, 1.0]]).expand(B, 3, 3)
    T = torch.eye(4).expand(B, 4, 4)
    args = (image, comp, instance, obj_mask, p, torch.zeros(3), torch.ones(3), K, T, coords, glimpse_frac)
    every_v, every_l = refiner_inputs(*args)
    active = torch.tensor([[True, False, False, True], [False, False, False, False], [False, True, True, True]])
    rows = active_rows(active)
    assert rows.tolist() == [0, 3, 9, 10, 11]
    some_v, some_l = refiner_inputs(*args, rows)
    assert torch.equal(some_v, every_v[rows]) and torch.equal(some_l, every_l[rows])
    assert active_rows(torch.ones(B, N, dtype=torch.bool)) is None and active_rows(None) is None


def test_glimpse_and_coords_hand_computed():
    """A whole-image glimpse centred on the image is the image; a half-size glimpse samples every second
    half pixel around its centre; position channels run from -1 + 1/W to 1 - 1/W at pixel centres."""
    g = torch.Generator().manual_seed(2)
    v = torch.rand(2, 4, 8, 8, generator=g)
    same, uv = glimpse(v, torch.tensor([[3.5, 3.5], [3.5, 3.5]]), 1.0)
    assert torch.allclose(same, v, atol=1e-6) and uv[0, 0, 0].tolist() == [0.0, 0.0]
    half, uv = glimpse(v, torch.tensor([[4.0, 3.0], [2.0, 2.0]]), 0.5)
    assert uv[0, 3, 3].tolist() == pytest.approx([3.75, 2.75]) and uv[0, 4, 4].tolist() == pytest.approx([4.25, 3.25])
    # view pixel (4, 4) of scene 0 falls a quarter pixel right of and below image pixel (4, 3): bilinear weights 9/16, 3/16, 3/16, 1/16
    want = (9 * v[0, :, 3, 4] + 3 * v[0, :, 3, 5] + 3 * v[0, :, 4, 4] + v[0, :, 4, 5]) / 16
    assert torch.allclose(half[0, :, 4, 4], want, atol=1e-6)
    far, _ = glimpse(v, torch.tensor([[100.0, 100.0], [-50.0, 3.0]]), 0.5)
    assert float(far.abs().max()) == 0.0  # outside the image: zeros
    c = with_coords(v)
    assert c.shape == (2, 6, 8, 8) and torch.equal(c[:, :4], v)
    assert c[0, 4, 0].tolist() == pytest.approx([(2 * u + 1) / 8 - 1 for u in range(8)])
    assert c[1, 5, :, 2].tolist() == pytest.approx([(2 * r + 1) / 8 - 1 for r in range(8)])


def test_centre_pixels_is_the_projection():
    """A centre on the optical axis projects to the principal point; one a unit to the side at depth 4
    lands fx / 4 pixels off it (camera at the world origin looking along +z)."""
    K = torch.tensor([[[40.0, 0.0, 31.5], [0.0, 40.0, 31.5], [0.0, 0.0, 1.0]]])
    T = torch.eye(4)[None]
    uv = centre_pixels(torch.tensor([[[0.0, 0.0, 4.0], [1.0, -2.0, 4.0]]]), K, T)
    assert uv[0].flatten().tolist() == pytest.approx([31.5, 31.5, 41.5, 11.5])


@pytest.mark.parametrize("fields", [{"refiner_coords": True}, {"refiner_glimpse": 0.5, "refiner_coords": True},
                                    {"refiner_coords": True, "refiner_shape": True}, {"refiner_keep": True}])
def test_fresh_refiner_with_coords_or_glimpse_is_the_identity(shipped, fields):
    from dataclasses import replace

    from prismonet.model.prismonet import PriSMONet

    model, b, _ = shipped
    new = PriSMONet(replace(model.cfg, refine_passes=1, **fields), prior=model.prior)
    own = {k: v for k, v in new.state_dict().items() if k.startswith("refiner.")}
    new.load_state_dict({**{k: v for k, v in model.state_dict().items() if not k.startswith("refiner.")}, **own})
    new.eval()
    with torch.no_grad():
        r = new(b.rgb, b.K, b.T_world_cam, b.ground_z, recolor=False)  # the refiner alone (the shipped model's colour step off)
        plain = new(b.rgb, b.K, b.T_world_cam, b.ground_z, refine=False)
    assert torch.allclose(r.latents.params.position, plain.latents.params.position, atol=1e-6)
    assert torch.equal(r.latents.params.z_sh, plain.latents.params.z_sh)
    assert torch.allclose(r.composite.image, plain.composite.image, atol=1e-5)
    assert r.latents.params.active is None or bool(r.latents.params.active.all())
    assert new.refiner.trunk[0].in_channels == IN_CHANNELS + (2 if new.cfg.refiner_coords else 0)
    extra = (new.sh_dim if new.cfg.refiner_shape else 0) + (1 if new.cfg.refiner_keep else 0)
    assert new.refiner.head[-1].out_features == 5 + model.cfg.tex_dim + extra


def test_refiner_glimpse_out_of_range():
    from prismonet.model.config import ModelConfig

    with pytest.raises(ValueError, match="refiner_glimpse"):
        ModelConfig(refiner_glimpse=1.5)


def test_fresh_refiner_is_the_identity(shipped):
    from prismonet.model.refiner_fit import with_refiner

    model, b, _ = shipped
    ref = with_refiner(model).eval()
    assert ref.cfg.refine_passes == 1
    with torch.no_grad():
        r = ref(b.rgb, b.K, b.T_world_cam, b.ground_z, recolor=False)  # the refiner alone (the shipped model's colour step off)
        plain = ref(b.rgb, b.K, b.T_world_cam, b.ground_z, refine=False)
        out = model(b.rgb, b.K, b.T_world_cam, b.ground_z, refine=False)
    for name in ("position", "scale", "cos_sin", "z_tex", "z_sh"):
        assert torch.allclose(getattr(r.latents.params, name), getattr(out.latents.params, name), atol=1e-6)
        assert torch.equal(getattr(plain.latents.params, name), getattr(out.latents.params, name))
    assert torch.allclose(r.composite.image, out.composite.image, atol=1e-5)


def test_refiner_turn_off_keeps_the_encoders_yaw(shipped):
    """``refiner_turn=False``: a refiner that turns every slot by 0.3 rad moves the positions as before and leaves the yaws."""
    from dataclasses import replace

    from prismonet.model.prismonet import PriSMONet
    from prismonet.model.refiner_fit import with_refiner

    model, b, _ = shipped
    ref = with_refiner(model).eval()
    with torch.no_grad():
        ref.refiner.head[-1].bias[3] = math.atanh(0.3 / MAX_TURN)
        ref.refiner.head[-1].bias[0] = 0.2
    still = PriSMONet(replace(ref.cfg, refiner_turn=False), prior=ref.prior).eval()
    still.load_state_dict(ref.state_dict())
    with torch.no_grad():
        enc = ref(b.rgb, b.K, b.T_world_cam, b.ground_z, refine=False).latents.params
        turned = ref(b.rgb, b.K, b.T_world_cam, b.ground_z, recolor=False).latents.params
        kept = still(b.rgb, b.K, b.T_world_cam, b.ground_z, recolor=False).latents.params
    assert torch.equal(kept.cos_sin, enc.cos_sin)
    angle = torch.atan2(turned.cos_sin[..., 1], turned.cos_sin[..., 0]) - torch.atan2(enc.cos_sin[..., 1], enc.cos_sin[..., 0])
    assert torch.allclose(torch.remainder(angle + math.pi, 2 * math.pi) - math.pi, torch.full_like(angle, 0.3), atol=1e-4)
    assert torch.equal(kept.position, turned.position) and not torch.equal(kept.position, enc.position)


def _shifted_targets(model, ds, folder, count, shift, shape_step: float | None = None, visible=None):
    """Targets ``shift`` away from the model's own slots (a known correction), in ``distill``'s format; with
    ``shape_step`` also shape latents that far from the slots' own in every coordinate; ``visible``: the pixels
    the fit shows of each slot (default 100 each)."""
    from prismonet.checkpoint import save_checkpoint

    b = ds.batch(list(range(count)))
    with torch.no_grad():
        p = model(b.rgb, b.K, b.T_world_cam, b.ground_z, refine=False).latents.params
    folder.mkdir()
    t = {"scale": p.scale, "position": p.position + torch.tensor(shift), "cos_sin": p.cos_sin, "z_tex": p.z_tex,
         "bg_color": torch.zeros(count, 3),
         "visible": torch.full(p.scale.shape, 100.0) if visible is None else torch.tensor(visible, dtype=torch.float32).expand(p.scale.shape)}
    if shape_step is not None:
        t["z_sh"] = p.z_sh + shape_step
    save_checkpoint(folder / "chunk_00000.safetensors", t, {"first": 0})
    (folder / "targets.json").write_text(json.dumps({"count": count, "chunk": 256, "num_slots": model.cfg.num_slots}))


def test_fit_refiner_learns_a_shape_step(clevr3, tmp_path):
    """Shape targets 0.3 from every slot's code: the held-out loss starts at the shape term (D_sh x 0.09) and a
    refiner that corrects shapes takes most of it away; one that does not cannot move it."""
    from prismonet.assets import shipped_samples
    from prismonet.data.dataset import SceneDataset
    from prismonet.model.refiner_fit import RefinerFitConfig, fit_refiner, with_refiner

    model = clevr3[0]
    ds = SceneDataset(shipped_samples(), split="test")
    _shifted_targets(model, ds, tmp_path / "t", 12, [0.0, 0.0, 0.0], shape_step=0.3)
    cfg = RefinerFitConfig(steps=60, batch_size=8, lr=2e-3, holdout=4, checkpoint_every=60)
    torch.manual_seed(0)
    s = fit_refiner(with_refiner(model, refiner_shape=True, refiner_keep=False), ds, tmp_path / "t", tmp_path / "shape", cfg,
                    progress=False)
    start = model.sh_dim * 0.09
    assert s["held_out_start"] == pytest.approx(start, rel=1e-4)
    assert s["held_out_end"] < 0.5 * start
    torch.manual_seed(0)
    plain = fit_refiner(with_refiner(model, refiner_keep=False), ds, tmp_path / "t", tmp_path / "plain", cfg, progress=False)
    assert plain["held_out_end"] > 0.9 * start


def test_fit_refiner_learns_which_slots_to_keep(clevr3, tmp_path):
    """Targets whose fit hides every slot: the refiner learns to drop them (held-out scenes too), so the saved model
    renders nothing; targets that show every slot keep them all."""
    from prismonet.assets import shipped_samples
    from prismonet.data.dataset import SceneDataset
    from prismonet.model.io import load_model
    from prismonet.model.refiner_fit import RefinerFitConfig, fit_refiner, with_refiner

    model = clevr3[0]
    ds = SceneDataset(shipped_samples(), split="test")
    cfg = RefinerFitConfig(steps=40, batch_size=8, lr=2e-3, holdout=4, checkpoint_every=40)
    b = ds.batch(list(range(8, 12)))  # the held-out scenes
    for name, shown in (("hidden", 3.0), ("shown", 100.0)):
        _shifted_targets(model, ds, tmp_path / name, 12, [0.0, 0.0, 0.0], visible=[shown] * model.cfg.num_slots)
        torch.manual_seed(0)
        s = fit_refiner(with_refiner(model, refiner_keep=True), ds, tmp_path / name, tmp_path / f"run_{name}", cfg, progress=False)
        loaded, _ = load_model(tmp_path / f"run_{name}")
        assert loaded.cfg.refiner_keep
        with torch.no_grad():
            out = loaded(b.rgb, b.K, b.T_world_cam, b.ground_z)
        if name == "hidden":
            assert s["held_out_end"] < 0.5 * s["held_out_start"]  # starts at 0.2 x BCE(3, 0) = 0.61
            assert not out.latents.params.active.any() and not out.obj_mask.any()
        else:
            assert out.latents.params.active.all() and out.obj_mask.any()


def test_fit_refiner_learns_a_known_correction_and_resumes(clevr3, tmp_path):
    """Targets 0.2 to the side of every encoder slot: the held-out loss falls from the shift's, the saved
    model loads with its refiner and moves its slots that way; a rerun with more steps resumes."""
    from prismonet.assets import shipped_samples
    from prismonet.data.dataset import SceneDataset
    from prismonet.model.io import load_model
    from prismonet.model.refiner_fit import RefinerFitConfig, fit_refiner, with_refiner

    model = clevr3[0]
    ds = SceneDataset(shipped_samples(), split="test")
    _shifted_targets(model, ds, tmp_path / "t", 12, [0.2, 0.0, 0.0])
    cfg = RefinerFitConfig(steps=30, batch_size=8, lr=2e-3, holdout=4, checkpoint_every=30)
    s = fit_refiner(with_refiner(model, refiner_keep=False), ds, tmp_path / "t", tmp_path / "run", cfg, progress=False)
    assert s["held_out_start"] == pytest.approx(0.2, abs=1e-4)  # position L1 of the shift, nothing else
    more = fit_refiner(with_refiner(model, refiner_keep=False), ds, tmp_path / "t", tmp_path / "run",
                       RefinerFitConfig(**{**cfg.__dict__, "steps": 60}), progress=False)
    rows = [json.loads(line) for line in (tmp_path / "run" / "log.jsonl").read_text().splitlines()]
    assert [r["step"] for r in rows] == [0, 30, 60]  # resumed at 30, not started again
    assert more["held_out_end"] < 0.5 * s["held_out_start"]
    loaded, info = load_model(tmp_path / "run")
    assert loaded.cfg.refine_passes == 1 and info["refiner_fit"]["target_scenes"] == 12
    b = ds.batch([0, 1])
    with torch.no_grad():
        moved = (loaded(b.rgb, b.K, b.T_world_cam, b.ground_z).latents.params.position
                 - loaded(b.rgb, b.K, b.T_world_cam, b.ground_z, refine=False).latents.params.position)
    assert float(moved[..., 0].mean()) > 0.1


def test_fit_refiner_keep_best_saves_the_held_out_minimum(clevr3, tmp_path):
    """Training scenes' targets 0.2 to one side, the held-out scenes' 0.2 to the other: the more the refiner learns, the
    worse it does on the held-out scenes, so with ``keep_best`` the saved refiner is the one it started from (a fresh
    refiner moves no slot), at step 0, while without it the saved refiner moves the slots; a rerun keeps the choice."""
    from prismonet.assets import shipped_samples
    from prismonet.data.dataset import SceneDataset
    from prismonet.model.io import load_model
    from prismonet.model.refiner_fit import RefinerFitConfig, fit_refiner, with_refiner

    model = clevr3[0]
    ds = SceneDataset(shipped_samples(), split="test")
    _shifted_targets(model, ds, tmp_path / "t", 12, [[[0.2, 0.0, 0.0]]] * 8 + [[[-0.2, 0.0, 0.0]]] * 4)
    cfg = RefinerFitConfig(steps=30, batch_size=8, lr=2e-3, holdout=4, checkpoint_every=10, keep_best=True)
    b = ds.batch([0, 1])

    def moved(run) -> float:
        loaded, info = load_model(run)
        with torch.no_grad():
            p = loaded(b.rgb, b.K, b.T_world_cam, b.ground_z).latents.params.position
            q = loaded(b.rgb, b.K, b.T_world_cam, b.ground_z, refine=False).latents.params.position
        return float((p - q)[..., 0].mean()), info["refiner_fit"]

    s = fit_refiner(with_refiner(model, refiner_keep=False), ds, tmp_path / "t", tmp_path / "best", cfg, progress=False)
    assert s["held_out_start"] == pytest.approx(0.2, abs=1e-4) and s["held_out_end"] > s["held_out_start"] + 0.02
    assert s["best_step"] == 0 and s["held_out_best"] == s["held_out_start"]
    shift, record = moved(tmp_path / "best")
    assert shift == 0.0 and record["best"] == {"step": 0, "held_out": s["held_out_start"]}
    last = fit_refiner(with_refiner(model, refiner_keep=False), ds, tmp_path / "t", tmp_path / "last",
                       RefinerFitConfig(**{**cfg.__dict__, "keep_best": False}), progress=False)
    assert last["held_out_end"] > last["held_out_start"] + 0.02 and "best_step" not in last
    assert moved(tmp_path / "last")[0] > 0.05
    again = fit_refiner(with_refiner(model, refiner_keep=False), ds, tmp_path / "t", tmp_path / "best", cfg, progress=False)
    assert again["best_step"] == 0 and moved(tmp_path / "best")[0] == 0.0


def test_best_held_out_keeps_the_lowest_and_resumes(tmp_path):
    from prismonet.model.distill import DistillError
    from prismonet.model.part_fit import BestHeldOut

    lin = torch.nn.Linear(2, 1)
    best = BestHeldOut(tmp_path / "best.safetensors", "p.", {"a": 1}, DistillError)
    kept = None
    for step, loss in [(0, 0.5), (10, 0.4), (20, 0.4), (30, 0.45)]:
        with torch.no_grad():
            lin.weight.fill_(float(step))
        best.offer(step, loss, lin)
        kept = lin.weight.clone() if step == 10 else kept
    assert (best.step, best.loss) == (10, 0.4)  # a tie keeps the earlier
    again = BestHeldOut(tmp_path / "best.safetensors", "p.", {"a": 1}, DistillError)
    assert (again.step, again.loss) == (10, 0.4)
    again.offer(40, 0.42, lin)
    again.restore(lin)
    assert torch.equal(lin.weight, kept)
    with pytest.raises(DistillError, match="other settings"):
        BestHeldOut(tmp_path / "best.safetensors", "p.", {"a": 2}, DistillError)


def test_fit_refiner_rerun_when_finished_makes_no_cache(clevr3, tmp_path, monkeypatch):
    """Rerunning a finished fit (as a resumable script does) takes no step and decodes no scene: it saves the same model
    and returns the logged held-out losses."""
    import prismonet.model.refiner_fit as rf
    from prismonet.assets import shipped_samples
    from prismonet.data.dataset import SceneDataset

    model = clevr3[0]
    ds = SceneDataset(shipped_samples(), split="test")
    _shifted_targets(model, ds, tmp_path / "t", 12, [0.2, 0.0, 0.0])
    cfg = rf.RefinerFitConfig(steps=4, batch_size=8, holdout=4, checkpoint_every=4)
    first = rf.fit_refiner(rf.with_refiner(model, refiner_keep=False), ds, tmp_path / "t", tmp_path / "run", cfg, progress=False)
    saved = (tmp_path / "run" / "model.safetensors").read_bytes()

    def no_cache(*args, **kwargs):
        raise AssertionError("a finished fit decoded its scenes again")

    monkeypatch.setattr(rf, "encoder_cache", no_cache)
    again = rf.fit_refiner(rf.with_refiner(model, refiner_keep=False), ds, tmp_path / "t", tmp_path / "run", cfg, progress=False)
    assert again["steps"] == 4 and again["held_out_end"] == first["held_out_end"]
    assert (tmp_path / "run" / "model.safetensors").read_bytes() == saved


def test_fit_refiner_bad_input(clevr3, tmp_path):
    from prismonet.assets import shipped_samples
    from prismonet.data.dataset import SceneDataset
    from prismonet.model.distill import DistillError
    from prismonet.model.refiner_fit import RefinerFitConfig, fit_refiner, with_refiner

    with pytest.raises(ValueError, match="steps"):
        RefinerFitConfig(steps=0)
    ds = SceneDataset(shipped_samples(), split="test")
    from prismonet.model.io import load_model

    with pytest.raises(DistillError, match="no refiner"):
        fit_refiner(load_model("clevr3_fc")[0], ds, tmp_path, tmp_path / "run")
    _shifted_targets(clevr3[0], ds, tmp_path / "t", 4, [0.0, 0.0, 0.0])
    with pytest.raises(DistillError, match="held out"):
        fit_refiner(with_refiner(clevr3[0]), ds, tmp_path / "t", tmp_path / "run", RefinerFitConfig(holdout=4))
    from prismonet.checkpoint import load_checkpoint, save_checkpoint

    tensors, meta = load_checkpoint(tmp_path / "t" / "chunk_00000.safetensors")
    (tmp_path / "old").mkdir()
    save_checkpoint(tmp_path / "old" / "chunk_00000.safetensors", {k: v for k, v in tensors.items() if k != "visible"}, meta)
    (tmp_path / "old" / "targets.json").write_text((tmp_path / "t" / "targets.json").read_text())
    with pytest.raises(DistillError, match="which slots the fit shows"):
        fit_refiner(with_refiner(clevr3[0], refiner_keep=True), ds, tmp_path / "old", tmp_path / "run")
    with pytest.raises(DistillError, match="no shape latents"):
        fit_refiner(with_refiner(clevr3[0], refiner_shape=True), ds, tmp_path / "t", tmp_path / "run")


@pytest.mark.parametrize("flag,words", [("--shape", "no shape latents"), ("--keep", "which slots the fit shows")])
def test_refiner_command_refuses_targets_without_what_it_learns(shipped, tmp_path, capsys, flag, words):
    """``prismonet refiner --shape`` on targets without shape latents, or ``--keep`` on targets that do not say which
    slots the fit shows: one line, exit status 2, no run folder."""
    from prismonet.assets import shipped_samples
    from prismonet.checkpoint import load_checkpoint, save_checkpoint
    from prismonet.cli import main
    from prismonet.data.dataset import SceneDataset

    ds = SceneDataset(shipped_samples(), split="test")
    _shifted_targets(shipped[0], ds, tmp_path / "t", 12, [0.0, 0.0, 0.0])  # shows every slot, has no shapes
    from prismonet.model.distill_fit import weights_digest
    from prismonet.model.io import load_model

    info = json.loads((tmp_path / "t" / "targets.json").read_text())
    info["model_digest"] = weights_digest(load_model("clevr3_fc")[0])  # the command checks whose targets they are first
    (tmp_path / "t" / "targets.json").write_text(json.dumps(info))
    if flag == "--keep":
        tensors, meta = load_checkpoint(tmp_path / "t" / "chunk_00000.safetensors")
        save_checkpoint(tmp_path / "t" / "chunk_00000.safetensors", {k: v for k, v in tensors.items() if k != "visible"}, meta)
    rc = main(["refiner", "clevr3_fc", str(shipped_samples()), "--split", "test", "--targets", str(tmp_path / "t"),
               "--out", str(tmp_path / "run"), "--holdout", "4", flag])
    lines = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert rc == 2 and len(lines) == 1 and words in lines[0], lines
    assert not (tmp_path / "run").exists()


def test_refiner_corrects_the_chosen_and_the_kept_slots(shipped):
    """With extra encoder steps the choice is among the encoder's slots and the refiner corrects the chosen
    ones; with stopping it corrects the slots kept, the others stay inactive and render nothing."""
    from prismonet.model.select import decode_overcomplete, select_slots
    from prismonet.model.stopping import StopRule

    model, b, _ = shipped
    assert model.cfg.refine_passes >= 1  # the shipped model has a refiner
    with torch.no_grad():
        chosen = decode_overcomplete(model, b, extra=1)
        four = model(b.rgb, b.K, b.T_world_cam, b.ground_z, num_slots=4, refine=False)
        expect = model.refine_slots(select_slots(four, b.rgb, b.depth, 3), b.rgb, b.K, b.T_world_cam, b.ground_z)
        assert torch.equal(chosen.slot_steps, expect.slot_steps)
        assert torch.allclose(chosen.latents.params.position, expect.latents.params.position, atol=1e-6)
        rule = StopRule().bind(b.rgb, b.depth)
        stopped = model(b.rgb, b.K, b.T_world_cam, b.ground_z, num_slots=5, stop=rule)
        plain = model(b.rgb, b.K, b.T_world_cam, b.ground_z, num_slots=5, stop=rule, refine=False)
    active = plain.latents.params.active
    kept = stopped.latents.params.active  # the shipped refiner may drop slots too (``refiner_keep``), never revive one
    assert not (kept & ~active).any() and not active.all()
    assert not stopped.obj_mask[~kept].any()
    assert torch.equal(stopped.latents.params.position[~active], plain.latents.params.position[~active])
    assert not torch.equal(stopped.latents.params.position[kept], plain.latents.params.position[kept])


def test_with_refiner_settings(shipped):
    """Refiner settings carry into the copy (a refiner it had is replaced by a fresh one); other settings may not change."""
    from prismonet.model.refiner_fit import with_refiner

    model = shipped[0]
    g = with_refiner(model, refiner_glimpse=0.5, refiner_coords=True)
    assert g.cfg.refiner_glimpse == 0.5 and g.cfg.refiner_coords and g.cfg.refine_passes == 1
    again = with_refiner(g)
    assert again.cfg.refiner_glimpse == 0.5 and float(again.refiner.head[-1].weight.detach().abs().max()) == 0.0
    for k, v in model.state_dict().items():
        if not k.startswith("refiner."):
            assert torch.equal(g.state_dict()[k], v)
    with pytest.raises(ValueError, match="only refiner settings"):
        with_refiner(model, num_slots=4)


def test_fit_refiner_on_a_shared_encoder_cache(clevr3, tmp_path):
    """A refiner fitted on a precomputed encoder cache learns exactly as one that computes it; a cache that
    holds fewer scenes than the targets is refused."""
    from prismonet.assets import shipped_samples
    from prismonet.data.dataset import SceneDataset
    from prismonet.model.distill import DistillError
    from prismonet.model.refiner_fit import RefinerFitConfig, encoder_cache, fit_refiner, with_refiner

    model = clevr3[0]
    ds = SceneDataset(shipped_samples(), split="test")
    _shifted_targets(model, ds, tmp_path / "t", 12, [0.2, 0.0, 0.0])
    cfg = RefinerFitConfig(steps=10, batch_size=8, lr=2e-3, holdout=4, checkpoint_every=10)
    torch.manual_seed(0)
    a = fit_refiner(with_refiner(model), ds, tmp_path / "t", tmp_path / "a", cfg, progress=False)
    cache = encoder_cache(with_refiner(model), ds, 12, progress=False)
    torch.manual_seed(0)
    b = fit_refiner(with_refiner(model), ds, tmp_path / "t", tmp_path / "b", cfg, progress=False, cache=cache)
    assert b["held_out_end"] == pytest.approx(a["held_out_end"], rel=1e-5)
    short = {k: v[:8] for k, v in cache.items()}
    with pytest.raises(DistillError, match="cache holds 8 scenes"):
        fit_refiner(with_refiner(model), ds, tmp_path / "t", tmp_path / "c", cfg, progress=False, cache=short)


def test_stage2_keep_term_gradient_hand_computed(shipped):
    """In training (stage 2) ``loss.w_keep`` reaches the refiner's keep logit: a fresh refiner outputs +3 for every slot,
    so the gradient of the term alone on the keep output's bias is the mean over scenes of the mean over slots of
    ``sigmoid(3) - shown``; nothing else of the refiner's last layer moves."""
    from prismonet.model.losses import LossConfig, compute_losses
    from prismonet.model.refiner import KEEP_INIT
    from prismonet.model.refiner_fit import with_refiner

    model, b, _ = shipped
    ref = with_refiner(model, refiner_keep=True).train()
    out = ref(b.rgb, b.K, b.T_world_cam, b.ground_z)
    assert out.keep_logit.shape == (4, model.cfg.num_slots)
    assert torch.allclose(out.keep_logit, torch.full_like(out.keep_logit, KEEP_INIT))
    visible = torch.tensor([[100.0, 0.0, 30.0], [0.0, 0.0, 0.0], [25.0, 24.0, 500.0], [100.0, 100.0, 100.0]])
    have = torch.tensor([1.0, 1.0, 1.0, 0.0])
    cfg = LossConfig(use_image=False, use_depth=False, use_ground=False, use_shape=False, w_keep=1.0)
    terms = compute_losses(ref, out, b, cfg, 0, distill=({"visible": visible}, have))
    terms.total.backward()
    shown = (visible >= 25).float()[:3]
    expect = float((torch.sigmoid(torch.tensor(KEEP_INIT)) - shown).mean(1).mean())
    grad = ref.refiner.head[-1].bias.grad
    assert float(grad[-1]) == pytest.approx(expect, rel=1e-5)
    assert float(grad[:-1].abs().max()) == 0.0
    assert float(terms.keep.detach()) == pytest.approx(float(torch.nn.functional.binary_cross_entropy_with_logits(
        torch.full((3, 3), KEEP_INIT), shown)), rel=1e-5)


def test_stage2_keep_term_needs_a_keep_refiner_and_visible_targets(tmp_path):
    """``loss.w_keep`` without a refiner that keeps or drops slots, or without targets, is refused at the config;
    targets that do not say which slots the fit shows are refused before the first step, in one line."""
    from prismonet.assets import shipped_samples
    from prismonet.checkpoint import save_checkpoint
    from prismonet.model.config import ModelConfig
    from prismonet.model.losses import LossConfig
    from prismonet.model.trainer import TrainConfig, TrainingError, train

    keep_model = ModelConfig(refine_passes=1, refiner_keep=True)
    with pytest.raises(ValueError, match="loss.w_keep needs"):
        TrainConfig(loss=LossConfig(w_keep=0.1), distill="t")
    with pytest.raises(ValueError, match="loss.w_keep needs"):
        TrainConfig(loss=LossConfig(w_keep=0.1), model=keep_model)
    with pytest.raises(ValueError, match="w_keep must be non-negative"):
        LossConfig(w_keep=-1.0)
    folder = tmp_path / "t"
    folder.mkdir()
    t = {"scale": torch.full((2, 3), 0.5), "position": torch.zeros(2, 3, 3), "cos_sin": torch.tensor([1.0, 0.0]).expand(2, 3, 2),
         "z_tex": torch.zeros(2, 3, 7), "bg_color": torch.zeros(2, 3)}
    save_checkpoint(folder / "chunk_00000.safetensors", t, {"first": 0})
    (folder / "targets.json").write_text(json.dumps({"count": 2, "chunk": 256, "num_slots": 3}))
    cfg = TrainConfig(data=str(shipped_samples()), split="test", steps=1, model=keep_model,
                      loss=LossConfig(w_keep=0.1), distill=str(folder))
    with pytest.raises(TrainingError, match="nothing to learn from"):
        train(cfg, tmp_path / "run", progress=False)


def test_refiner_runs_on_active_slots_only():
    """An anchored 8-slot model with a (random) keep refiner on shipped 1-8-object scenes: the refiner network sees
    only the active slots' rows, and its corrections are those of a run over every row; inactive slots stay
    inactive and keep their latents."""
    from prismonet.assets import samples_for
    from prismonet.data.dataset import SceneDataset
    from prismonet.model.io import load_model
    from prismonet.model.refiner_fit import with_refiner

    base, _ = load_model("clevr1to8_anchor")
    model = with_refiner(base, refiner_keep=True, refiner_glimpse=0.375, refiner_coords=True).eval()
    torch.manual_seed(0)
    torch.nn.init.normal_(model.refiner.head[-1].weight, std=1e-3)
    b = SceneDataset(samples_for("clevr1to8_anchor"), split="test").batch([0, 1, 2, 3])
    seen = []
    hook = model.refiner.register_forward_hook(lambda m, i, o: seen.append(i[0].shape[0]))
    with torch.no_grad():
        plain = model(b.rgb, b.K, b.T_world_cam, b.ground_z, refine=False)
        out = model(b.rgb, b.K, b.T_world_cam, b.ground_z)
        p = plain.latents.params
        every = model.refiner(*model.refiner_inputs(b.rgb, plain.composite.image, plain.composite.instance, plain.obj_mask,
                                                    p, b.K, b.T_world_cam))
    hook.remove()
    active = p.active
    assert 0 < int(active.sum()) < active.numel()  # the scenes leave some slots empty
    assert seen[0] == int(active.sum())  # the refiner pass ran on the active rows only
    from prismonet.model.refiner import apply_correction

    want = apply_correction(p, every, model.pos_scale, model.cfg.scale_range, keep=True)
    got = out.latents.params
    assert torch.equal(got.active, want.active)
    for name in ("position", "scale", "cos_sin", "z_tex"):
        assert torch.allclose(getattr(got, name), getattr(want, name), atol=1e-5)
        assert torch.equal(getattr(got, name)[~active], getattr(p, name)[~active])


def test_reanchor_fills_empty_slots_and_leaves_the_others():
    """``reanchor_steps``: after refinement, more anchored steps go into empty slots only (at most that many per
    scene); the slots the refiner left active keep their latents exactly; training ignores it; it needs a refiner."""
    from dataclasses import replace

    from prismonet.assets import samples_for
    from prismonet.data.dataset import SceneDataset
    from prismonet.model.config import ModelConfig
    from prismonet.model.io import load_model
    from prismonet.model.prismonet import PriSMONet

    shipped, _ = load_model("clevr1to8_keep")  # ships with reanchor_steps 2: compare with the same weights without
    base = PriSMONet(replace(shipped.cfg, reanchor_steps=0), prior=shipped.prior)
    model = PriSMONet(replace(shipped.cfg, reanchor_steps=2), prior=shipped.prior)
    base.load_state_dict(shipped.state_dict())
    model.load_state_dict(shipped.state_dict())
    model.eval()
    base.eval()
    b = SceneDataset(samples_for("clevr1to8_keep"), split="test").batch(list(range(16)))
    with torch.no_grad():
        before = base(b.rgb, b.K, b.T_world_cam, b.ground_z).latents.params
        after = model(b.rgb, b.K, b.T_world_cam, b.ground_z).latents.params
    old, new = before.active, after.active
    assert bool((new | ~old).all())  # no slot the refiner kept is lost
    added = new & ~old
    assert bool(added.any()) and int(added.sum(1).max()) <= 2
    for name in ("position", "scale", "cos_sin", "z_tex", "z_sh"):
        assert torch.equal(getattr(after, name)[old], getattr(before, name)[old])
    model.train()
    with torch.no_grad():
        trained_way = model(b.rgb[:2], b.K[:2], b.T_world_cam[:2], b.ground_z[:2]).latents.params.active
        base.train()
        plain = base(b.rgb[:2], b.K[:2], b.T_world_cam[:2], b.ground_z[:2]).latents.params.active
    assert torch.equal(trained_way, plain)
    for bad in ({"reanchor_steps": 1}, {"reanchor_steps": 1, "anchor": True}, {"reanchor_steps": -1, "anchor": True, "refine_passes": 1}):
        with pytest.raises(ValueError, match="reanchor_steps"):
            ModelConfig(**bad)


def test_reanchor_on_an_unanchored_model_takes_plain_steps_into_empty_slots():
    """An unanchored model's ``reanchor_steps`` are its plain recurrent step on the refined composition: a new slot
    goes only into a slot its keep output dropped, one per step at most, and every slot the
    refiner kept keeps its pose and shape exactly (the colour step then recolours every slot against the new
    composition, so texture latents may move)."""
    from dataclasses import replace

    from prismonet.assets import samples_for
    from prismonet.data.dataset import SceneDataset
    from prismonet.model.io import load_model
    from prismonet.model.prismonet import PriSMONet

    shipped, _ = load_model("clevr5")  # the default decoded with 5 slots: unanchored, a keep refiner
    assert not shipped.cfg.anchor and shipped.cfg.refiner_keep
    models = []
    for steps in (0, 1):
        m = PriSMONet(replace(shipped.cfg, reanchor_steps=steps), prior=shipped.prior)
        m.load_state_dict(shipped.state_dict())
        models.append(m.eval())
    b = SceneDataset(samples_for("clevr5"), split="test").batch(list(range(16)))
    with torch.no_grad():
        before, after = (m(b.rgb, b.K, b.T_world_cam, b.ground_z).latents.params for m in models)
    old, new = before.active, after.active
    assert bool((new | ~old).all())  # nothing the refiner kept is lost
    added = new & ~old
    room = ~old.all(1)
    assert bool(added.any()) and int(added.sum(1).max()) == 1
    assert not bool(added[~room].any())  # a scene whose slots are all kept takes no step
    for name in ("position", "scale", "cos_sin", "z_sh"):
        assert torch.equal(getattr(after, name)[old], getattr(before, name)[old])


def test_steps_after_refinement_render_only_the_slots_they_change():
    """The steps after refinement and the refiner's passes on their new slots render those slots alone and keep every
    other slot's render (``PriSMONet._render_changed``): the result is the render of every slot, its hits included."""
    from prismonet.assets import samples_for
    from prismonet.data.dataset import SceneDataset
    from prismonet.model.io import load_model
    from prismonet.render import render_objects

    model, _ = load_model("clevr5")
    assert model.cfg.reanchor_steps and not model.cfg.anchor
    b = SceneDataset(samples_for("clevr5"), split="test").batch(list(range(16)))
    with torch.no_grad():
        out = model(b.rgb, b.K, b.T_world_cam, b.ground_z)
        full = render_objects(model.sdf_fn, model.color_fn, out.latents.params, b.K, b.T_world_cam, 64, 64,
                              model.render_settings())
    assert bool(out.latents.params.active.any(1).all())
    assert torch.equal(out.obj_mask, full.mask) and torch.equal(out.obj_depth, full.depth)
    assert torch.allclose(out.obj_color, full.color, atol=1e-5)
    key = lambda r: torch.sort(r.hit_slot * 64 * 64 + r.hit_pix).values
    assert torch.equal(key(out.render), key(full))


def test_reanchor_keep_bar_keeps_more_new_slots_only():
    """``reanchor_keep_logit``: a lower bar for the re-anchored slots keeps a superset of them (``None``: every one),
    and never changes the encoder's own slots, their activity or their latents."""
    from dataclasses import replace

    from prismonet.assets import samples_for
    from prismonet.data.dataset import SceneDataset
    from prismonet.model.config import ModelConfig
    from prismonet.model.io import load_model
    from prismonet.model.prismonet import PriSMONet

    shipped, _ = load_model("clevr1to8_keep")
    b = SceneDataset(samples_for("clevr1to8_keep"), split="test").batch(list(range(16)))
    got = {}
    for bar in (0.0, -4.0, None, "off"):
        cfg = replace(shipped.cfg, reanchor_steps=0) if bar == "off" else replace(shipped.cfg, reanchor_steps=2, reanchor_keep_logit=bar)
        m = PriSMONet(cfg, prior=shipped.prior)
        m.load_state_dict(shipped.state_dict())
        with torch.no_grad():
            # the colour step off: it reads the whole composite, so the other slots' colours would move with the bar
            got[bar] = m.eval()(b.rgb, b.K, b.T_world_cam, b.ground_z, recolor=False).latents.params
    own = got["off"].active
    for bar in (0.0, -4.0, None):
        assert torch.equal(got[bar].active & own, own)
        for name in ("position", "scale", "z_tex"):
            assert torch.equal(getattr(got[bar], name)[own], getattr(got["off"], name)[own])
    new = {bar: got[bar].active & ~own for bar in (0.0, -4.0, None)}
    assert bool((new[-4.0] | ~new[0.0]).all()) and bool((new[None] | ~new[-4.0]).all())  # supersets
    assert int(new[None].sum()) > int(new[0.0].sum())  # the bar matters on these scenes
    with pytest.raises(ValueError, match="reanchor_keep_logit"):
        ModelConfig(reanchor_keep_logit=float("-inf"))


def test_keep_passes_drop_in_the_first_passes_only():
    """``refiner_keep_passes``: with two passes and the keep output in the first only, the slots kept are exactly those
    one pass keeps, and the second pass moves them as it does with both passes dropping (the shipped 1-8 model's second
    pass drops a slot on these scenes, so the field matters here); re-anchored slots' passes follow the same rule; bad
    values refused."""
    from dataclasses import replace

    from prismonet.assets import samples_for
    from prismonet.data.dataset import SceneDataset
    from prismonet.model.config import ModelConfig
    from prismonet.model.io import load_model
    from prismonet.model.prismonet import PriSMONet

    shipped, _ = load_model("clevr1to8_keep")
    b = SceneDataset(samples_for("clevr1to8_keep"), split="test").batch(list(range(16)))
    got, bars = {}, {}
    for passes, keep_passes, reanchor in ((1, None, 0), (2, None, 0), (2, 1, 0), (3, 2, 2)):
        cfg = replace(shipped.cfg, refine_passes=passes, refiner_keep_passes=keep_passes, reanchor_steps=reanchor)
        m = PriSMONet(cfg, prior=shipped.prior)
        m.load_state_dict(shipped.state_dict())
        seen = bars.setdefault((passes, keep_passes), [])
        plain = m._refine_pass
        m._refine_pass = lambda *a, **kw: (seen.append((kw.get("only") is not None, kw["keep_above"])), plain(*a, **kw))[1]
        with torch.no_grad():
            got[passes, keep_passes] = m.eval()(b.rgb, b.K, b.T_world_cam, b.ground_z, recolor=False).latents.params
    one, both, first = got[1, None], got[2, None], got[2, 1]
    assert torch.equal(first.active, one.active) and int(both.active.sum()) < int(first.active.sum())
    assert torch.equal(first.position, both.position) and torch.equal(first.scale, both.scale)
    bar, re_bar = shipped.cfg.refiner_keep_logit, shipped.cfg.reanchor_keep_logit
    assert bars[2, 1] == [(False, bar), (False, None)]
    assert bars[3, 2] == [(False, bar), (False, bar), (False, None), (True, re_bar), (True, re_bar), (True, None)]
    for fields in ({"refiner_keep_passes": 0, "refine_passes": 2, "refiner_keep": True},
                   {"refiner_keep_passes": 1, "refine_passes": 2}):
        with pytest.raises(ValueError, match="refiner_keep_passes must be >= 1"):
            ModelConfig(**fields)


def test_reanchor_cache_and_term_on_the_re_anchored_slots_only():
    """``refiner_fit.reanchor_cache``: the slots it marks as subjects are those the re-anchoring put into slots the
    refined decoding left empty, and the others keep the refined latents exactly; ``subjects_term``: with targets equal to the
    corrected re-anchored slots, the term is the keep logits' cross-entropy alone (by hand), targets of the other slots
    do not move it, and a shifted target of a shown re-anchored slot adds its L1 distance."""
    from dataclasses import replace

    from prismonet.assets import samples_for
    from prismonet.data.dataset import SceneDataset
    from prismonet.model.distill import MIN_VISIBLE, VISIBLE, DistillWeights
    from prismonet.model.io import load_model
    from prismonet.model.prismonet import PriSMONet
    from prismonet.model.refiner import split_keep
    from prismonet.model.refiner_fit import KEEP_WEIGHT, cached_refiner_inputs, reanchor_cache, subjects_term
    from prismonet.render import SceneParams

    shipped, _ = load_model("clevr1to8_keep")
    m = PriSMONet(replace(shipped.cfg, reanchor_keep_logit=None), prior=shipped.prior)
    m.load_state_dict(shipped.state_dict())
    ds = SceneDataset(samples_for("clevr1to8_keep"), split="test")
    rc = reanchor_cache(m.eval(), ds, 16, batch_size=16, progress=False)
    b = ds.batch(list(range(16)))
    with torch.no_grad():
        refined = m.refine_slots(m(b.rgb, b.K, b.T_world_cam, b.ground_z, refine=False), b.rgb, b.K, b.T_world_cam, b.ground_z)
    before = refined.latents.params
    added = rc["subjects"]
    assert bool(added.any()) and not bool((added & before.active).any())
    assert torch.equal(rc["position"][~added], before.position[~added])
    fields = ("z_sh", "z_tex", "position", "cos_sin", "scale")
    params = SceneParams(*(rc[k] for k in fields))
    with torch.no_grad():
        delta, keep = split_keep(m.refiner(*cached_refiner_inputs(m, rc, ds, torch.arange(16), params)), True)
    from prismonet.model.refiner import apply_correction

    new = apply_correction(params, delta, m.pos_scale, m.cfg.scale_range)
    visible = torch.where(added, torch.tensor(40.0), torch.tensor(0.0))
    visible[added.nonzero()[0, 0], added.nonzero()[0, 1]] = MIN_VISIBLE - 1  # one re-anchored slot hidden: a drop target

    class Targets:  # DistillTargets' lookup, in memory
        def __init__(self, t):
            self.t = t

        def lookup(self, idx):
            return {k: v[idx] for k, v in self.t.items()}, torch.ones(len(idx))

    t = {"scale": new.scale.clone(), "position": new.position.clone(), "cos_sin": new.cos_sin.clone(), "z_tex": new.z_tex.clone(),
         "bg_color": torch.zeros(16, 3), VISIBLE: visible}
    w = DistillWeights(background=0.0, texture=0.1)
    idx = torch.arange(16)
    with torch.no_grad():
        got = float(subjects_term(m, rc, ds, Targets(t), idx, w))
        shown = (visible >= MIN_VISIBLE).float()
        bce = torch.nn.functional.binary_cross_entropy_with_logits(keep.reshape(16, -1), shown, reduction="none")
        rows = added.any(1)
        want = float((KEEP_WEIGHT * (bce * added).sum(1)[rows] / added.sum(1)[rows]).mean())
        assert got == pytest.approx(want, rel=1e-5, abs=1e-6)
        t_other = {**t, "position": torch.where(added[..., None], t["position"], t["position"] + 5.0)}
        assert float(subjects_term(m, rc, ds, Targets(t_other), idx, w)) == pytest.approx(got, rel=1e-6)
        s_, k_ = [int(v) for v in (added & (visible >= MIN_VISIBLE)).nonzero()[0]]
        t_moved = {**t, "position": t["position"].clone()}
        t_moved["position"][s_, k_, 0] += 0.3
        shown_here = float((added[s_] & (visible[s_] >= MIN_VISIBLE)).sum())
        extra = 0.3 / shown_here / int(rows.sum())
        assert float(subjects_term(m, rc, ds, Targets(t_moved), idx, w)) == pytest.approx(got + extra, rel=1e-4)
        # beside it, the encoder's rows: a slot the encoder left empty is not a target of the whole model's
        from prismonet.model.refiner_fit import _loss, encoder_cache

        cache = encoder_cache(m, ds, 16, batch_size=16, progress=False)
        every = {**t, VISIBLE: torch.full_like(visible, 40.0)}
        masked = {**t, VISIBLE: torch.where(cache["active"], every[VISIBLE], torch.zeros_like(visible))}
        none_added = {**rc, "subjects": torch.zeros_like(added)}
        assert not bool(cache["active"].all())
        a = float(_loss(m, cache, ds, Targets(every), idx, w, later=((none_added, 1.0, True),)))
        assert a == pytest.approx(float(_loss(m, cache, ds, Targets(masked), idx, w)), rel=1e-6)
        assert a != pytest.approx(float(_loss(m, cache, ds, Targets(every), idx, w)), rel=1e-3)


def test_second_pass_cache_is_what_the_second_pass_sees():
    """``refiner_fit.second_pass_cache``: the slots it marks as subjects are those active after the first pass, and the
    refiner's correction of them from the cached inputs (the composite kept in float16) gives the model's own two-pass
    output (``refine_slots``) within 1e-3; a one-pass refiner is refused."""
    from dataclasses import replace

    from prismonet.assets import samples_for
    from prismonet.data.dataset import SceneDataset
    from prismonet.model.distill import DistillError
    from prismonet.model.io import load_model
    from prismonet.model.prismonet import PriSMONet
    from prismonet.model.refiner import apply_correction
    from prismonet.model.refiner_fit import cached_refiner_inputs, second_pass_cache
    from prismonet.render import SceneParams

    shipped, _ = load_model("clevr1to8_keep")
    ds = SceneDataset(samples_for("clevr1to8_keep"), split="test")
    sc = second_pass_cache(shipped.eval(), ds, 16, batch_size=16, progress=False)
    b = ds.batch(list(range(16)))
    with torch.no_grad():
        raw = shipped(b.rgb, b.K, b.T_world_cam, b.ground_z, refine=False)
        first = shipped.refine_pass(raw, b.rgb, b.K, b.T_world_cam, 0)
        both = shipped.refine_slots(raw, b.rgb, b.K, b.T_world_cam, b.ground_z)
        assert torch.equal(sc["subjects"], first.latents.params.active)
        assert bool((~sc["subjects"] & raw.latents.params.active).any())  # the first pass dropped some
        params = SceneParams(*(sc[k] for k in ("z_sh", "z_tex", "position", "cos_sin", "scale")), active=sc["subjects"])
        delta = shipped.refiner(*cached_refiner_inputs(shipped, sc, ds, torch.arange(16), params))
        new = apply_correction(params, delta, shipped.pos_scale, shipped.cfg.scale_range, True, shipped.cfg.refiner_keep_logit)
    got, want = both.latents.params, new
    assert torch.equal(got.active, want.active)
    kept = got.active
    assert torch.allclose(got.position[kept], want.position[kept], atol=1e-3)
    assert torch.allclose(got.scale[kept], want.scale[kept], atol=1e-3)
    one = PriSMONet(replace(shipped.cfg, refine_passes=1), prior=shipped.prior)
    with pytest.raises(DistillError, match="two passes or more"):
        second_pass_cache(one, ds, 16, progress=False)


def test_second_pass_term_without_the_shape_ignores_the_shape_targets():
    """``RefinerFitConfig.second_pass_shape`` ``False``: the second-pass term leaves the shape latent out, so moving
    the targets' shape latents changes the fit's loss by exactly what it changes the encoder rows' term; with the shape
    kept, by more. On the default model (a refiner that corrects shapes) and its sample scenes."""
    from prismonet.assets import samples_for
    from prismonet.data.dataset import SceneDataset
    from prismonet.model.distill import SHAPE, VISIBLE, DistillWeights
    from prismonet.model.io import load_model
    from prismonet.model.refiner_fit import _loss, encoder_cache, second_pass_cache

    m, _ = load_model("shipped")
    assert m.cfg.refiner_shape and m.cfg.refine_passes == 2
    ds = SceneDataset(samples_for("shipped"), split="test")
    n = 8
    cache = encoder_cache(m.eval(), ds, n, batch_size=n, progress=False)
    sc = second_pass_cache(m, ds, n, batch_size=n, progress=False)

    class Targets:  # DistillTargets' lookup, in memory
        def __init__(self, t):
            self.t = t

        def lookup(self, idx):
            return {k: v[idx] for k, v in self.t.items()}, torch.ones(len(idx))

    t = {k: cache[k].float().clone() for k in ("scale", "position", "cos_sin", "z_tex", "z_sh")}
    t.update(bg_color=torch.zeros(n, 3), **{VISIBLE: torch.full_like(t["scale"], 40.0)})
    moved = {**t, SHAPE: t[SHAPE] + 0.2}
    w, idx = DistillWeights(background=0.0, texture=0.1), torch.arange(n)
    with torch.no_grad():
        def change(later):
            return float(_loss(m, cache, ds, Targets(moved), idx, w, later=later)) - float(_loss(m, cache, ds, Targets(t), idx, w, later=later))

        main = change(())
        assert main > 0.01
        assert change(((sc, 1.0, False),)) == pytest.approx(main, rel=1e-4, abs=1e-6)
        assert change(((sc, 1.0, True),)) > main + 0.01


def test_set_refine_passes_refuses_bad_settings_with_one_line(tmp_path):
    """``scripts/set_refine_passes.py`` with a setting the model cannot take (a negative ``--reanchor``, anchor
    settings on a model without anchors, ...): one line, exit status non-zero, nothing written."""
    import subprocess
    import sys
    from pathlib import Path

    script = Path(__file__).resolve().parents[1] / "scripts" / "set_refine_passes.py"
    r = subprocess.run([sys.executable, str(script), "clevr3", "2", str(tmp_path / "out"), "--reanchor", "-1"],
                       capture_output=True, text=True)
    assert r.returncode != 0 and "--reanchor needs N >= 0" in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1 and not (tmp_path / "out").exists()
    for name, extra, says in (("clevr3", ["--anchor-shade", "0.5"], "--anchor-shade needs an anchored model"),
                              ("tabletop_keep", ["--anchor-shade", "1.5"], "anchor_shade_min must be in"),
                              ("tabletop_keep", ["--reanchor-keep", "x"], "--reanchor-keep: expected a number"),
                              ("clevr3_glimpse", ["--keep-logit", "1"], "--keep-logit needs a refiner with a keep output"),
                              ("clevr3_glimpse", ["--rescue", "10"], "--rescue needs a refiner with a keep output"),
                              ("cars_keep", ["--rescue", "-1"], "refiner_rescue_px must be >= 0"),
                              ("clevr3_glimpse", ["--anchor-color", "0.2"], "--anchor-color needs an anchored model"),
                              ("tabletop_keep", ["--anchor-color", "0"], "anchor_color_tol > 0"),
                              ("cars_keep", ["--keep-passes", "0"], "refiner_keep_passes must be >= 1"),
                              ("cars_keep", ["--keep-passes", "1.5"], "--keep-passes: expected a whole number"),
                              ("clevr3_glimpse", ["--keep-passes", "1"], "needs refiner_keep")):
        r = subprocess.run([sys.executable, str(script), name, "2", str(tmp_path / "out"), *extra], capture_output=True, text=True)
        assert r.returncode != 0 and says in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
        assert not (tmp_path / "out").exists()


def test_set_refine_passes_anchor_color_writes_the_tolerance_and_the_same_weights(tmp_path):
    """``--anchor-color T`` writes a copy whose ``anchor_color_tol`` is T, with the source's weights and the change
    recorded."""
    import subprocess
    import sys
    from dataclasses import replace

    from prismonet.model.io import load_model

    script = Path(__file__).resolve().parents[1] / "scripts" / "set_refine_passes.py"
    r = subprocess.run([sys.executable, str(script), "clevr1to8_keep", "2", str(tmp_path / "out"), "--anchor-color", "0.2"],
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    src, new = load_model("clevr1to8_keep")[0], load_model(str(tmp_path / "out"))[0]
    assert new.cfg.anchor_color_tol == 0.2 and src.cfg.anchor_color_tol == 0.25
    assert replace(new.cfg, anchor_color_tol=0.25) == src.cfg
    assert all(torch.equal(a, b) for a, b in zip(src.state_dict().values(), new.state_dict().values()))
    record = json.loads((tmp_path / "out" / "model.json").read_text())
    assert record["refine_passes_from"]["anchor_color_tol"] == 0.25


def test_color_term_hand_computed():
    """``refiner_fit.color_term`` with a colour function whose answer is known (the first three latent entries plus
    the point's x): the squared RGB difference, averaged over points, over the slots the fit shows, then over the
    scenes with targets; no gradient reaches the targets."""
    from prismonet.model.refiner_fit import color_points, color_term

    color_fn = lambda z, x: z[..., :3] + x[..., :1]  # the point's part cancels in the difference
    z = torch.zeros(2, 2, 4, requires_grad=True)
    zt = torch.zeros(2, 2, 4)
    zt[0, 0, :3] = torch.tensor([1.0, 2.0, 0.0])  # shown: 5
    zt[0, 1, 0] = 3.0                             # shown: 9
    zt[1, 0, 0] = 7.0                             # hidden: not counted
    zt[1, 1, 3] = 5.0                             # shown, but the fourth entry is no colour: 0
    targets = {"visible": torch.tensor([[30.0, 25.0], [3.0, 40.0]])}
    got = color_term(color_fn, z, zt, targets, torch.ones(2), color_points())
    assert torch.isclose(got, torch.tensor((5 + 9) / 2 / 2 + 0.0 / 2))
    only_first = color_term(color_fn, z, zt, targets, torch.tensor([1.0, 0.0]), color_points())
    assert torch.isclose(only_first, torch.tensor(7.0))
    got.backward()
    assert z.grad[0, 0, :3].tolist() == pytest.approx([-0.5, -1.0, 0.0]) and float(z.grad[1].abs().sum()) == 0.0
    assert color_points().shape == (64, 3) and torch.equal(color_points(), color_points())


def test_refiner_fit_refuses_a_negative_color_weight():
    from prismonet.model.refiner_fit import RefinerFitConfig

    with pytest.raises(ValueError, match="color must be >= 0"):
        RefinerFitConfig(color=-1.0)


def test_fit_refiner_with_the_color_term(clevr3, tmp_path):
    """``RefinerFitConfig.color``: targets whose texture latents are the encoder's own start the colour term at 0 (the
    held-out loss is the shift's alone); targets with other texture latents add it; the run records the weight, and a
    run without it records none (so runs made before it resume)."""
    from prismonet.assets import shipped_samples
    from prismonet.checkpoint import load_checkpoint, save_checkpoint
    from prismonet.data.dataset import SceneDataset
    from prismonet.model.io import load_model
    from prismonet.model.refiner_fit import RefinerFitConfig, fit_refiner, with_refiner

    model = clevr3[0]
    ds = SceneDataset(shipped_samples(), split="test")
    _shifted_targets(model, ds, tmp_path / "t", 12, [0.2, 0.0, 0.0])
    cfg = RefinerFitConfig(steps=2, batch_size=4, holdout=4, checkpoint_every=2, color=1.0)
    s = fit_refiner(with_refiner(model, refiner_keep=False), ds, tmp_path / "t", tmp_path / "run", cfg, progress=False)
    assert s["held_out_start"] == pytest.approx(0.2, abs=1e-4)
    assert load_model(tmp_path / "run")[1]["refiner_fit"]["fit"]["color"] == 1.0
    tensors, meta = load_checkpoint(tmp_path / "t" / "chunk_00000.safetensors")
    (tmp_path / "t2").mkdir()
    save_checkpoint(tmp_path / "t2" / "chunk_00000.safetensors", {**tensors, "z_tex": tensors["z_tex"] + 0.5}, meta)
    (tmp_path / "t2" / "targets.json").write_text((tmp_path / "t" / "targets.json").read_text())
    start = {}
    for w in (0.0, 1.0):
        c = RefinerFitConfig(steps=1, batch_size=4, holdout=4, checkpoint_every=1, color=w)
        start[w] = fit_refiner(with_refiner(model, refiner_keep=False), ds, tmp_path / "t2", tmp_path / f"run{w}", c, progress=False)["held_out_start"]
    assert start[1.0] > start[0.0] + 1e-4
    assert "color" not in load_model(tmp_path / "run0.0")[1]["refiner_fit"]["fit"]


SCRIPTS = Path(__file__).resolve().parents[1] / "scripts"


def test_encoder_only_decodes_as_the_model_unrefined(shipped, tmp_path, script):
    """``scripts/encoder_only.py``: the shipped model (a refiner and a colour step) without both decodes exactly as the
    model with ``refine=False``, and saved, it loads as a model of its own; a model with neither is refused in one line,
    nothing written."""
    import subprocess
    import sys

    from prismonet.model.io import load_model

    scripts = SCRIPTS
    encoder_only = script("encoder_only").encoder_only
    model, b, _ = shipped
    assert model.cfg.refine_passes and model.cfg.color_step  # what the check needs
    enc = encoder_only(model).eval()
    assert enc.cfg.refine_passes == 0 and not enc.cfg.color_step
    assert not any(k.startswith(("refiner.", "color_step.")) for k in enc.state_dict())
    with torch.no_grad():
        a = enc(b.rgb, b.K, b.T_world_cam, b.ground_z)
        ref = model(b.rgb, b.K, b.T_world_cam, b.ground_z, refine=False)
    for name in ("position", "scale", "cos_sin", "z_tex", "z_sh"):
        assert torch.equal(getattr(a.latents.params, name), getattr(ref.latents.params, name))
    assert torch.equal(a.composite.image, ref.composite.image)
    r = subprocess.run([sys.executable, str(scripts / "encoder_only.py"), "shipped", str(tmp_path / "enc")],
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    loaded, info = load_model(tmp_path / "enc")
    assert info["encoder_of"] == "shipped" and loaded.cfg.refine_passes == 0
    assert all(torch.equal(v, enc.state_dict()[k]) for k, v in loaded.state_dict().items())
    r = subprocess.run([sys.executable, str(scripts / "encoder_only.py"), str(tmp_path / "enc"), str(tmp_path / "again")],
                       capture_output=True, text=True)
    assert r.returncode != 0 and "it is an encoder already" in r.stderr and len(r.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "again").exists()


def test_swap_weights_takes_the_sources_parts_and_keeps_the_rest(shipped, tmp_path, script):
    """``scripts/swap_weights.py``: a model's encoder replaced by another's (here the shipped encoder, nudged), its
    refiner and colour step kept; a source with a part the model lacks is refused before anything changes."""
    import copy
    import subprocess
    import sys

    from prismonet.model.io import load_model, save_model

    scripts = SCRIPTS
    encoder_only, swap_weights = script("encoder_only").encoder_only, script("swap_weights").swap_weights
    model, _, _ = shipped
    enc = copy.deepcopy(encoder_only(model))
    with torch.no_grad():
        for p in enc.encoder.parameters():
            p.add_(0.01)
    target = copy.deepcopy(model)
    names = swap_weights(target, enc)
    assert set(names) == set(enc.state_dict()) and not any(n.startswith(("refiner.", "color_step.")) for n in names)
    after = target.state_dict()
    for k, v in model.state_dict().items():
        if k.startswith("encoder."):
            assert torch.equal(after[k], v + 0.01)
        else:
            assert torch.equal(after[k], v), k  # refiner, colour step, background encoder, texture field: the model's
    before = {k: v.clone() for k, v in enc.state_dict().items()}
    with pytest.raises(ValueError, match="the model has no weight 'refiner"):
        swap_weights(enc, model)
    assert all(torch.equal(v, before[k]) for k, v in enc.state_dict().items())
    save_model(enc, tmp_path / "enc" / "model", {})
    r = subprocess.run([sys.executable, str(scripts / "swap_weights.py"), "shipped", str(tmp_path / "enc"), str(tmp_path / "out")],
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    loaded, info = load_model(tmp_path / "out")
    assert "weights_from" in info and loaded.cfg == model.cfg
    assert all(torch.equal(v, after[k]) for k, v in loaded.state_dict().items())
    r = subprocess.run([sys.executable, str(scripts / "swap_weights.py"), str(tmp_path / "enc"), "shipped", str(tmp_path / "bad")],
                       capture_output=True, text=True)
    assert r.returncode != 0 and "swap_weights: error: the model has no weight" in r.stderr and not (tmp_path / "bad").exists()


def test_refiner_command_targets_from_another_model(shipped, tmp_path, capsys):
    """Targets made by one model, a refiner fitted on another's encoder (one fine-tuned on them): refused in one line
    that names ``--targets-from``, and accepted with ``--targets-from`` naming the model that made them (checked
    against that model's weights instead)."""
    from prismonet.assets import shipped_samples
    from prismonet.cli import main
    from prismonet.data.dataset import SceneDataset
    from prismonet.model.distill_fit import weights_digest
    from prismonet.model.io import load_model

    ds = SceneDataset(shipped_samples(), split="test")
    _shifted_targets(shipped[0], ds, tmp_path / "t", 12, [0.0, 0.0, 0.0])
    info = json.loads((tmp_path / "t" / "targets.json").read_text())
    info["model_digest"] = weights_digest(load_model("clevr3_fc")[0])
    (tmp_path / "t" / "targets.json").write_text(json.dumps(info))
    args = ["refiner", "clevr3_60k", str(shipped_samples()), "--split", "test", "--targets", str(tmp_path / "t"),
            "--holdout", "4", "--steps", "2", "--batch", "4", "--quiet"]
    assert main([*args, "--out", str(tmp_path / "no")]) == 2
    lines = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(lines) == 1 and "--targets-from" in lines[0] and not (tmp_path / "no").exists(), lines
    assert main([*args, "--out", str(tmp_path / "wrong"), "--targets-from", "clevr3_60k"]) == 2  # not the maker either
    capsys.readouterr()
    assert main([*args, "--out", str(tmp_path / "run"), "--targets-from", "clevr3_fc"]) == 0
    assert (tmp_path / "run" / "model.safetensors").is_file()


def test_refiner_command_refuses_shape_codes_without_shape_in_one_line(tmp_path, capsys):
    """``prismonet refiner --shape-codes`` without ``--shape``: one line, exit status 2, no run folder left."""
    from prismonet.cli import main

    out = tmp_path / "run"
    assert main(["refiner", "clevr3_fc", str(tmp_path / "data"), "--targets", str(tmp_path / "t"), "--out", str(out),
                 "--shape-codes"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("prismonet: error:") and "refiner --shape" in err[-1] and "Traceback" not in "\n".join(err)
    assert not out.exists()


@pytest.mark.parametrize("model, extra, says", [
    ("clevr1to8_keep", [], "already has a refiner; start from its encoder's model, or --fine-tune it"),
    ("clevr1to8_keep", ["--fine-tune", "--keep"], "--fine-tune trains the model's own refiner"),
    ("clevr1to8_keep", ["--fine-tune", "--reanchored", "-1"], "reanchored must be >= 0"),
    ("clevr1to8_keep", ["--fine-tune", "--second-pass", "-1"], "second_pass must be >= 0"),
    ("shipped", ["--fine-tune", "--shape"], "adds a shape step to a refiner without one: the model has one already"),
])
def test_refiner_command_fine_tune_refusals_in_one_line(model, extra, says, tmp_path, capsys):
    """``prismonet refiner``: a model with a refiner needs ``--fine-tune``, which keeps its refiner settings; a negative
    ``--reanchored`` is refused; one line each, exit status 2, no run folder left."""
    from prismonet.cli import main

    out = tmp_path / "run"
    assert main(["refiner", model, str(tmp_path / "data"), "--targets", str(tmp_path / "t"), "--out", str(out), *extra]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("prismonet: error:") and says in err[-1] and "Traceback" not in "\n".join(err)
    assert not out.exists()


def test_model_variant_refuses_bad_values_in_one_line(script, tmp_path, capsys):
    """``scripts/model_variant.py``: an unknown field and a value ``ModelConfig`` refuses each give one line and exit
    status 2, and no model is written; a good value writes the copy with the field changed."""
    mv = script("model_variant")
    out = tmp_path / "variant"
    for arg, says in (("no_such_field=1", "is not a ModelConfig field"),
                      ("refiner_hold_cells_from=2", "refiner_hold_cells_from must index")):
        assert mv.main(["clevr3_sharp", str(out), arg]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("model_variant: error:") and says in err[0]
        assert not (out / "model.json").exists()
    assert mv.main(["clevr3_sharp", str(out), "refiner_hold_cells_from=1"]) == 0
    assert json.loads((out / "model.json").read_text())["model"]["refiner_hold_cells_from"] == 1
