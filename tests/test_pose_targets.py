"""Distillation targets with the true poses (``prismonet.model.pose_targets``, the + 3D pose variant): the yaw up to a
shape's symmetry and the slot-to-object matching, by hand; ``refiner --true-poses`` fits to them."""

import json
import math

import pytest
import torch

from prismonet.model.pose_targets import nearest_turn, with_true_poses


def test_nearest_turn_hand_computed():
    """A half-turn shape's true yaw 0.1 read near 3.0 is 0.1 + pi; a shape without symmetry keeps its true yaw up to
    whole turns; a round shape keeps the fitted yaw."""
    yaw = torch.tensor([3.0, 6.0, 1.3, -1.4])
    true = torch.tensor([0.1, 0.1, 0.1, 0.0])
    period = torch.tensor([math.pi, 2 * math.pi, 0.0, math.pi / 2])
    got = nearest_turn(yaw, true, period)
    assert torch.allclose(got, torch.tensor([0.1 + math.pi, 0.1 + 2 * math.pi, 1.3, -math.pi / 2]))


def _targets():
    """One scene, three slots: two shown (at x = 1 and y = 1), one hidden."""
    return {"scale": torch.tensor([[0.5, 0.6, 0.7]]),
            "position": torch.tensor([[[1.0, 0.0, 0.5], [0.0, 1.0, 0.5], [3.0, 3.0, 0.5]]]),
            "cos_sin": torch.tensor([[[math.cos(3.0), math.sin(3.0)], [math.cos(1.3), math.sin(1.3)], [1.0, 0.0]]]),
            "z_tex": torch.randn(1, 3, 4), "z_sh": torch.randn(1, 3, 5), "bg_color": torch.rand(1, 3),
            "visible": torch.tensor([[100.0, 40.0, 3.0]])}


def test_true_poses_replace_the_matched_slots_only():
    """Object 0 (round, shape 0) lies near slot 1 and object 1 (half-turn, shape 1) near slot 0, listed the other way
    round: each shown slot takes its object's position and scale; slot 0 the true yaw turned by pi towards its own,
    slot 1 its own yaw (round); the hidden slot, the latents and the background stay as they were."""
    t = _targets()
    pos = torch.tensor([[[0.1, 1.1, 0.4], [0.9, -0.1, 0.45], [0.0, 0.0, 0.0]]])
    new, stats = with_true_poses(t, torch.tensor([2]), torch.tensor([[0, 1, -1]]), pos, torch.tensor([[2.0, 0.1, 0.0]]),
                                 torch.tensor([[0.3, 0.4, 0.0]]), [0.0, math.pi])
    assert torch.equal(new["position"][0, 0], pos[0, 1]) and torch.equal(new["position"][0, 1], pos[0, 0])
    assert torch.allclose(new["scale"], torch.tensor([[0.4, 0.3, 0.7]]))
    yaw = torch.atan2(new["cos_sin"][..., 1], new["cos_sin"][..., 0])
    assert yaw[0, 0] == pytest.approx(0.1 + math.pi - 2 * math.pi, abs=1e-6)  # 0.1 + pi, read back in (-pi, pi]
    assert yaw[0, 1] == pytest.approx(1.3, abs=1e-6)
    for k in ("z_tex", "z_sh", "bg_color", "visible"):
        assert torch.equal(new[k], t[k])
    assert torch.equal(new["position"][0, 2], t["position"][0, 2]) and torch.equal(new["cos_sin"][0, 2], t["cos_sin"][0, 2])
    assert stats == {"slots": 2, "matched": 2, "objects": 2, "filled": 0, "unmatched_objects": 0}
    assert torch.equal(t["position"], _targets()["position"])  # the input is not changed


def test_true_poses_more_objects_than_shown_slots():
    """Three objects, two shown slots: the nearest two are matched; the third goes to the hidden slot, which becomes a
    target (shown at the visibility bar) with that object's pose and its own latents with ``fill_hidden``; by default it
    is left unmatched and the hidden slot as it was."""
    from prismonet.model.distill import MIN_VISIBLE

    t = _targets()
    pos = torch.tensor([[[5.0, 5.0, 0.4], [1.0, 0.1, 0.4], [0.1, 1.0, 0.4]]])
    args = (torch.tensor([3]), torch.tensor([[0, 0, 0]]), pos, torch.zeros(1, 3), torch.tensor([[0.5, 0.6, 0.7]]), [0.0])
    new, stats = with_true_poses(t, *args, fill_hidden=True)
    assert torch.equal(new["position"][0], pos[0, [1, 2, 0]])
    assert torch.allclose(new["scale"][0], torch.tensor([0.6, 0.7, 0.5]))
    assert new["visible"][0].tolist() == [100.0, 40.0, float(MIN_VISIBLE)]
    assert torch.equal(new["z_sh"], t["z_sh"]) and torch.equal(new["cos_sin"][0, 2], t["cos_sin"][0, 2])  # round: its yaw
    assert stats == {"slots": 2, "matched": 2, "objects": 3, "filled": 1, "unmatched_objects": 0}
    kept, stats = with_true_poses(t, *args)  # the default
    assert torch.equal(kept["position"][0, :2], pos[0, 1:]) and torch.equal(kept["position"][0, 2], t["position"][0, 2])
    assert torch.equal(kept["visible"], t["visible"])
    assert stats["filled"] == 0 and stats["unmatched_objects"] == 1


def test_true_poses_bad_input():
    from prismonet.model.refiner_fit import RefinerFitConfig

    with pytest.raises(ValueError, match="fill_hidden needs true_poses"):
        RefinerFitConfig(fill_hidden=True)
    t = _targets()
    with pytest.raises(ValueError, match="shape ids"):
        with_true_poses(t, torch.tensor([1]), torch.tensor([[4, -1, -1]]), torch.zeros(1, 3, 3), torch.zeros(1, 3),
                        torch.ones(1, 3), [0.0])
    with pytest.raises(ValueError, match="which slots"):
        with_true_poses({k: v for k, v in t.items() if k != "visible"}, torch.tensor([1]), torch.zeros(1, 3, dtype=torch.long),
                        torch.zeros(1, 3, 3), torch.zeros(1, 3), torch.ones(1, 3), [0.0])
    with pytest.raises(ValueError, match="true poses for 2"):
        with_true_poses(t, torch.tensor([1, 1]), torch.zeros(2, 3, dtype=torch.long), torch.zeros(2, 3, 3), torch.zeros(2, 3),
                        torch.ones(2, 3), [0.0])


def test_true_poses_need_the_shape_library(tmp_path):
    """Scenes made from an imported library that is not here: the symmetries are unknown, refused in one line."""
    from types import SimpleNamespace

    from prismonet.model.pose_targets import true_poses_for

    ds = SimpleNamespace(path=tmp_path, meta={"config": {"shapes": str(tmp_path / "gone")}})
    with pytest.raises(ValueError, match="shape library is not here") as e:
        true_poses_for(_targets(), ds, 1)
    assert "\n" not in str(e.value)


def test_fit_refiner_to_the_true_poses(clevr3, tmp_path):
    """Targets equal to the encoder's own slots: without the true poses there is nothing to learn (held-out loss 0);
    with them the held-out loss starts at the slots' distance from the true poses (``distill_loss`` against
    ``with_true_poses``'s targets, computed here), and the model's record says how many slots were given the truth."""
    from prismonet.assets import shipped_samples
    from prismonet.checkpoint import save_checkpoint
    from prismonet.data.dataset import SceneDataset
    from prismonet.model.io import load_model
    from prismonet.model.refiner_fit import RefinerFitConfig, fit_refiner, with_refiner

    model = clevr3[0]
    ds = SceneDataset(shipped_samples(), split="test")
    b = ds.batch(list(range(12)))
    with torch.no_grad():
        p = model(b.rgb, b.K, b.T_world_cam, b.ground_z, refine=False).latents.params
    (tmp_path / "t").mkdir()
    save_checkpoint(tmp_path / "t" / "chunk_00000.safetensors",
                    {"scale": p.scale, "position": p.position, "cos_sin": p.cos_sin, "z_tex": p.z_tex, "bg_color": torch.zeros(12, 3),
                     "visible": torch.full(p.scale.shape, 100.0)}, {"first": 0})
    (tmp_path / "t" / "targets.json").write_text(json.dumps({"count": 12, "chunk": 256, "num_slots": model.cfg.num_slots}))
    cfg = RefinerFitConfig(steps=40, batch_size=8, lr=2e-3, holdout=4, checkpoint_every=40)
    torch.manual_seed(0)
    own = fit_refiner(with_refiner(model, refiner_keep=False), ds, tmp_path / "t", tmp_path / "own", cfg, progress=False)
    torch.manual_seed(0)
    true = fit_refiner(with_refiner(model, refiner_keep=False), ds, tmp_path / "t", tmp_path / "true",
                       RefinerFitConfig(**{**cfg.__dict__, "true_poses": True}), progress=False)
    assert own["held_out_start"] == pytest.approx(0.0, abs=1e-6)
    from prismonet.evaluation.evaluate import shape_periods
    from prismonet.model.distill import DistillWeights, distill_loss
    from prismonet.render import SceneParams

    t = {"scale": p.scale, "position": p.position, "cos_sin": p.cos_sin, "z_tex": p.z_tex, "bg_color": torch.zeros(12, 3),
         "visible": torch.full(p.scale.shape, 100.0)}
    periods = shape_periods(ds, range(27), True)
    want, _ = with_true_poses(t, b.obj_count, b.obj_shape, b.obj_position, b.obj_yaw, b.obj_scale, periods)
    held = SceneParams(*(getattr(p, k)[8:] for k in ("z_sh", "z_tex", "position", "cos_sin", "scale")))
    expect = distill_loss(held, torch.zeros(4, 3), {k: v[8:] for k, v in want.items()}, torch.ones(4),
                          DistillWeights(background=0.0, texture=0.1))
    assert expect > 0.02 and true["held_out_start"] == pytest.approx(float(expect), rel=1e-4)
    _, info = load_model(tmp_path / "true")
    stats = info["refiner_fit"]["true_poses"]
    assert stats["slots"] == 12 * model.cfg.num_slots and stats["matched"] == int(b.obj_count.clamp_max(model.cfg.num_slots).sum())
    assert "true_poses" not in load_model(tmp_path / "own")[1]["refiner_fit"]["fit"]  # runs made before the option resume


def _slots():
    """One scene, three active slots at x = 1, y = 1 and (3, 3), yaws 3.0, 1.3 and 0."""
    from prismonet.render import SceneParams

    t = _targets()
    return SceneParams(t["z_sh"], t["z_tex"], t["position"], t["cos_sin"], t["scale"])


def test_posed_at_truth_moves_the_nearest_slots_and_hides_the_rest():
    """Two objects (round near slot 1, half-turn near slot 0): those slots take the objects' positions, scales and yaws
    (the half-turn one turned by pi towards the slot's own 3.0, the round one keeping 1.3); slot 2, which no object
    takes, is made inactive; the latents are the slots' own. With four objects and three slots one is left over."""
    from types import SimpleNamespace

    from prismonet.model.pose_targets import posed_at_truth

    pos = torch.tensor([[[0.1, 1.1, 0.4], [0.9, -0.1, 0.45], [0.0, 0.0, 0.0]]])
    truth = SimpleNamespace(obj_count=torch.tensor([2]), obj_shape=torch.tensor([[0, 1, -1]]), obj_position=pos,
                            obj_yaw=torch.tensor([[2.0, 0.1, 0.0]]), obj_scale=torch.tensor([[0.3, 0.4, 0.0]]))
    p = _slots()
    new, stats = posed_at_truth(p, truth, [0.0, math.pi])
    assert torch.equal(new.position[0, :2], pos[0, [1, 0]]) and torch.allclose(new.scale[0, :2], torch.tensor([0.4, 0.3]))
    yaw = torch.atan2(new.cos_sin[..., 1], new.cos_sin[..., 0])
    assert yaw[0, 0] == pytest.approx(0.1 + math.pi - 2 * math.pi, abs=1e-6)
    assert yaw[0, 1] == pytest.approx(1.3, abs=1e-6)
    assert new.active.tolist() == [[True, True, False]]
    assert torch.equal(new.z_sh, p.z_sh) and torch.equal(new.z_tex, p.z_tex)
    assert stats == {"objects": 2, "matched": 2, "unmatched_objects": 0}
    assert torch.equal(p.position, _targets()["position"])  # the input is not changed
    four = SimpleNamespace(obj_count=torch.tensor([4]), obj_shape=torch.zeros(1, 4, dtype=torch.long),
                           obj_position=torch.rand(1, 4, 3), obj_yaw=torch.zeros(1, 4), obj_scale=torch.ones(1, 4))
    new, stats = posed_at_truth(p, four, [0.0])
    assert new.active.all() and stats == {"objects": 4, "matched": 3, "unmatched_objects": 1}
    with pytest.raises(ValueError, match="shape ids"):
        posed_at_truth(p, SimpleNamespace(**{**vars(truth), "obj_shape": torch.tensor([[5, 1, -1]])}), [0.0, math.pi])


def test_distill_targets_at_the_true_poses(tmp_path):
    """``fit_targets(..., true_poses=True)`` on the shipped scenes: every slot the fit shows sits exactly on a true
    object (position and scale equal, yaw equal up to the shape's period), and no object takes two slots; with pose
    trials left on it is refused in one line."""
    from prismonet.assets import shipped_samples
    from prismonet.data.dataset import SceneDataset
    from prismonet.model.color_fit import ColorFitConfig
    from prismonet.model.distill import DistillError, DistillTargets
    from prismonet.model.distill_fit import fit_targets, true_pose_search
    from prismonet.model.inference import InferenceConfig
    from prismonet.model.io import load_model
    from prismonet.model.pose_targets import yaw_periods_of
    from prismonet.model.search import SearchConfig

    model, _ = load_model("shipped")
    ds = SceneDataset(shipped_samples(), split="test")
    cfg = InferenceConfig(search=SearchConfig(rounds=1, shape_nearest=2), color_fit=ColorFitConfig(steps=2))
    with pytest.raises(DistillError, match="may only try shapes") as e:
        fit_targets(model, ds, tmp_path / "no", 2, cfg, batch_size=2, progress=False, true_poses=True)
    assert "\n" not in str(e.value)
    cfg = true_pose_search(cfg)
    assert cfg.search.trials_per_slot == 0 and cfg.search.shape_nearest == 2
    n = 3
    s = fit_targets(model, ds, tmp_path / "t", n, cfg, batch_size=2, progress=False, true_poses=True)
    assert s["scenes"] == n
    t = DistillTargets(tmp_path / "t", num_slots=3).t
    b = ds.batch(list(range(n)))
    periods = torch.tensor(yaw_periods_of(ds))
    shown = 0
    for i in range(n):
        used = set()
        for k in torch.nonzero(t["visible"][i] >= 25).flatten().tolist():
            d = (b.obj_position[i, : int(b.obj_count[i])] - t["position"][i, k]).norm(dim=-1)
            j = int(d.argmin())
            assert float(d[j]) < 1e-6 and j not in used
            used.add(j)
            assert float(t["scale"][i, k]) == pytest.approx(float(b.obj_scale[i, j]), abs=1e-6)
            period = float(periods[int(b.obj_shape[i, j])])
            if period > 0:
                yaw = math.atan2(float(t["cos_sin"][i, k, 1]), float(t["cos_sin"][i, k, 0]))
                turns = (yaw - float(b.obj_yaw[i, j])) / period
                assert turns == pytest.approx(round(turns), abs=1e-4)
            shown += 1
    assert shown >= n  # the sample scenes have objects in view
