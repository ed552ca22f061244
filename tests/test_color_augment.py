"""Colour augmentations for training: hue turns about the grey axis (``prismonet.data.hue``, ``TrainConfig.hue_rotate``)
and per-object recolouring from depth (``prismonet.data.recolor``, ``TrainConfig.recolor_objects``)."""

import math
from dataclasses import replace

import numpy as np
import pytest
import torch

from prismonet.data.hue import hue_rotation, random_angles, rotate_hue


@pytest.fixture(scope="module")
def batch():
    """Eight shipped sample scenes (only their container is used: the images are replaced)."""
    from prismonet.assets import shipped_samples
    from prismonet.data.dataset import SceneDataset

    ds = SceneDataset(shipped_samples(), split="test")
    return ds.batch([i % len(ds) for i in range(8)])


def test_rotation_is_a_rotation_about_the_grey_axis():
    angles = torch.tensor([0.0, 0.3, -1.1, math.pi, 2.5], dtype=torch.float64)
    R = hue_rotation(angles)
    eye = torch.eye(3, dtype=torch.float64)
    for r, a in zip(R, angles):
        torch.testing.assert_close(r @ r.T, eye, rtol=0, atol=1e-12)  # orthogonal
        assert torch.linalg.det(r).item() == pytest.approx(1.0, abs=1e-12)  # proper
        torch.testing.assert_close(r @ torch.ones(3, dtype=torch.float64), torch.ones(3, dtype=torch.float64), rtol=0, atol=1e-12)
        assert torch.trace(r).item() == pytest.approx(1 + 2 * math.cos(a.item()), abs=1e-12)  # the angle itself
    torch.testing.assert_close(R[0], eye, rtol=0, atol=0)


def test_a_third_of_a_turn_permutes_the_channels():
    # about (1, 1, 1), 120 degrees right-handed takes the x axis to the y axis: red becomes green, green blue
    R = hue_rotation(torch.tensor(2 * math.pi / 3, dtype=torch.float64))
    torch.testing.assert_close(R, torch.tensor([[0.0, 0, 1], [1, 0, 0], [0, 1, 0]], dtype=torch.float64), rtol=0, atol=1e-12)
    rgb = torch.tensor([0.4, 0.2, 0.1]).reshape(1, 3, 1, 1)
    torch.testing.assert_close(rotate_hue(rgb, torch.tensor([2 * math.pi / 3])).flatten(), torch.tensor([0.1, 0.4, 0.2]),
                               rtol=0, atol=1e-6)


def test_turned_image_is_the_scene_with_turned_albedos():
    # a Lambertian pixel is albedo x shading per channel; the turn commutes with the shading, keeps greys and the
    # mean of the channels, and each image gets its own angle
    g = torch.Generator().manual_seed(0)
    albedo = torch.rand(2, 3, 1, 1, generator=g) * 0.5
    shading = torch.rand(2, 1, 8, 8, generator=g)
    angle = torch.tensor([0.7, -2.0])
    got = rotate_hue(albedo * shading, angle)
    expect = rotate_hue(albedo, angle) * shading
    torch.testing.assert_close(got, expect, rtol=0, atol=1e-6)
    torch.testing.assert_close(got.mean(1), (albedo * shading).mean(1), rtol=0, atol=1e-6)
    grey = torch.full((2, 3, 4, 4), 0.59)
    torch.testing.assert_close(rotate_hue(grey, angle), grey, rtol=0, atol=1e-6)
    assert not torch.allclose(got[0], (albedo * shading)[0], atol=1e-3)  # it did turn
    with pytest.raises(ValueError, match="expected rgb"):
        rotate_hue(torch.zeros(2, 4, 3, 3), angle)


def test_random_angles_stay_in_range():
    a = random_angles(1000, 30.0, torch.Generator().manual_seed(1))
    assert a.abs().max().item() <= math.radians(30.0) and a.min() < -0.4 and a.max() > 0.4


def test_hue_batch_in_training(batch):
    """0 draws nothing (older runs keep their random stream); > 0 turns each image and the background targets by the
    same drawn angle; bad settings are refused in one line."""
    from prismonet.model.losses import LossConfig
    from prismonet.model.trainer import TrainConfig, hue_batch

    g = torch.Generator().manual_seed(5)
    same, none = hue_batch(batch, None, TrainConfig(), g)
    assert same is batch and none is None and torch.equal(g.get_state(), torch.Generator().manual_seed(5).get_state())
    colourful = replace(batch, rgb=torch.rand(8, 3, 16, 16, generator=torch.Generator().manual_seed(0)) * 0.5 + 0.25)
    bg = torch.tensor([[0.6, 0.3, 0.3]]).expand(8, 3)
    got, (t, mask) = hue_batch(colourful, ({"bg_color": bg}, torch.ones(8)), TrainConfig(hue_rotate=90.0), torch.Generator().manual_seed(1))
    angle = random_angles(8, 90.0, torch.Generator().manual_seed(1))  # the draw hue_batch makes
    torch.testing.assert_close(got.rgb, rotate_hue(colourful.rgb, angle), rtol=0, atol=0)
    torch.testing.assert_close(t["bg_color"], rotate_hue(bg, angle), rtol=0, atol=0)
    assert not torch.allclose(got.rgb, colourful.rgb, atol=1e-3)
    with pytest.raises(ValueError, match="hue_rotate"):
        TrainConfig(hue_rotate=200.0)
    with pytest.raises(ValueError, match="distill_texture"):
        TrainConfig(hue_rotate=90.0, loss=LossConfig(w_distill=0.5))
    TrainConfig(hue_rotate=90.0, loss=LossConfig(w_distill=0.5, distill_texture=0.0))  # allowed


def test_object_regions_from_depth_alone():
    """Pixels off the ground plane's depth form the regions; the ground and the far clip are 0."""
    from prismonet.data.recolor import object_regions

    ground = torch.full((1, 1, 6, 8), 5.0)
    ground[..., :2, :] = 12.0  # the sky / beyond the clip
    depth = ground.clone()
    depth[0, 0, 3:5, 1:3] = 4.0  # one object
    depth[0, 0, 2:4, 5:7] = 4.5  # another, not touching it
    depth[0, 0, 0, 0] = 12.0  # far clip: not an object
    lab = object_regions(depth, ground, 12.0)
    assert lab.shape == (1, 6, 8) and lab.max() == 2
    assert len({int(lab[0, 3, 1]), int(lab[0, 2, 5])}) == 2 and lab[0, 3, 1] > 0 and lab[0, 2, 5] > 0
    assert (lab[0] > 0).sum() == 8 and lab[0, 0, 0] == 0


def test_recolor_is_a_per_channel_albedo_change(batch):
    """Each region is multiplied by one gain per channel (so a Lambertian object is re-rendered with a new albedo),
    its mean brightness is kept within the drawn factor, the rest of the image is untouched, and the draws are the
    documented ones."""
    from prismonet.data.recolor import recolor_regions

    g = torch.Generator().manual_seed(0)
    shading = torch.rand(1, 1, 10, 10, generator=g) * 0.5 + 0.5
    albedo = torch.tensor([0.45, 0.45, 0.45]).reshape(1, 3, 1, 1)  # a grey object: a hue turn cannot change it
    rgb = torch.full((1, 3, 10, 10), 0.59)
    labels = np.zeros((1, 10, 10), np.int64)
    labels[0, 2:7, 3:8] = 1
    m = torch.from_numpy(labels[0] == 1)
    rgb[0][:, m] = (albedo * shading)[0][:, m]
    out = recolor_regions(rgb, labels, torch.Generator().manual_seed(3), brightness=(1.0, 1.0))
    gains = out[0][:, m] / rgb[0][:, m]
    torch.testing.assert_close(gains, gains[:, :1].expand_as(gains), rtol=1e-5, atol=0)  # one gain per channel
    assert gains[:, 0].std() > 0.05  # the grey object is grey no more
    torch.testing.assert_close(out[0][:, ~m], rgb[0][:, ~m], rtol=0, atol=0)
    torch.testing.assert_close(out[0][:, m].mean(), rgb[0][:, m].mean(), rtol=1e-5, atol=0)  # brightness factor 1
    draw = torch.rand(4, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    c = draw[:3] + 1e-3
    expect = (c / c.mean()).float()  # the mean colour's gains for a grey region of equal channels, brightness kept
    torch.testing.assert_close(gains[:, 0], expect, rtol=1e-4, atol=0)
    kept = recolor_regions(rgb, labels, torch.Generator().manual_seed(3), which=torch.tensor([False]))
    assert torch.equal(kept, rgb)


def test_recolor_batch_in_training(batch):
    from prismonet.model.losses import LossConfig
    from prismonet.model.trainer import TrainConfig, recolor_batch

    g = torch.Generator().manual_seed(5)
    assert recolor_batch(batch, TrainConfig(), g) is batch
    assert torch.equal(g.get_state(), torch.Generator().manual_seed(5).get_state())  # nothing drawn
    got = recolor_batch(batch, TrainConfig(recolor_objects=1.0), torch.Generator().manual_seed(1))
    assert got.rgb.shape == batch.rgb.shape and not torch.equal(got.rgb, batch.rgb)
    with pytest.raises(ValueError, match="recolor_objects"):
        TrainConfig(recolor_objects=2.0)
    with pytest.raises(ValueError, match="distill_texture"):
        TrainConfig(recolor_objects=0.5, loss=LossConfig(w_distill=0.5))


def test_shape_recall_script(capsys, script):
    """``scripts/shape_recall.py`` on the shipped car samples: a row per shape present, a recolouring to the same
    colour changes nothing, and bad flags get one line and exit 2."""
    from prismonet.assets import samples_for

    data = str(samples_for("cars_keep"))
    run = script("shape_recall").main
    assert run(["cars", data, "--split", "test", "--limit", "6"]) == 0
    plain = capsys.readouterr().out
    rows = [r for r in plain.splitlines() if r.startswith("| ") and r[2].isdigit()]
    assert rows and all(0 <= float(r.split("|")[3]) <= 1 for r in rows)
    shape = rows[0].split("|")[1].strip()
    assert run(["cars", data, "--split", "test", "--limit", "6", "--recolor", shape, "0.4,0.2,0.2", "0.4,0.2,0.2"]) == 0
    same = capsys.readouterr().out
    assert same.splitlines()[1:] == plain.splitlines()[1:]  # only the title line names the recolouring
    for argv, says in ((["--recolor", "0", "a,b", "1,1,1"], "expected three comma-separated numbers"),
                       (["--recolor", "0", "1,1,1", "1,0,1"], "expected three positive numbers"),
                       (["--limit", "0"], "must be positive")):
        assert run(["cars", data, "--split", "test", *argv]) == 2
        err = capsys.readouterr().err
        assert says in err and len(err.strip().splitlines()) == 1, err


def test_color_augment_figure_script(tmp_path, capsys, script):
    import cv2

    from prismonet.assets import samples_for

    run = script("color_augment_figure").main
    out = tmp_path / "f.png"
    assert run([str(samples_for("cars_keep")), "--split", "test", "--scenes", "2", "--out", str(out)]) == 0
    img = cv2.imread(str(out))
    assert img.shape[1] == 3 * 160 and img.shape[0] > 2 * 160  # three labelled panels a row, two rows
    assert run([str(tmp_path / "none"), "--out", str(tmp_path / "g.png")]) == 2
    assert "no such dataset folder" in capsys.readouterr().err and not (tmp_path / "g.png").exists()


def test_recolored_scenes_are_drawn_once_per_scene():
    """``RecoloredScenes``: a scene's colours are ``recolor_regions`` with the generator of ``(seed, index)``, the same
    whichever batch asks for it and in whatever order; depth and ground pixels are the scene's own; another seed draws
    other colours."""
    from prismonet.assets import samples_for
    from prismonet.data.dataset import SceneDataset
    from prismonet.data.recolor import RecoloredScenes, batch_regions, recolor_regions

    ds = SceneDataset(samples_for("cars_keep"), split="test")
    view = RecoloredScenes(ds, 12.0, seed=3)
    a = view.batch([2, 0, 1])
    b = view.batch([1, 2])
    assert torch.equal(a.rgb[0], b.rgb[1]) and torch.equal(a.rgb[2], b.rgb[0])
    fresh = RecoloredScenes(ds, 12.0, seed=3).batch([1])
    assert torch.equal(fresh.rgb[0], b.rgb[0])  # not a matter of what was asked for first
    plain = ds.batch([2, 0, 1])
    assert torch.equal(a.depth, plain.depth) and len(view) == len(ds)
    labels = batch_regions(plain, 12.0)
    want = recolor_regions(plain.rgb[1:2], labels[1:2], torch.Generator().manual_seed(3 * 1_000_003 + 0))
    assert torch.equal(a.rgb[1], want[0])
    ground = torch.from_numpy(labels == 0)[:, None].expand_as(plain.rgb)
    assert torch.equal(a.rgb[ground], plain.rgb[ground]) and not torch.equal(a.rgb, plain.rgb)
    other = RecoloredScenes(ds, 12.0, seed=4).batch([2, 0, 1])
    assert not torch.equal(other.rgb, a.rgb)


def test_refiner_fit_with_recoloured_scenes(clevr3, tmp_path, capsys):
    """``RefinerFitConfig.recolor``: refused with a texture or colour term (one line from the CLI), and with a cache made
    elsewhere; a fit with it runs, learns, records it and resumes."""
    import json

    from prismonet.assets import shipped_samples
    from prismonet.cli import main
    from prismonet.data.dataset import SceneDataset
    from prismonet.model.distill import DistillError
    from prismonet.model.refiner_fit import RefinerFitConfig, encoder_cache, fit_refiner, with_refiner
    from test_refiner import _shifted_targets

    for bad in (dict(texture=0.1), dict(texture=0.0, color=0.5)):
        with pytest.raises(ValueError, match="recolor needs texture = 0 and color = 0"):
            RefinerFitConfig(recolor=True, **bad)
    assert main(["refiner", "clevr3", str(shipped_samples()), "--targets", str(tmp_path / "t"), "--out",
                 str(tmp_path / "x"), "--recolor"]) != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert "recolor needs texture = 0" in err[-1] and not (tmp_path / "x" / "model.json").exists()
    model = clevr3[0]
    ds = SceneDataset(shipped_samples(), split="test")
    _shifted_targets(model, ds, tmp_path / "t", 12, [0.2, 0.0, 0.0])
    cfg = RefinerFitConfig(steps=30, batch_size=8, lr=2e-3, holdout=4, checkpoint_every=30, texture=0.0, recolor=True)
    with pytest.raises(DistillError, match="made from the recoloured scenes"):
        fit_refiner(with_refiner(model), ds, tmp_path / "t", tmp_path / "c", cfg, progress=False,
                    cache=encoder_cache(with_refiner(model), ds, 12, progress=False))
    s = fit_refiner(with_refiner(model, refiner_keep=False), ds, tmp_path / "t", tmp_path / "run", cfg, progress=False)
    assert s["held_out_end"] < s["held_out_start"]
    rec = json.loads((tmp_path / "run" / "model.json").read_text())["refiner_fit"]["fit"]
    assert rec["recolor"] is True
    more = fit_refiner(with_refiner(model, refiner_keep=False), ds, tmp_path / "t", tmp_path / "run",
                       RefinerFitConfig(**{**cfg.__dict__, "steps": 40}), progress=False)
    rows = [json.loads(line) for line in (tmp_path / "run" / "log.jsonl").read_text().splitlines()]
    assert [r["step"] for r in rows] == [0, 30, 40] and more["steps"] == 40


def test_gray_scenes_share_is_drawn_once_per_scene():
    """``GrayScenes(share=...)``: each scene is grey or not by its index and seed alone, whatever batch asks for it; the
    grey ones are exactly their luminance, the others untouched; about the share of them are grey."""
    from prismonet.assets import shipped_samples
    from prismonet.data.dataset import SceneDataset
    from prismonet.data.gray import GrayScenes, is_gray, to_gray

    ds = SceneDataset(shipped_samples(), split="test")
    n = len(ds)
    g = GrayScenes(ds, share=0.5, seed=3)
    which = [g.grey(i) for i in range(n)]
    assert 0 < sum(which) < n
    a, b = g.batch(list(range(n))), g.batch(list(reversed(range(n))))
    assert torch.equal(a.rgb, b.rgb.flip(0))
    plain = ds.batch(list(range(n)))
    assert is_gray(a.rgb).tolist() == which
    for i in range(n):
        assert torch.equal(a.rgb[i], to_gray(plain.rgb[i : i + 1])[0] if which[i] else plain.rgb[i])
    assert [GrayScenes(ds, share=0.5, seed=4).grey(i) for i in range(n)] != which or n < 4
    with pytest.raises(ValueError, match="share must be in"):
        GrayScenes(ds, share=0.0)


def test_refiner_fit_with_grey_scenes(clevr3, tmp_path):
    """``RefinerFitConfig.gray_share``: refused with a texture or colour term and with a cache made elsewhere; a fit with
    it runs, learns and records the share."""
    import json

    from prismonet.assets import shipped_samples
    from prismonet.data.dataset import SceneDataset
    from prismonet.model.distill import DistillError
    from prismonet.model.refiner_fit import RefinerFitConfig, encoder_cache, fit_refiner, with_refiner
    from test_refiner import _shifted_targets

    for bad in (dict(texture=0.1), dict(texture=0.0, color=0.5), dict(texture=0.0, gray_share=1.5)):
        with pytest.raises(ValueError, match="gray_share must be in"):
            RefinerFitConfig(**{"gray_share": 0.5, **bad})
    model = clevr3[0]
    ds = SceneDataset(shipped_samples(), split="test")
    _shifted_targets(model, ds, tmp_path / "t", 12, [0.2, 0.0, 0.0])
    cfg = RefinerFitConfig(steps=30, batch_size=8, lr=2e-3, holdout=4, checkpoint_every=30, texture=0.0, gray_share=0.5)
    with pytest.raises(DistillError, match="made from the grey scenes"):
        fit_refiner(with_refiner(model), ds, tmp_path / "t", tmp_path / "c", cfg, progress=False,
                    cache=encoder_cache(with_refiner(model), ds, 12, progress=False))
    s = fit_refiner(with_refiner(model, refiner_keep=False), ds, tmp_path / "t", tmp_path / "run", cfg, progress=False)
    assert s["held_out_end"] < s["held_out_start"]
    assert json.loads((tmp_path / "run" / "model.json").read_text())["refiner_fit"]["fit"]["gray_share"] == 0.5


def test_refiner_cli_refuses_a_bad_gray_share_in_one_line(tmp_path, capsys):
    from prismonet.assets import shipped_samples
    from prismonet.cli import main

    assert main(["refiner", "shipped", str(shipped_samples()), "--targets", str(tmp_path / "t"), "--out",
                 str(tmp_path / "x"), "--texture", "0", "--gray-share", "1.5"]) != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "gray_share must be in [0, 1]" in err[0] and not (tmp_path / "x").exists()


def test_distill_gray_fits_the_grey_images_and_says_so(tmp_path):
    """``distill --gray``: the targets are the same steps run on the grey scenes (``fit_targets`` on ``GrayScenes``,
    equal to the last bit), not the colour ones, and ``targets.json`` records it (``DistillTargets.gray``)."""
    import json

    from prismonet.assets import shipped_samples
    from prismonet.checkpoint import load_checkpoint
    from prismonet.cli import main
    from prismonet.data.dataset import SceneDataset
    from prismonet.data.gray import GrayScenes
    from prismonet.model.distill import DistillTargets
    from prismonet.model.distill_fit import fit_targets
    from prismonet.model.inference import InferenceConfig
    from prismonet.model.io import load_model

    data = str(shipped_samples())
    flags = ["--split", "test", "--count", "3", "--batch", "3", "--search", "0", "--fit-color", "5", "--quiet"]
    assert main(["distill", "shipped", data, "--out", str(tmp_path / "g"), "--gray", *flags]) == 0
    assert main(["distill", "shipped", data, "--out", str(tmp_path / "c"), *flags]) == 0
    assert json.loads((tmp_path / "g" / "targets.json").read_text())["gray"] is True
    assert DistillTargets(tmp_path / "g", 3).gray and not DistillTargets(tmp_path / "c", 3).gray
    model = load_model("shipped")[0]
    fit_targets(model, GrayScenes(SceneDataset(data, split="test")), tmp_path / "ref", 3,
                InferenceConfig.of(fit_color=5), batch_size=3, progress=False)
    g, c, ref = (load_checkpoint(tmp_path / d / "chunk_00000.safetensors")[0] for d in ("g", "c", "ref"))
    assert torch.equal(g["z_tex"], ref["z_tex"]) and torch.equal(g["bg_color"], ref["bg_color"])
    assert not torch.equal(g["z_tex"], c["z_tex"])
    bg = g["bg_color"]
    assert torch.allclose(bg, bg.mean(1, keepdim=True).expand_as(bg), atol=0.02)  # a grey scene's background is grey


def test_refiner_fit_on_grey_targets(clevr3, tmp_path, capsys):
    """Targets fitted on grey scenes: the fit must be set up for them (``gray_targets``, with ``gray_share`` 1) and may
    then regress textures; the command line sets it from ``targets.json`` and refuses another grey share."""
    import json

    from prismonet.assets import shipped_samples
    from prismonet.cli import main
    from prismonet.data.dataset import SceneDataset
    from prismonet.model.distill import DistillError
    from prismonet.model.refiner_fit import RefinerFitConfig, fit_refiner, with_refiner
    from test_refiner import _shifted_targets

    with pytest.raises(ValueError, match="need gray_share 1"):
        RefinerFitConfig(gray_targets=True, gray_share=0.5)
    model = clevr3[0]
    ds = SceneDataset(shipped_samples(), split="test")
    _shifted_targets(model, ds, tmp_path / "t", 12, [0.2, 0.0, 0.0])
    info = json.loads((tmp_path / "t" / "targets.json").read_text())
    (tmp_path / "t" / "targets.json").write_text(json.dumps({**info, "gray": True}))
    base = dict(steps=30, batch_size=8, lr=2e-3, holdout=4, checkpoint_every=30)
    with pytest.raises(DistillError, match="fitted on grey scenes"):
        fit_refiner(with_refiner(model), ds, tmp_path / "t", tmp_path / "x", RefinerFitConfig(**base), progress=False)
    cfg = RefinerFitConfig(**base, texture=0.1, gray_share=1.0, gray_targets=True)
    s = fit_refiner(with_refiner(model, refiner_keep=False), ds, tmp_path / "t", tmp_path / "run", cfg, progress=False)
    assert s["held_out_end"] < s["held_out_start"]
    fit = json.loads((tmp_path / "run" / "model.json").read_text())["refiner_fit"]["fit"]
    assert fit["gray_targets"] is True and fit["gray_share"] == 1.0 and fit["texture"] == 0.1
    assert main(["refiner", "clevr3", str(shipped_samples()), "--split", "test", "--targets", str(tmp_path / "t"),
                 "--out", str(tmp_path / "y"), "--gray-share", "0.5"]) != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "fitted on grey scenes" in err[0] and not (tmp_path / "y").exists()
