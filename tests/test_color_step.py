"""The learnt colour step (``prismonet.model.color_step``) and its photometric fit (``color_step_fit``)."""

import json

import pytest
import torch


@pytest.fixture(scope="module")
def plain(shipped):
    """The shipped model without its colour step, the four scenes, and its output on them."""
    from prismonet.model.color_step_fit import without_color_step

    model, b, _ = shipped
    model = without_color_step(model).eval()
    with torch.no_grad():
        out = model(b.rgb, b.K, b.T_world_cam, b.ground_z)
    return model, b, out


def test_without_color_step_is_the_model_before_it(shipped, plain):
    """The shipped model's colour step moves its texture latents and colours only; without it, the same weights give the
    same geometry and the colours the step started from."""
    model, b, out = shipped
    base, _, before = plain
    assert model.cfg.color_step and not base.cfg.color_step and not hasattr(base, "color_step")
    assert model.cfg.color_step_passes == 3 and base.cfg.color_step_passes == 1  # the default's step looks three times
    for name in ("z_sh", "position", "cos_sin", "scale"):
        assert torch.equal(getattr(out.latents.params, name), getattr(before.latents.params, name))
    assert torch.equal(out.composite.instance, before.composite.instance)
    assert not torch.equal(out.latents.params.z_tex, before.latents.params.z_tex)
    with torch.no_grad():
        again = model(b.rgb, b.K, b.T_world_cam, b.ground_z, recolor=False)
    assert torch.equal(again.latents.params.z_tex, before.latents.params.z_tex)
    assert torch.equal(again.composite.image, before.composite.image)


def _with_step(model, seed: int = 0, scale: float = 0.0):
    """``model`` with a colour step whose last layer is random at ``scale`` (0: a fresh, identity step)."""
    from prismonet.model.color_step_fit import with_color_step

    new = with_color_step(model).eval()
    if scale:
        g = torch.Generator().manual_seed(seed)
        last = new.color_step.head[-1]
        with torch.no_grad():
            last.weight.copy_(torch.randn(last.weight.shape, generator=g) * scale)
            last.bias.copy_(torch.randn(last.bias.shape, generator=g) * scale * 10)
    return new


def test_fresh_color_step_is_the_identity(plain):
    model, b, out = plain
    with torch.no_grad():
        got = _with_step(model)(b.rgb, b.K, b.T_world_cam, b.ground_z)
    assert torch.equal(got.latents.params.z_tex, out.latents.params.z_tex)
    assert torch.allclose(got.composite.image, out.composite.image, atol=1e-6)
    assert torch.equal(got.composite.instance, out.composite.instance)
    assert torch.equal(got.composite.depth, out.composite.depth)


def test_color_step_moves_colours_only(plain):
    """A non-zero step changes the texture latents of the active slots and the colours of the object pixels; the shapes,
    poses, depth, masks, instances and the ground's pixels stay exactly as they were."""
    model, b, out = plain
    stepped = _with_step(model, scale=0.05)
    with torch.no_grad():
        got = stepped(b.rgb, b.K, b.T_world_cam, b.ground_z)
        plain = stepped(b.rgb, b.K, b.T_world_cam, b.ground_z, recolor=False)
    p, q = got.latents.params, plain.latents.params
    for name in ("z_sh", "position", "cos_sin", "scale"):
        assert torch.equal(getattr(p, name), getattr(q, name))
    active = q.active if q.active is not None else torch.ones_like(q.scale, dtype=torch.bool)
    moved = (p.z_tex - q.z_tex).abs().amax(-1)
    assert bool((moved[active] > 0).all()) and bool((moved[~active] == 0).all())
    assert torch.equal(got.composite.depth, plain.composite.depth)
    assert torch.equal(got.composite.instance, plain.composite.instance)
    assert torch.equal(got.obj_mask, plain.obj_mask)
    ground = (plain.composite.instance == 0)[:, None].expand_as(plain.composite.image)
    assert torch.equal(got.composite.image[ground], plain.composite.image[ground])
    assert float((got.composite.image - plain.composite.image).abs()[~ground].mean()) > 1e-3


def test_recolor_without_the_last_render_casts_the_same_rays(plain):
    """``recolor`` on an output that holds no render (it casts the rays again) gives the image it gives with one."""
    from dataclasses import replace

    model, b, _ = plain
    stepped = _with_step(model, scale=0.05)
    with torch.no_grad():
        plain = stepped(b.rgb, b.K, b.T_world_cam, b.ground_z, recolor=False)
        a = stepped.recolor(plain, b.rgb, b.K, b.T_world_cam)
        c = stepped.recolor(replace(plain, render=None), b.rgb, b.K, b.T_world_cam)
    assert plain.render is not None
    assert torch.allclose(a.composite.image, c.composite.image, atol=1e-6)
    assert torch.equal(a.composite.instance, c.composite.instance)


def test_two_passes_are_the_step_run_twice(plain):
    """``color_step_passes`` 2 is the one-pass step applied to its own output: the second pass sees the image the first
    made. The fit's latents (from the geometry cache) follow the model's to float16 rounding of the cached points."""
    from prismonet.assets import shipped_samples
    from prismonet.data.dataset import SceneDataset
    from prismonet.model.color_step_fit import _step_latents, geometry_cache

    import copy
    from dataclasses import replace

    model, b, _ = plain
    one = _with_step(model, scale=0.05)
    two = copy.deepcopy(one)
    two.cfg = replace(two.cfg, color_step_passes=2)  # the same weights
    with torch.no_grad():
        base = one(b.rgb, b.K, b.T_world_cam, b.ground_z, recolor=False)
        once = one.recolor(base, b.rgb, b.K, b.T_world_cam)
        twice = one.recolor(once, b.rgb, b.K, b.T_world_cam)
        got = two(b.rgb, b.K, b.T_world_cam, b.ground_z)
    assert torch.allclose(got.latents.params.z_tex, twice.latents.params.z_tex, atol=1e-6)
    assert torch.allclose(got.composite.image, twice.composite.image, atol=1e-6)
    assert not torch.allclose(twice.latents.params.z_tex, once.latents.params.z_tex, atol=1e-3)
    ds = SceneDataset(shipped_samples(), split="test")
    cache = geometry_cache(two, ds, 4, progress=False)
    with torch.no_grad():
        z = _step_latents(two, cache, ds, torch.arange(4))
    assert torch.allclose(z, got.latents.params.z_tex, atol=5e-3)
    with pytest.raises(ValueError, match="color_step_passes"):
        from prismonet.model.config import ModelConfig

        ModelConfig(color_step=True, color_step_passes=0)


def test_geometry_cache_recolours_to_the_models_image(plain):
    """The cached winning surface points, recoloured with the model's own texture latents, give the model's composite
    (float16 points: within 2e-3 per channel) and its background where no slot wins."""
    from prismonet.assets import shipped_samples
    from prismonet.data.dataset import SceneDataset
    from prismonet.model.color_step_fit import geometry_cache, recolored, scene_mse

    model, b, out = plain
    stepped = _with_step(model, scale=0.05)  # the cache must not see the step
    ds = SceneDataset(shipped_samples(), split="test")
    cache = geometry_cache(stepped, ds, 4, batch_size=3, progress=False)
    idx = torch.arange(4)
    with torch.no_grad():
        img = recolored(model, cache, idx, cache["z_tex"])
    want = out.composite.image.flatten(2).transpose(1, 2)
    assert float((img - want).abs().max()) < 2e-3
    assert torch.equal(cache["winner"].long() + 1, out.composite.instance.reshape(4, -1).long())
    mse = scene_mse(cache, idx, want)
    truth = (b.rgb * 255).round() / 255
    assert torch.allclose(mse, ((out.composite.image - truth) ** 2).flatten(1).mean(1), atol=1e-6)


def test_fit_color_step_raises_psnr_on_its_scenes_and_resumes(plain, tmp_path):
    """A colour step fitted to eight scenes makes their image closer to the input than the model's own colours (the
    loss can only fall that way), the saved model loads with it, and a rerun with more steps resumes."""
    from prismonet.assets import shipped_samples
    from prismonet.data.dataset import SceneDataset
    from prismonet.model.color_step_fit import ColorStepFitConfig, fit_color_step, geometry_cache, held_out_psnr, with_color_step
    from prismonet.model.io import load_model

    model = plain[0]
    ds = SceneDataset(shipped_samples(), split="test")
    cfg = ColorStepFitConfig(steps=40, batch_size=8, lr=3e-3, holdout=4, checkpoint_every=20)
    torch.manual_seed(0)
    fit_color_step(with_color_step(model), ds, 12, tmp_path / "run", cfg, progress=False)
    torch.manual_seed(0)
    s = fit_color_step(with_color_step(model), ds, 12, tmp_path / "run", ColorStepFitConfig(**{**cfg.__dict__, "steps": 80}),
                       progress=False)
    rows = [json.loads(line) for line in (tmp_path / "run" / "log.jsonl").read_text().splitlines()]
    assert [r["step"] for r in rows] == [0, 20, 40, 60, 80]  # resumed at 40, not started again
    loaded, info = load_model(tmp_path / "run")
    assert loaded.cfg.color_step and info["color_step_fit"]["scenes"] == 12
    cache = geometry_cache(loaded, ds, 8, progress=False)
    train = torch.arange(8)
    before = held_out_psnr(loaded, cache, ds, train, step=False)
    after = held_out_psnr(loaded, cache, ds, train)
    assert after > before + 0.1, (before, after)
    assert s["held_out_psnr_start"] == pytest.approx(held_out_psnr(loaded, geometry_cache(loaded, ds, 12, progress=False), ds,
                                                                   torch.arange(8, 12), step=False), abs=1e-6)


def test_fit_color_step_rerun_when_finished_makes_no_cache(plain, tmp_path, monkeypatch):
    """Rerunning a finished colour-step fit takes no step and renders no scene: it saves the same model and returns the
    logged held-out PSNRs."""
    import prismonet.model.color_step_fit as cf
    from prismonet.assets import shipped_samples
    from prismonet.data.dataset import SceneDataset

    ds = SceneDataset(shipped_samples(), split="test")
    cfg = cf.ColorStepFitConfig(steps=4, batch_size=8, holdout=4, checkpoint_every=4)
    first = cf.fit_color_step(cf.with_color_step(plain[0]), ds, 12, tmp_path / "run", cfg, progress=False)
    saved = (tmp_path / "run" / "model.safetensors").read_bytes()

    def no_cache(*args, **kwargs):
        raise AssertionError("a finished fit rendered its scenes again")

    monkeypatch.setattr(cf, "geometry_cache", no_cache)
    again = cf.fit_color_step(cf.with_color_step(plain[0]), ds, 12, tmp_path / "run", cfg, progress=False)
    assert again["steps"] == 4 and again["held_out_psnr_end"] == first["held_out_psnr_end"]
    assert (tmp_path / "run" / "model.safetensors").read_bytes() == saved


def test_color_step_bad_input(plain, tmp_path, capsys):
    from prismonet.assets import shipped_samples
    from prismonet.cli import main
    from prismonet.data.dataset import SceneDataset
    from prismonet.model.color_step_fit import ColorStepError, ColorStepFitConfig, fit_color_step
    from prismonet.model.config import ModelConfig

    model = plain[0]
    ds = SceneDataset(shipped_samples(), split="test")
    with pytest.raises(ColorStepError, match="no colour step"):
        fit_color_step(model, ds, 12, tmp_path / "a", ColorStepFitConfig(steps=1, holdout=4), progress=False)
    with pytest.raises(ValueError, match="steps"):
        ColorStepFitConfig(steps=0)
    with pytest.raises(ValueError, match="presence"):
        ModelConfig(color_step=True, presence=True)
    for extra, words in ((["--channels", "16,0"], "--channels"), (["--count", "0"], "--count"), (["--passes", "0"], "--passes"), ([], "already has a colour step")):
        assert main(["color-step", "shipped", str(shipped_samples()), "--split", "test", "--out", str(tmp_path / "c"), *extra]) == 2
        err = capsys.readouterr().err
        assert words in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "c").exists()  # a command that fails leaves no folder behind


@pytest.mark.parametrize("name", ["cars_keep", "tableware_keep", "clevr1to8_keep", "tabletop_keep"])
def test_the_other_refiner_models_ship_with_their_colour_steps(name):
    """Session 58: every shipped model with a refiner carries a colour step fitted on 8,192 of its own training images,
    with its log beside it; without the step it is the model that shipped before."""
    from prismonet.assets import asset_path
    from prismonet.model.color_step_fit import without_color_step
    from prismonet.model.io import load_model

    model, info = load_model(name)
    assert model.cfg.color_step and model.cfg.refine_passes >= 1 and info["color_step_fit"]["scenes"] == 8192
    assert asset_path(f"{name}_color_log.jsonl").is_file()
    rows = [json.loads(line) for line in asset_path(f"{name}_color_log.jsonl").read_text().splitlines()]
    assert rows[-1]["step"] == 2000 and rows[-1]["held_out_psnr"] > rows[0]["held_out_psnr"] + 0.3
    assert not without_color_step(model).cfg.color_step
