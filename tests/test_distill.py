"""Self-distillation: targets from the test-time fit (resumable, chunked), their lookup and the loss."""

import math
from dataclasses import replace

import pytest
import torch

import prismonet.model.distill as distill
from prismonet.assets import shipped_samples
from prismonet.model.color_fit import ColorFitConfig
from prismonet.model.inference import InferenceConfig
from prismonet.model.distill import DistillError, DistillTargets, DistillWeights, distill_loss
from prismonet.model.distill_fit import fit_targets
from prismonet.model.search import SearchConfig
from prismonet.render import SceneParams


def params(scale, position, yaw_deg, z_tex):
    c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
    return SceneParams(torch.zeros(1, 1, 8), torch.tensor([[z_tex]]), torch.tensor([[position]]),
                       torch.tensor([[[2 * c, 2 * s]]]), torch.tensor([[scale]]))  # (cos, sin) need not be unit


def test_distill_loss_hand_computed():
    p = params(0.5, [0.0, 0.0, 0.5], 0.0, [1.0, 0.0])
    t = {"scale": torch.tensor([[0.6]]), "position": torch.tensor([[[0.1, -0.2, 0.5]]]),
         "cos_sin": torch.tensor([[[0.0, 1.0]]]), "z_tex": torch.tensor([[[0.0, 0.0]]]), "bg_color": torch.tensor([[0.5, 0.5, 0.5]])}
    bg = torch.tensor([[0.4, 0.5, 0.7]])
    w = DistillWeights(position=1.0, scale=2.0, rotation=0.5, texture=0.1, background=1.0)
    expect = 1.0 * 0.3 + 2.0 * 0.1 + 0.5 * 1.0 + 0.1 * 1.0 + 1.0 * 0.3  # 90 degrees of yaw: 1 - cos = 1
    assert float(distill_loss(p, bg, t, torch.ones(1), w)) == pytest.approx(expect, rel=1e-6)
    assert float(distill_loss(p, bg, t, torch.zeros(1), w)) == 0.0  # no targets for this scene


def test_distill_loss_regresses_only_the_slots_the_fit_shows():
    """With ``visible``, a hidden slot's target is ignored whatever it is; a scene showing none keeps only
    its background term."""
    two = SceneParams(torch.zeros(1, 2, 8), torch.zeros(1, 2, 2), torch.zeros(1, 2, 3), torch.tensor([[[1.0, 0.0]] * 2]),
                      torch.tensor([[0.5, 0.5]]))
    t = {"scale": torch.tensor([[0.7, 9.0]]), "position": torch.zeros(1, 2, 3), "cos_sin": torch.tensor([[[1.0, 0.0]] * 2]),
         "z_tex": torch.zeros(1, 2, 2), "bg_color": torch.tensor([[0.5, 0.5, 0.5]]), "visible": torch.tensor([[300.0, 24.0]])}
    bg = torch.tensor([[0.5, 0.5, 0.6]])
    w = DistillWeights(scale=1.0, background=1.0)
    assert float(distill_loss(two, bg, t, torch.ones(1), w)) == pytest.approx(0.2 + 0.1, rel=1e-6)  # slot 2 (24 px) left out
    t["visible"] = torch.tensor([[0.0, 0.0]])
    assert float(distill_loss(two, bg, t, torch.ones(1), w)) == pytest.approx(0.1, rel=1e-6)
    del t["visible"]  # targets made before the field: every slot
    assert float(distill_loss(two, bg, t, torch.ones(1), w)) == pytest.approx((0.2 + 8.5) / 2 + 0.1, rel=1e-6)


def test_distill_loss_shape_term_only_with_shape_targets():
    """Targets with ``z_sh`` (made by a search that tried the prior's shapes) add the squared L2 of the
    shape latents, weighted; targets without it leave the shapes alone."""
    p = params(0.5, [0.0, 0.0, 0.5], 0.0, [0.0, 0.0])  # z_sh all zeros, D = 8
    t = {"scale": torch.tensor([[0.5]]), "position": torch.tensor([[[0.0, 0.0, 0.5]]]), "cos_sin": torch.tensor([[[1.0, 0.0]]]),
         "z_tex": torch.zeros(1, 1, 2), "bg_color": torch.zeros(1, 3)}
    bg = torch.zeros(1, 3)
    assert float(distill_loss(p, bg, t, torch.ones(1))) == pytest.approx(0.0, abs=1e-7)
    t[distill.SHAPE] = torch.tensor([[[0.5, -1.0, 0, 0, 0, 0, 0, 2.0]]])  # squared distance 0.25 + 1 + 4
    assert float(distill_loss(p, bg, t, torch.ones(1), DistillWeights(shape=2.0))) == pytest.approx(2.0 * 5.25, rel=1e-6)


def test_shape_targets_only_from_a_search_with_shape_trials(tmp_path, monkeypatch):
    """A search that tries the prior's shapes saves each slot's fitted code (and the loader reads it);
    one that cannot change the shapes saves none, so old recipes are not anchored to their own codes.
    Settings added to the search after a folder's targets were made read as their defaults there."""
    import json

    from prismonet.data.dataset import SceneDataset
    from prismonet.model.io import load_model

    model, _ = load_model("shipped")
    ds = SceneDataset(shipped_samples(), split="test")
    shapes = InferenceConfig(search=SearchConfig(rounds=1, scales=(), shifts=(), yaws=(), shape_nearest=2))
    fit_targets(model, ds, tmp_path / "s", 2, shapes, batch_size=2, progress=False)
    t = DistillTargets(tmp_path / "s", num_slots=3)
    assert tuple(t.t[distill.SHAPE].shape) == (2, 3, model.prior.latents.shape[1])
    from prismonet.model.inference import infer

    with torch.no_grad():
        enc = infer(model, ds.batch([0, 1]), InferenceConfig()).latents.params.z_sh
    z = t.t[distill.SHAPE]  # every slot's code is the encoder's or one of the prior's
    d_prior = (z.reshape(-1, 1, z.shape[-1]) - model.prior.latents.float()).norm(dim=-1).min(1).values  # exact, unlike cdist's matmul
    d_enc = (z - enc).norm(dim=-1).reshape(-1)
    assert bool(((d_prior < 1e-6) | (d_enc < 1e-6)).all())
    plain = InferenceConfig(search=SearchConfig(rounds=1))
    fit_targets(model, ds, tmp_path / "p", 2, plain, batch_size=2, progress=False)
    assert distill.SHAPE not in DistillTargets(tmp_path / "p", num_slots=3).t
    info = json.loads((tmp_path / "p" / "targets.json").read_text())
    del info["search"]["shape_nearest"]  # as written before the setting existed
    (tmp_path / "p" / "targets.json").write_text(json.dumps(info))
    fit_targets(model, ds, tmp_path / "p", 2, plain, batch_size=2, progress=False)  # resumes: no "other settings"


def test_fit_targets_resume_lookup_and_settings(tmp_path, monkeypatch):
    from prismonet.data.dataset import SceneDataset
    from prismonet.model.io import load_model

    monkeypatch.setattr(distill, "CHUNK", 2)
    model, _ = load_model("shipped")
    ds = SceneDataset(shipped_samples(), split="test")
    cfg = InferenceConfig(search=SearchConfig(rounds=1), color_fit=ColorFitConfig(steps=2))
    s = fit_targets(model, ds, tmp_path / "t", 3, cfg, batch_size=2, progress=False)
    assert s["score_after"] <= s["score_before"]  # the fit never makes a scene worse
    files = sorted(p.name for p in (tmp_path / "t").glob("chunk_*.safetensors"))
    assert files == ["chunk_00000.safetensors", "chunk_00001.safetensors"]
    first = (tmp_path / "t" / files[0]).stat().st_mtime_ns
    (tmp_path / "t" / files[1]).unlink()  # as if interrupted during the second chunk
    s = fit_targets(model, ds, tmp_path / "t", 3, cfg, batch_size=2, progress=False)
    assert (tmp_path / "t" / files[0]).stat().st_mtime_ns == first  # a finished chunk is kept, not redone
    assert (tmp_path / "t" / files[1]).is_file()
    t = DistillTargets(tmp_path / "t", num_slots=3)
    assert t.count == 3 and tuple(t.t["position"].shape) == (3, 3, 3) and tuple(t.t["bg_color"].shape) == (3, 3)
    assert tuple(t.t["visible"].shape) == (3, 3) and float(t.t["visible"].sum()) > 0  # pixels each fitted slot wins
    tg, mask = t.lookup(torch.tensor([2, 0, 7]))
    assert mask.tolist() == [1.0, 1.0, 0.0] and torch.equal(tg["scale"][0], t.t["scale"][2])
    with pytest.raises(DistillError, match="other settings"):
        fit_targets(model, ds, tmp_path / "t", 3, replace(cfg, search=SearchConfig(rounds=2)), progress=False)
    with pytest.raises(DistillError, match="slots"):
        DistillTargets(tmp_path / "t", num_slots=4)
    with pytest.raises(DistillError, match="no distillation targets"):
        DistillTargets(tmp_path / "missing", num_slots=3)
    with pytest.raises(DistillError, match="count"):
        fit_targets(model, ds, tmp_path / "u", 0, cfg, progress=False)
    with pytest.raises(DistillError, match="extra slots"):
        fit_targets(model, ds, tmp_path / "u", 3, replace(cfg, extra_slots=1), progress=False)
    from prismonet.model.reseed import ReseedConfig

    with pytest.raises(DistillError, match="other settings"):  # re-seeding is recorded with the targets
        fit_targets(model, ds, tmp_path / "t", 3, replace(cfg, reseed=ReseedConfig(rounds=1)), progress=False)
    with pytest.raises(DistillError, match="--reseed-grow"):
        fit_targets(model, ds, tmp_path / "u", 3, replace(cfg, reseed=ReseedConfig(rounds=1, grow=1)), progress=False)


def test_lanes_fill_one_folder_with_the_chunks_of_one_run(tmp_path, monkeypatch):
    """``lane=(i, n)``: each lane fits every n-th chunk; two lanes into one folder give the single run's chunks bit for
    bit, a lane alone leaves the other lane's chunks missing (so ``DistillTargets`` reads the unbroken prefix), and the
    CLI's 1-based ``--lane I/N`` maps to it and refuses nonsense in one line."""
    import argparse

    from safetensors.torch import load_file

    from prismonet.cli.train import _lane
    from prismonet.data.dataset import SceneDataset
    from prismonet.model.io import load_model

    monkeypatch.setattr(distill, "CHUNK", 1)
    model, _ = load_model("shipped")
    ds = SceneDataset(shipped_samples(), split="test")
    cfg = InferenceConfig(search=SearchConfig(rounds=1), color_fit=ColorFitConfig(steps=2))
    fit_targets(model, ds, tmp_path / "one", 3, cfg, batch_size=1, progress=False)
    s = fit_targets(model, ds, tmp_path / "lanes", 3, cfg, batch_size=1, progress=False, lane=(1, 2))
    made = sorted(p.name for p in (tmp_path / "lanes").glob("chunk_*"))
    assert s["chunks"] == 1 and made == ["chunk_00001.safetensors"]
    with pytest.raises(DistillError, match="no finished chunk"):  # chunk 0 missing: no prefix yet
        DistillTargets(tmp_path / "lanes", num_slots=3)
    fit_targets(model, ds, tmp_path / "lanes", 3, cfg, batch_size=1, progress=False, lane=(0, 2))
    for i in range(3):
        a = load_file(tmp_path / "one" / f"chunk_{i:05d}.safetensors")
        b = load_file(tmp_path / "lanes" / f"chunk_{i:05d}.safetensors")
        assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    assert DistillTargets(tmp_path / "lanes", num_slots=3).count == 3
    assert not list((tmp_path / "lanes").glob("*.tmp*"))
    with pytest.raises(DistillError, match="lane"):
        fit_targets(model, ds, tmp_path / "bad", 3, cfg, progress=False, lane=(2, 2))
    assert _lane("1/2") == (0, 2) and _lane("2/2") == (1, 2) and _lane("1/1") == (0, 1)
    for bad in ("0/2", "3/2", "2", "a/b"):
        with pytest.raises(argparse.ArgumentTypeError, match="I/N"):
            _lane(bad)


def test_training_uses_the_targets(tmp_path, monkeypatch):
    import json

    from prismonet.data.dataset import SceneDataset
    from prismonet.model.config import ModelConfig
    from prismonet.model.io import load_model
    from prismonet.model.losses import LossConfig
    from prismonet.model.trainer import TrainConfig, train

    model, _ = load_model("clevr3_fc")  # the encoder-only model the run below starts from
    ds = SceneDataset(shipped_samples(), split="test")
    fit_targets(model, ds, tmp_path / "t", len(ds), InferenceConfig.of(search=1, fit_color=2), progress=False)
    weights = []  # the texture term's weight reaches the loss from the config (0 here)
    original = distill.distill_loss
    monkeypatch.setattr(distill, "distill_loss", lambda *a: weights.append(a[4].texture) or original(*a))
    cfg = TrainConfig(data=str(shipped_samples()), split="test", steps=2, log_every=1, init_from="clevr3_fc",
                      model=ModelConfig(soft_mask_tau=0.05),
                      loss=LossConfig(w_mask=0.1, mask_from_depth=True, w_distill=0.5, distill_texture=0.0),
                      distill=str(tmp_path / "t"))
    train(cfg, tmp_path / "run", progress=False)
    rows = [json.loads(line) for line in (tmp_path / "run" / "log.jsonl").read_text().splitlines()]
    assert all(r["distill"] > 0 for r in rows)
    assert weights == [0.0, 0.0]
    with pytest.raises(ValueError, match="distill_texture must be non-negative"):
        LossConfig(distill_texture=-0.1)


def test_batch_rows_follow_the_indices_asked_for():
    """Row j of a batch is scene indices[j] (the trainer looks targets up by the same indices;
    ``batch`` once sorted them silently, so every target landed on another scene)."""
    from prismonet.data.dataset import SceneDataset

    ds = SceneDataset(shipped_samples(), split="test")
    idx = [5, 2, 9, 2]
    b = ds.batch(idx)
    for j, i in enumerate(idx):
        assert torch.equal(b.rgb[j], ds.batch([i]).rgb[0])


def test_weights_digest_tells_models_apart():
    from prismonet.model.distill_fit import weights_digest
    from prismonet.model.io import load_model

    a, _ = load_model("shipped")
    b, _ = load_model("shipped")
    assert weights_digest(a) == weights_digest(b) and len(weights_digest(a)) == 16
    with torch.no_grad():
        next(b.parameters()).view(-1)[0] += 1e-3
    assert weights_digest(a) != weights_digest(b)


def test_keep_loss_hand_computed():
    """The keep term: per scene the mean binary cross-entropy of the slots' keep logits against whether the fit shows
    them (25 pixels or more), then the mean over the scenes with targets; targets without ``visible`` are refused."""
    from prismonet.model.distill import keep_loss

    logit = torch.tensor([[0.0, 2.0], [-1.0, 1.0]])
    t = {"visible": torch.tensor([[30.0, 0.0], [24.0, 25.0]])}
    first = (math.log(2.0) + math.log(1 + math.exp(2.0))) / 2  # shown at logit 0, hidden at logit 2
    second = (math.log(1 + math.exp(-1.0)) + math.log(1 + math.exp(-1.0))) / 2  # hidden at -1, shown at 1
    assert float(keep_loss(logit, t, torch.tensor([1.0, 0.0]))) == pytest.approx(first, rel=1e-6)
    assert float(keep_loss(logit, t, torch.ones(2))) == pytest.approx((first + second) / 2, rel=1e-6)
    assert float(keep_loss(logit, t, torch.zeros(2))) == 0.0
    with pytest.raises(DistillError, match="which slots the fit shows"):
        keep_loss(logit, {}, torch.ones(2))


def test_targets_made_by_a_refined_model_match_its_encoder():
    """A later round of self-distillation: targets made by ``chairs_refiner`` (the ``chairs`` encoder with a refinement
    pass) may be fitted on ``chairs``, and on no other encoder."""
    from prismonet.cli.train import _made_by_refined
    from prismonet.model.distill_fit import encoder_digest, weights_digest
    from prismonet.model.io import load_model

    encoder, refined, other = (load_model(n)[0] for n in ("chairs", "chairs_refiner", "chairs_depth01"))
    assert encoder_digest(refined) == weights_digest(encoder) == encoder_digest(encoder)
    assert weights_digest(refined) != weights_digest(encoder)
    meta = {"model": "chairs_refiner", "model_digest": weights_digest(refined)}
    assert _made_by_refined(meta, weights_digest(encoder))
    assert not _made_by_refined(meta, weights_digest(other))
    assert not _made_by_refined({**meta, "model_digest": "0" * 16}, weights_digest(encoder))  # not the weights named
    assert not _made_by_refined({"model": "chairs", "model_digest": weights_digest(encoder)}, weights_digest(other))
    assert not _made_by_refined({"model": "no/such/model"}, weights_digest(encoder))


def _write_round(root, visible, offset, count=4, chunk=2, num_slots=2):
    """A hand-made round of targets: every field of slot k in scene i is ``offset + 10 i + k``; ``visible`` (count, K)."""
    import json

    from prismonet.checkpoint import save_checkpoint

    root.mkdir(parents=True)
    base = offset + 10 * torch.arange(count, dtype=torch.float32)[:, None] + torch.arange(num_slots, dtype=torch.float32)
    full = {"scale": base, "position": base[..., None].expand(-1, -1, 3).clone(), "cos_sin": base[..., None].expand(-1, -1, 2).clone(),
            "z_tex": base[..., None].expand(-1, -1, 4).clone(), "z_sh": base[..., None].expand(-1, -1, 5).clone(),
            "bg_color": torch.full((count, 3), float(offset)), "visible": torch.as_tensor(visible, dtype=torch.float32)}
    for c in range(0, count, chunk):
        save_checkpoint(root / f"chunk_{c // chunk:05d}.safetensors", {k: v[c:c + chunk] for k, v in full.items()}, {"round": offset})
    (root / "targets.json").write_text(json.dumps({"count": count, "chunk": chunk, "num_slots": num_slots, "data": "d", "split": "train",
                                                   "model": f"m{offset}"}))


def test_merge_targets_takes_the_later_round_where_it_shows_a_slot(tmp_path):
    """``scripts/merge_targets.py``: per slot, every field from the later round where it shows the slot (>= 25 pixels), else
    from the earlier one; ``visible`` the larger; the background the later round's. Rounds that differ are refused in one line."""
    import json
    import subprocess
    import sys
    from pathlib import Path

    later_vis = [[30, 0], [0, 24], [25, 99], [0, 0]]
    earlier_vis = [[40, 50], [0, 60], [0, 0], [10, 5]]
    _write_round(tmp_path / "later", later_vis, 1000)
    _write_round(tmp_path / "earlier", earlier_vis, 2000)
    script = Path(__file__).resolve().parents[1] / "scripts" / "merge_targets.py"
    r = subprocess.run([sys.executable, str(script), str(tmp_path / "later"), str(tmp_path / "earlier"), str(tmp_path / "out")],
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    merged = DistillTargets(tmp_path / "out", 2)
    take_later = torch.tensor(later_vis) >= 25
    want = torch.where(take_later, 1000.0, 2000.0) + 10 * torch.arange(4.0)[:, None] + torch.arange(2.0)
    assert torch.equal(merged.t["scale"], want)
    assert torch.equal(merged.t["z_sh"][..., 3], want) and torch.equal(merged.t["position"][..., 0], want)
    assert torch.equal(merged.t["visible"], torch.maximum(torch.tensor(later_vis, dtype=torch.float32), torch.tensor(earlier_vis, dtype=torch.float32)))
    assert torch.equal(merged.t["bg_color"], torch.full((4, 3), 1000.0))
    assert json.loads((tmp_path / "out" / "targets.json").read_text())["merged_from"]["later"] == str(tmp_path / "later")
    _write_round(tmp_path / "three", later_vis + [[0, 0], [0, 0]], 3000, count=6)
    r = subprocess.run([sys.executable, str(script), str(tmp_path / "three"), str(tmp_path / "earlier"), str(tmp_path / "out2")],
                       capture_output=True, text=True)
    assert r.returncode != 0 and "differ in count" in r.stderr and len(r.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "out2").exists()
