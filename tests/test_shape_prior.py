"""The auto-decoder, pre-training (overfit, resume), mesh extraction, metrics, the prior file."""

import numpy as np
import pytest
import torch

from prismonet.checkpoint import load_checkpoint, save_checkpoint
from prismonet.shapes.clevr_set import shape_mesh
from prismonet.shapes.decoder import LatentSizeError, SDFDecoder, SDFDecoderConfig
from prismonet.shapes.mesh import EmptyMeshError, extract_mesh
from prismonet.shapes.metrics import chamfer_l1, grid_points, volumetric_iou
from prismonet.shapes.pretrain import PretrainConfig, PriorInitError, ShapeSet, pretrain
from prismonet.shapes.prior import ShapePrior, load_prior
from prismonet.shapes.sdf_samples import SamplingConfig


class AnalyticSphere(torch.nn.Module):
    """An exact SDF with the decoder's interface: radius = 0.5 + 0.1 * z[0]."""

    cfg = SDFDecoderConfig(latent_dim=1)

    def check_latent(self, z):
        SDFDecoder.check_latent(self, z)

    def forward(self, z, x):
        return x.norm(dim=-1) - (0.5 + 0.1 * z[..., 0])


def test_decoder_shapes_broadcast_and_latent_check():
    phi = SDFDecoder(SDFDecoderConfig(latent_dim=8, width=32, depth=4, skip_layer=2))
    out = phi(torch.zeros(3, 1, 8), torch.rand(3, 50, 3))
    assert out.shape == (3, 50)
    # per-point latents give the same values as a broadcast latent
    z = torch.randn(3, 1, 8)
    x = torch.rand(3, 50, 3)
    assert torch.allclose(phi(z, x), phi(z.expand(3, 50, 8), x), atol=1e-6)
    with pytest.raises(LatentSizeError, match="latent: expected size 8, got 16"):
        phi(torch.zeros(16), torch.zeros(10, 3))
    with pytest.raises(ValueError, match="skip_layer"):
        SDFDecoderConfig(depth=3, skip_layer=3)


def test_marching_cubes_on_exact_sphere():
    mesh = extract_mesh(AnalyticSphere(), torch.tensor([2.0]), resolution=48)  # r = 0.7
    r = np.linalg.norm(mesh.vertices, axis=1)
    spacing = 2 * 1.1 / 47
    assert np.abs(r - 0.7).max() < spacing * 0.1  # linear interpolation of an exact SDF
    assert mesh.volume > 0  # outward-facing winding
    assert mesh.volume == pytest.approx(4 / 3 * np.pi * 0.7**3, rel=0.01)
    T = torch.eye(4)
    T[:3, :3] *= 2.0
    T[:3, 3] = torch.tensor([1.0, 2.0, 3.0])
    world = extract_mesh(AnalyticSphere(), torch.tensor([2.0]), resolution=48, T_world_obj=T)
    assert np.allclose(world.bounds.mean(0), [1.0, 2.0, 3.0], atol=1e-3)
    assert np.allclose(world.extents, 2 * 2 * 0.7, atol=0.01)


def test_open3d_conversion_keeps_geometry():
    from prismonet.shapes.mesh import to_open3d

    mesh = extract_mesh(AnalyticSphere(), torch.tensor([2.0]), resolution=24)
    o3 = to_open3d(mesh)
    assert np.allclose(np.asarray(o3.vertices), mesh.vertices) and np.array_equal(np.asarray(o3.triangles), mesh.faces)
    assert o3.has_vertex_normals()
    # outward normals: they point away from the centre
    assert (np.sum(np.asarray(o3.vertex_normals) * mesh.vertices, axis=1) > 0).all()


def test_empty_sdf_has_no_mesh():
    with pytest.raises(EmptyMeshError, match="no surface"):
        extract_mesh(AnalyticSphere(), torch.tensor([-10.0]), resolution=16)  # radius < 0


def test_chamfer_and_iou_hand_computed():
    a = np.array([[0.0, 0, 0], [1, 0, 0]])
    b = np.array([[0.0, 0, 0], [1, 0, 0], [3, 0, 0]])
    # a->b: 0, 0 ; b->a: 0, 0, 2 -> 0.5 * (0 + 2/3)
    assert chamfer_l1(a, b) == pytest.approx(1 / 3)
    g = grid_points(10)
    box_a = np.all(np.abs(g) < 0.5, axis=1)
    box_b = np.all(np.abs(g - [0.5, 0, 0]) < 0.5, axis=1)
    # cell centres at spacing 0.22: exact overlap fraction from the discrete counts
    inter, union = (box_a & box_b).sum(), (box_a | box_b).sum()
    assert volumetric_iou(box_a, box_b) == pytest.approx(inter / union)
    assert 0 < volumetric_iou(box_a, box_b) < 1 and volumetric_iou(box_a, box_a) == 1.0
    with pytest.raises(ValueError, match="shapes differ"):
        volumetric_iou(box_a, box_b[:5])


TINY = PretrainConfig(
    decoder=SDFDecoderConfig(latent_dim=4, width=64, depth=3),
    sampling=SamplingConfig(num_points=4096, uniform_ratio=0.3),
    epochs=150,
    points_per_shape=2048,
    checkpoint_every=1000,
)


def _two_shapes():
    return ShapeSet("two", (shape_mesh(0), shape_mesh(18)), ("sphere", "cube"), (0, 2), (0, 0))


def test_overfit_two_shapes(tmp_path):
    from prismonet.shapes.evaluate import evaluate_prior

    prior = pretrain(TINY, tmp_path / "run", shape_set=_two_shapes(), progress=False)
    report = evaluate_prior(prior, shape_set=_two_shapes(), resolution=32, iou_resolution=32, chamfer_points=5000,
                            interpolation_pairs=1, progress=False)
    assert report["min_iou"] > 0.85, report
    assert report["max_chamfer_l1"] < 0.06, report
    assert report["interpolation_nonempty"] == 1.0
    assert (tmp_path / "run" / "prior.safetensors").is_file()


def test_resume_after_kill_matches_uninterrupted_run(tmp_path):
    cfg = PretrainConfig(
        decoder=SDFDecoderConfig(latent_dim=4, width=16, depth=2),
        sampling=SamplingConfig(num_points=1024),
        epochs=4, points_per_shape=512, checkpoint_every=1,
    )
    cache = tmp_path / "cache"
    full = pretrain(cfg, tmp_path / "a", shape_set=_two_shapes(), cache_dir=cache, progress=False)
    pretrain(cfg, tmp_path / "b", shape_set=_two_shapes(), cache_dir=cache, progress=False, stop_after_epoch=1)
    assert not (tmp_path / "b" / "prior.safetensors").exists()
    resumed = pretrain(cfg, tmp_path / "b", shape_set=_two_shapes(), cache_dir=cache, progress=False)
    for (k, v), (k2, v2) in zip(full.decoder.state_dict().items(), resumed.decoder.state_dict().items()):
        assert k == k2 and torch.equal(v, v2), k
    assert torch.equal(full.latents, resumed.latents)
    # a different config refuses to resume into the same folder
    with pytest.raises(ValueError, match="another config"):
        pretrain(PretrainConfig(**{**cfg.__dict__, "epochs": 5}), tmp_path / "b", shape_set=_two_shapes(), cache_dir=cache, progress=False)


def test_pretraining_can_start_from_a_prior_and_checks_that_it_fits(tmp_path):
    cfg = PretrainConfig(decoder=SDFDecoderConfig(latent_dim=4, width=16, depth=2), sampling=SamplingConfig(num_points=1024),
                         epochs=2, points_per_shape=512)
    cache = tmp_path / "cache"
    first = pretrain(cfg, tmp_path / "a", shape_set=_two_shapes(), cache_dir=cache, progress=False)
    stem = str(tmp_path / "a" / "prior")
    # no epochs: the run is its init, exactly
    same = pretrain(PretrainConfig(**{**cfg.__dict__, "epochs": 0, "init": stem}), tmp_path / "b", shape_set=_two_shapes(),
                    cache_dir=cache, progress=False)
    for (k, v), (k2, v2) in zip(first.decoder.state_dict().items(), same.decoder.state_dict().items()):
        assert k == k2 and torch.equal(v, v2), k
    assert torch.equal(first.latents, same.latents)
    # more epochs from it train on from there, not from a fresh start
    more = pretrain(PretrainConfig(**{**cfg.__dict__, "init": stem}), tmp_path / "c", shape_set=_two_shapes(), cache_dir=cache,
                    progress=False)
    fresh_again = pretrain(cfg, tmp_path / "d", shape_set=_two_shapes(), cache_dir=cache, progress=False)
    assert torch.equal(first.latents, fresh_again.latents) and not torch.equal(more.latents, first.latents)
    # another decoder, or the shapes in another order, is refused in one line
    with pytest.raises(PriorInitError, match="decoder"):
        pretrain(PretrainConfig(**{**cfg.__dict__, "decoder": SDFDecoderConfig(latent_dim=4, width=32, depth=2), "init": stem}),
                 tmp_path / "e", shape_set=_two_shapes(), cache_dir=cache, progress=False)
    swapped = ShapeSet("two", (shape_mesh(18), shape_mesh(0)), ("cube", "sphere"), (2, 0), (0, 0))
    with pytest.raises(PriorInitError, match="other shapes"):
        pretrain(PretrainConfig(**{**cfg.__dict__, "init": stem}), tmp_path / "f", shape_set=swapped, cache_dir=cache, progress=False)


def test_an_init_prior_that_does_not_exist_is_refused_before_any_work(tmp_path):
    cfg = PretrainConfig(decoder=SDFDecoderConfig(latent_dim=4, width=16, depth=2), sampling=SamplingConfig(num_points=1024),
                         epochs=1, points_per_shape=512, init=str(tmp_path / "nosuch"))
    with pytest.raises(FileNotFoundError, match="no such shape-prior config"):
        pretrain(cfg, tmp_path / "run", shape_set=_two_shapes(), progress=False)
    assert not (tmp_path / "run").exists()  # no folder, no SDF samples made for nothing


@pytest.mark.parametrize("script, args", [("swap_prior.py", ["chairs_refiner", "NOSUCH"]),
                                          ("swap_prior.py", ["NOSUCH_MODEL", "chairs"]),
                                          ("prior_reach.py", ["data/furniture/chairs", "NOSUCH"])])
def test_the_prior_scripts_refuse_a_missing_prior_or_model_in_one_line(tmp_path, script, args):
    import subprocess
    import sys
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "scripts" / script
    extra = [str(tmp_path / "out")] if script == "swap_prior.py" else []
    r = subprocess.run([sys.executable, str(path), *args, *extra], capture_output=True, text=True,
                       cwd=Path(__file__).resolve().parents[1])
    assert r.returncode != 0 and len(r.stderr.strip().splitlines()) == 1 and "NOSUCH" in r.stderr, r.stderr
    assert not (tmp_path / "out").exists()


def test_prior_save_load_round_trip(tmp_path):
    phi = SDFDecoder(SDFDecoderConfig(latent_dim=8, width=16, depth=2))
    prior = ShapePrior(phi, torch.randn(3, 8), ["a", "b", "c"], [0, 1, 2], [0, 0, 0], {"note": "x"})
    weights, config = prior.save(tmp_path / "p")
    assert weights.suffix == ".safetensors" and config.suffix == ".json"
    back = load_prior(tmp_path / "p")
    x = torch.rand(10, 3)
    assert torch.equal(back.sdf(back.latents[1], x), phi(prior.latents[1], x))
    assert back.shape_names == ["a", "b", "c"] and back.info == {"note": "x"}
    assert not any(p.requires_grad for p in back.decoder.parameters())


def test_checkpoint_is_atomic_and_rejects_damage(tmp_path):
    path = tmp_path / "c.safetensors"
    save_checkpoint(path, {"w": torch.ones(3)}, {"epoch": 1})
    save_checkpoint(path, {"w": torch.zeros(3)}, {"epoch": 2})
    tensors, meta = load_checkpoint(path)
    assert meta == {"epoch": 2} and torch.equal(tensors["w"], torch.zeros(3))
    assert [p.name for p in tmp_path.iterdir()] == ["c.safetensors"]  # no temporary left
    path.write_bytes(path.read_bytes()[:20])
    with pytest.raises(ValueError, match="not a readable safetensors checkpoint"):
        load_checkpoint(path)


def test_shipped_clevr_prior_loads_and_reconstructs():
    """The prior inside the package: 27 latents with ids, and good shapes for a few of them."""
    from prismonet.shapes.evaluate import evaluate_prior
    from prismonet.shapes.pretrain import load_shape_set

    prior = load_prior()
    assert prior.latents.shape == (27, 8) and prior.decoder.cfg.latent_dim == 8
    assert prior.category_ids[:9] == [0] * 9 and prior.category_ids[-1] == 2 and prior.instance_ids[:3] == [0, 1, 2]
    full = load_shape_set("clevr")
    picks = [0, 13, 26]  # one shape per category
    subset = ShapeSet("clevr-subset", tuple(full.meshes[i] for i in picks), tuple(full.names[i] for i in picks), (0, 1, 2), (0, 4, 8))
    sub_prior = ShapePrior(prior.decoder, prior.latents[picks], list(subset.names), [0, 1, 2], [0, 4, 8])
    report = evaluate_prior(sub_prior, shape_set=subset, resolution=48, iou_resolution=48, chamfer_points=10000,
                            interpolation_pairs=2, progress=False)
    # recorded quality at resolution 64: mean IoU 0.986, mean Chamfer-L1 0.011 (BENCHMARKS.md)
    assert report["min_iou"] > 0.95, report
    assert report["max_chamfer_l1"] < 0.03, report
    assert report["interpolation_nonempty"] == 1.0


@pytest.mark.parametrize("skip", [None, 2])
def test_nograd_path_is_the_same_function(skip):
    """Without autograd the MLP runs in place on a flat buffer; it must compute exactly what the
    autograd path computes (float64, latents shared per ray and per point, and a skip layer)."""
    import prismonet.shapes.decoder as dec_mod
    from prismonet.model.texture import TextureField

    torch.manual_seed(0)
    phi = SDFDecoder(SDFDecoderConfig(latent_dim=5, width=16, depth=4, skip_layer=skip)).double()
    psi = TextureField(4, width=16).double()
    cases = [(phi, torch.randn(7, 1, 5), torch.randn(7, 9, 3)),  # one latent per ray (the root search)
             (phi, torch.randn(7, 9, 5), torch.randn(7, 9, 3)),  # one latent per point
             (phi, torch.randn(0, 1, 5), torch.randn(0, 2, 3)),  # a slot whose rays all miss: no points
             (psi, torch.randn(11, 4), torch.randn(11, 3)),      # texture field at hits
             (psi, torch.randn(0, 4), torch.randn(0, 3))]
    for net, z, x in cases:
        z, x = z.double(), x.double()
        with torch.enable_grad():
            ref = net(z, x)
        with torch.no_grad():
            fast = net(z, x)
        assert fast.shape == ref.shape
        assert torch.allclose(fast, ref, rtol=0, atol=1e-12)
    # a latent that does not broadcast into the points' shape takes the general path
    z, x = torch.randn(2, 3, 5).double(), torch.randn(3, 3).double()
    with torch.no_grad():
        assert phi._features_nograd(z, x) is None
        assert torch.equal(phi(z, x), phi(z, x))
    # and the switch for A/B benchmarks turns the fast path off
    try:
        dec_mod.INPLACE_NOGRAD = False
        with torch.no_grad():
            off = phi(cases[0][1].double(), cases[0][2].double())
    finally:
        dec_mod.INPLACE_NOGRAD = True
    with torch.no_grad():
        assert torch.allclose(off, phi(cases[0][1].double(), cases[0][2].double()), rtol=0, atol=1e-12)


def test_the_cars_prior_ships_with_its_sources_and_box():
    """Priors load by name (prismonet.assets.PRIORS); the cars prior has D_sh = 16, one code per seen car,
    a box tighter than the padded cube, and every mesh it learnt is attributed."""
    from prismonet.assets import asset_path
    from prismonet.model.config import ModelConfig
    from prismonet.model.prismonet import PriSMONet

    prior = load_prior("cars")
    assert prior.latents.shape == (8, 16)
    lo, hi = prior.bounds
    assert all(-1.1 <= a < -0.5 and 0.5 < b <= 1.1 for a, b in zip(lo, hi))
    assert (hi[0] - lo[0]) * (hi[2] - lo[2]) < 0.5 * 2.2**2  # long and flat: under half the cube's cross-section
    sources = asset_path("cars_prior_SOURCES.md").read_text()
    assert all(name in sources for name in prior.shape_names)
    model = PriSMONet(ModelConfig(prior="cars", tex_dim=15))
    assert model.sh_dim == 16 and model.render_settings().box == prior.bounds


@pytest.mark.parametrize("name,shapes", [("tableware", 13), ("chairs", 37)])
def test_the_other_shapenet_style_priors_ship_with_their_sources(name, shapes):
    """One code per seen mesh at D_sh = 16, a box inside the padded cube, every mesh attributed, and each
    decodes a surface: the SDF is negative somewhere on a grid over the box and positive at its corners."""
    from prismonet.assets import asset_path

    prior = load_prior(name)
    assert prior.latents.shape == (shapes, 16)
    lo, hi = prior.bounds
    assert all(-1.1 <= a < 0 < b <= 1.1 for a, b in zip(lo, hi))
    sources = asset_path(f"{name}_prior_SOURCES.md").read_text()
    assert all(n in sources for n in prior.shape_names)
    with torch.no_grad():
        z = prior.latents[:, None, :]
        axes = [torch.linspace(a, b, 32) for a, b in zip(lo, hi)]  # fine enough for thin chairs
        grid = torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).reshape(1, -1, 3).expand(shapes, -1, 3)
        inside = prior.decoder(z, grid).reshape(shapes, -1).amin(1)
        corner = prior.decoder(z, torch.tensor([[1.05, 1.05, 1.05]]).expand(shapes, 1, 3))[..., 0]
    assert (inside < 0).all() and (corner > 0).all()


def test_fit_code_recovers_a_training_shape_and_nearest_code_names_it():
    """A training shape of the shipped Clevr prior, encoded again from its SDF samples (the decoder frozen): the fitted
    code's clamped L1 is as low as the trained code's (within 20 %), and the nearest training code is that shape's own.
    Bad samples are one clear error."""
    import numpy as np

    from prismonet.shapes.clevr_set import shape_mesh
    from prismonet.shapes.code_fit import CodeFitConfig, fit_code, nearest_code
    from prismonet.shapes.pretrain import clamped_l1
    from prismonet.shapes.prior import load_prior
    from prismonet.shapes.sdf_samples import SamplingConfig, sample_sdf

    prior = load_prior()
    k = 22  # a cube with its own proportions: far from the mean code the fit starts at
    v, f = shape_mesh(k)
    p, s = (torch.from_numpy(x) for x in sample_sdf(v, f, SamplingConfig(num_points=8192), np.random.default_rng(3)))
    with torch.no_grad():
        own = float(clamped_l1(prior.sdf(prior.latents[k].expand(len(p), -1), p), s, 0.1))
        start = float(clamped_l1(prior.sdf(prior.latents.mean(0).expand(len(p), -1), p), s, 0.1))
    z, err = fit_code(prior, p, s, CodeFitConfig(steps=300))
    assert start > 2 * own and err <= 1.2 * own + 1e-4
    assert nearest_code(prior, p, s)[0] == k
    with pytest.raises(ValueError, match="expected points"):
        fit_code(prior, p, s[:-1])
