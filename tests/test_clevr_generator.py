"""The CLEVR-style generator: exact depth, placement, determinism, variants, bad settings."""

import numpy as np
import pytest

from prismonet.data.clevr import (
    COLOR_RGB,
    ClevrConfig,
    ObjectSpec,
    SceneSpec,
    check_placement_feasible,
    clevr_camera,
    sample_scene,
)
from prismonet.data.errors import PlacementError
from prismonet.data.generate import generate_clevr, render_range
from prismonet.data.raycast_gt import render_scene, world_rays
from prismonet.shapes.clevr_set import clevr_shapes, shape_mesh

CFG = ClevrConfig()


def test_clevr_colours_are_the_published_table():
    from prismonet.data.clevr import CLEVR_COLORS

    assert COLOR_RGB[:8] == (
        (87, 87, 87), (173, 35, 35), (42, 75, 215), (29, 105, 20),
        (129, 74, 25), (129, 38, 192), (41, 208, 208), (255, 238, 51),
    )
    assert CFG.colors == CLEVR_COLORS == tuple(range(8))  # the default draws CLEVR's eight alone


def test_extra_colours_are_drawn_only_when_asked(tmp_path):
    """``colors`` (``--colors``): white, silver and black objects for real tables, opt-in; the default stream is
    CLEVR's (``test_varying_object_counts`` checks it against the shipped samples bit for bit)."""
    from prismonet.cli import main
    from prismonet.data.dataset import SceneDataset

    cfg = ClevrConfig(num_objects=4, min_objects=1, image_size=24, colors=(8, 10))
    arrays = render_range(cfg.to_dict(), 0, 0, 12)
    drawn = {int(c) for i, n in enumerate(arrays["obj_count"]) for c in arrays["obj_color"][i, :n]}
    assert drawn == {8, 10}
    # a white object renders grey-white: equal channels, far brighter than CLEVR's grey
    white = render_range(ClevrConfig(num_objects=1, image_size=32, colors=(8,)).to_dict(), 0, 0, 1)
    px = white["rgb"][0][white["instance"][0] == 1].astype(np.float64)  # (n, 3), 0-255
    assert len(px) and np.array_equal(px[:, 0], px[:, 1]) and np.array_equal(px[:, 1], px[:, 2])
    assert px.max() > 200  # CLEVR's grey, lit fully, stays at 87
    # read back from a dataset's meta (JSON lists) and rejected when out of range
    assert ClevrConfig(**{**cfg.to_dict(), "colors": [8, 10]}) == cfg
    with pytest.raises(ValueError, match="colors: expected colour ids in 0..10"):
        ClevrConfig(colors=(11,))
    with pytest.raises(ValueError, match="colors"):
        ClevrConfig(colors=())
    # the command line takes names, ids and 'clevr'; a wrong name is one line
    assert main(["data", "clevr", "--objects", "2", "--colors", "white,9,black", "--split", "0,0,3", "--workers", "1", "--quiet",
                 "--out", str(tmp_path / "w")]) == 0
    ds = SceneDataset(tmp_path / "w", "test")
    assert set(ds.arrays["obj_color"][ds.arrays["obj_color"] >= 0].tolist()) <= {8, 9, 10}
    assert main(["data", "clevr", "--colors", "clevr,pink", "--out", str(tmp_path / "p")]) == 2
    assert not (tmp_path / "p").exists()


def test_shape_set_has_nine_scalings_per_category():
    shapes = clevr_shapes()
    assert len(shapes) == 27
    for cat in range(3):
        ext = {s.half_extents for s in shapes if s.category_id == cat}
        assert len(ext) == 9 and all(max(e) == 1.0 for e in ext)


def _analytic_sphere(spec: SceneSpec, centre, radius):
    o, d = world_rays(spec)
    oc = o - np.asarray(centre)
    a = (d * d).sum(1)
    b = 2 * (oc * d).sum(1)
    c = (oc * oc).sum(1) - radius**2
    disc = b * b - 4 * a * c
    hit = disc >= 0
    t = np.where(hit, (-b - np.sqrt(np.where(hit, disc, 0))) / (2 * a), np.inf)
    # closest approach of each ray to the centre, for the silhouette test
    closest = np.linalg.norm(np.cross(oc, d), axis=1) / np.linalg.norm(d, axis=1)
    t_ground = np.where(d[:, 2] < 0, (spec.ground_z - o[:, 2]) / d[:, 2], np.inf)
    return t, hit, closest, t_ground


def test_sphere_depth_matches_analytic_ray_sphere_intersection():
    centre, r = (0.2, -0.3, 0.5), 0.5
    cam = clevr_camera(CFG)
    spec = SceneSpec((ObjectSpec(0, 0, 1, r, centre, 0.3),), cam, 0.0, CFG.ground_color)
    out = render_scene(spec, CFG)
    t, hit, closest, t_ground = _analytic_sphere(spec, centre, r)
    depth, inst = out.depth.reshape(-1), out.instance.reshape(-1)
    # The icosphere is inscribed in the sphere: its faces lie at most one sagitta inside,
    # the gap between the sphere and its deepest face plane.
    v, f = shape_mesh(0)
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    plane_dist = np.abs((n / np.linalg.norm(n, axis=1, keepdims=True) * v[f[:, 0]]).sum(1))
    sagitta = r * (1.0 - plane_dist.min())
    both = hit & (inst == 1)
    assert both.sum() > 50
    err = depth[both] - t[both]
    assert err.min() >= -1e-4  # never in front of the true sphere (float32 rounding only)
    # along a ray at incidence angle theta a sagitta costs sagitta / cos(theta) of depth
    inner = both & (closest < 0.85 * r)
    cos_incidence = np.sqrt(1.0 - (closest[inner] / r) ** 2)
    assert np.all(np.abs(depth[inner] - t[inner]) <= sagitta / cos_incidence + 1e-4)
    # mask differs only at silhouette pixels: rays passing within a sagitta of the rim
    wrong = hit != (inst == 1)
    assert np.all(np.abs(closest[wrong] - r) <= sagitta + 1e-4)
    # the ground is a plane at z = 0: exact, clipped at far_depth
    ground = ~hit
    assert np.allclose(depth[ground], np.minimum(t_ground[ground], CFG.far_depth), atol=1e-4)
    # Lambertian: RGB is the CLEVR colour times one shade factor per pixel
    rgb = out.rgb.reshape(-1, 3)[inner].astype(float)
    shade = rgb / np.asarray(COLOR_RGB[1])
    assert np.allclose(shade[:, 0], shade[:, 1], atol=0.03) and np.all(shade[:, 0] >= CFG.ambient - 0.01)


def _pairwise_disjoint(spec: SceneSpec) -> bool:
    """No object's surface samples lie inside another object (open3d occupancy, independent of
    the generator's disc test)."""
    import open3d as o3d
    import trimesh

    meshes = [obj.world_mesh() for obj in spec.objects]
    for i, (vi, fi) in enumerate(meshes):
        pts = trimesh.Trimesh(vi, fi).sample(3000, seed=i).astype(np.float32)
        for j, (vj, fj) in enumerate(meshes):
            if i == j:
                continue
            scene = o3d.t.geometry.RaycastingScene()
            scene.add_triangles(o3d.core.Tensor(vj.astype(np.float32)), o3d.core.Tensor(fj.astype(np.uint32)))
            if scene.compute_occupancy(o3d.core.Tensor(pts)).numpy().any():
                return False
    return True


@pytest.mark.parametrize("n", [2, 5])
def test_placement_in_bounds_on_ground_and_disjoint(n):
    cfg = ClevrConfig(num_objects=n)
    cam = clevr_camera(cfg)
    for seed in range(15):
        spec = sample_scene(np.random.default_rng(seed), cfg, cam)
        assert len(spec.objects) == n
        for obj in spec.objects:
            assert abs(obj.position[0]) <= 1.5 and abs(obj.position[1]) <= 1.5
            assert cfg.scale_range[0] <= obj.scale <= cfg.scale_range[1]
            assert obj.world_mesh()[0][:, 2].min() == pytest.approx(0.0, abs=1e-9)  # resting on the ground
        assert _pairwise_disjoint(spec)


def test_disjoint_check_detects_overlap():
    """The independent check used above can fail."""
    cam = clevr_camera(CFG)
    a = ObjectSpec(18, 2, 0, 0.5, (0.0, 0.0, 0.5), 0.0)
    b = ObjectSpec(0, 0, 1, 0.5, (0.6, 0.0, 0.5), 0.0)
    assert not _pairwise_disjoint(SceneSpec((a, b), cam, 0.0, CFG.ground_color))


def test_full_rotation_objects_rest_on_ground_and_are_disjoint():
    cfg = ClevrConfig(num_objects=4, full_rotation=True)
    spec = sample_scene(np.random.default_rng(3), cfg, clevr_camera(cfg))
    assert any(abs(o.axis[2]) < 0.99 for o in spec.objects)
    for obj in spec.objects:
        assert obj.world_mesh()[0][:, 2].min() == pytest.approx(0.0, abs=1e-9)
    assert _pairwise_disjoint(spec)


def test_random_height_lowers_ground_below_every_object():
    cfg = ClevrConfig(num_objects=4, random_height=True)
    assert cfg.ground_z < -1.5
    for seed in range(5):
        spec = sample_scene(np.random.default_rng(seed), cfg, clevr_camera(cfg))
        zs = [o.position[2] for o in spec.objects]
        assert all(-1.5 <= z <= 1.5 for z in zs)
        assert all(o.world_mesh()[0][:, 2].min() > spec.ground_z for o in spec.objects)
        assert _pairwise_disjoint(spec)


def test_noisy_depth_has_sigma_eta_d_squared():
    clean = render_range(CFG.to_dict(), 7, 0, 3)
    noisy = render_range(ClevrConfig(depth_noise_eta=1e-3).to_dict(), 7, 0, 3)
    assert np.array_equal(clean["rgb"], noisy["rgb"])
    d = clean["depth"].astype(np.float64)
    keep = d < CFG.far_depth - 1.0  # away from the clip
    z = (noisy["depth"][keep] - d[keep]) / (1e-3 * d[keep] ** 2)
    assert abs(z.mean()) < 0.05 and abs(z.std() - 1.0) < 0.05


def test_generation_is_deterministic_given_seed():
    a = render_range(CFG.to_dict(), 11, 5, 9)
    b = render_range(CFG.to_dict(), 11, 5, 9)
    c = render_range(CFG.to_dict(), 12, 5, 9)
    for k in a:
        assert np.array_equal(a[k], b[k])
    assert not np.array_equal(a["rgb"], c["rgb"])
    # scene i does not depend on where its range starts
    d = render_range(CFG.to_dict(), 11, 7, 8)
    assert np.array_equal(d["rgb"][0], a["rgb"][2])


def test_generate_does_not_depend_on_workers(tmp_path):
    from prismonet.data.dataset import SceneDataset

    generate_clevr(tmp_path / "a", CFG, split=(6, 1, 1), seed=5, workers=1, progress=False, chunk=3)
    generate_clevr(tmp_path / "b", CFG, split=(6, 1, 1), seed=5, workers=2, progress=False, chunk=3)
    for split in ("train", "val", "test"):
        a, b = SceneDataset(tmp_path / "a", split), SceneDataset(tmp_path / "b", split)
        for k in a.arrays:
            assert np.array_equal(a.arrays[k], b.arrays[k]), (split, k)


def test_camera_jitter_moves_camera_within_bounds():
    cfg = ClevrConfig(camera_jitter=0.5)
    eyes = [sample_scene(np.random.default_rng(s), cfg).camera.center.numpy() for s in range(4)]
    base = np.asarray(cfg.camera_eye)
    assert all(np.abs(e - base).max() <= 0.5 + 1e-5 for e in eyes)
    assert len({tuple(np.round(e, 4)) for e in eyes}) == 4


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"num_objects": 0}, "num_objects must be positive"),
        ({"num_objects": -3}, "num_objects must be positive"),
        ({"scale_range": (0.5, 0.2)}, "scale_range"),
        ({"image_size": 0}, "image_size must be positive"),
    ],
)
def test_bad_config_is_rejected(kwargs, message):
    with pytest.raises(ValueError, match=message):
        ClevrConfig(**kwargs)


def test_impossible_placement_is_rejected_quickly():
    with pytest.raises(PlacementError, match="impossible placement: 40 objects"):
        check_placement_feasible(ClevrConfig(num_objects=40))
    # just under the upfront bound, rejection sampling gives up with a clear error too
    with pytest.raises(PlacementError, match="impossible placement"):
        sample_scene(np.random.default_rng(0), ClevrConfig(num_objects=25, scale_range=(0.35, 0.35)))


def test_varying_object_counts():
    """``min_objects``: each scene draws its count uniformly from min..max; arrays are padded to the max."""
    from collections import Counter

    from prismonet.data.clevr import ClevrConfig, sample_scene

    cfg = ClevrConfig(num_objects=8, min_objects=1, area_half=2.5)
    counts = Counter(len(sample_scene(np.random.default_rng([3, i]), cfg).objects) for i in range(240))
    assert sorted(counts) == list(range(1, 9)) and min(counts.values()) >= 15  # 30 expected each
    fixed = ClevrConfig(num_objects=3)
    assert all(len(sample_scene(np.random.default_rng([3, i]), fixed).objects) == 3 for i in range(5))
    # the fixed-count stream is unchanged by the option: the shipped samples (test scenes 0-1 of
    # `data clevr --seed 0`, global indices 10000-10001, made before it existed) come out bit for bit
    from prismonet.assets import shipped_samples
    from prismonet.data.dataset import SceneDataset

    shipped = SceneDataset(shipped_samples(), "test").arrays
    again = render_range(ClevrConfig().to_dict(), 0, 10000, 10002)
    assert np.array_equal(again["rgb"], shipped["rgb"][:2]) and np.array_equal(again["obj_position"], shipped["obj_position"][:2])
    with pytest.raises(ValueError, match="min_objects"):
        ClevrConfig(num_objects=3, min_objects=4)
    arrays = render_range(ClevrConfig(num_objects=4, min_objects=1, image_size=16).to_dict(), 0, 0, 6)
    assert arrays["obj_position"].shape[1] == 4 and set(arrays["obj_count"].tolist()) <= {1, 2, 3, 4}
    for i, n in enumerate(arrays["obj_count"]):
        assert (arrays["obj_shape"][i, n:] == -1).all() and arrays["instance"][i].max() <= n


def test_randomized_scenes_draw_camera_ground_and_light_within_their_ranges():
    import math
    from dataclasses import replace

    import torch

    from prismonet.data.clevr import ClevrConfig, RandomizeConfig, sample_scene

    r = RandomizeConfig()
    cfg = ClevrConfig(randomize=r)
    specs = [sample_scene(np.random.default_rng([5, i]), cfg) for i in range(24)]
    eyes = np.array([s.camera.T_world_cam[:3, 3].numpy() for s in specs])
    assert len({tuple(np.round(e, 4)) for e in eyes}) == 24  # a camera per scene
    d0 = float(np.linalg.norm(cfg.camera_eye))
    for s in specs:
        T = s.camera.T_world_cam.double()
        fwd = T[:3, 2]
        elev = math.degrees(math.asin(-fwd[2]))  # the camera looks at a point on the ground
        assert r.camera_elevation_deg[0] - 1e-6 <= elev <= r.camera_elevation_deg[1] + 1e-6
        target = T[:3, 3] + fwd * (-T[2, 3] / fwd[2])
        assert abs(target[0]) <= r.look_at_jitter + 1e-6 and abs(target[1]) <= r.look_at_jitter + 1e-6
        dist = float((T[:3, 3] - target).norm())
        assert d0 * r.camera_distance[0] - 1e-6 <= dist <= d0 * r.camera_distance[1] + 1e-6
        g = np.asarray(s.ground_color, float)
        assert abs(g[0] + g[2] - 2 * g[1]) <= 1.0 and r.ground_gray[0] - 1 <= g[1] <= r.ground_gray[1] + 1
        direction, ambient, diffuse = s.light
        assert np.linalg.norm(direction) == pytest.approx(1.0) and r.ambient[0] <= ambient <= r.ambient[1]
        assert r.brightness[0] - 1e-9 <= ambient + diffuse <= r.brightness[1] + 1e-9
        # every object centre projects inside the image (the focal length fits the area, scaled down)
        T_cw = torch.linalg.inv(T)
        for o in s.objects:
            x = T_cw[:3, :3] @ torch.tensor(o.position, dtype=torch.float64) + T_cw[:3, 3]
            uv = (s.camera.K.double() @ x)[:2] / x[2]
            assert (uv >= -0.5).all() and (uv <= cfg.image_size - 0.5).all()
    # the scene's own light shades it: the same layout under the config's light renders differently
    s = specs[0]
    a = render_scene(s, cfg).rgb
    b = render_scene(replace(s, light=None), cfg).rgb
    inst = render_scene(s, cfg).instance
    assert (a[inst == 0] == np.asarray(s.ground_color, np.uint8)).all()  # the flat ground has the drawn colour
    assert np.abs(a.astype(int) - b.astype(int))[inst > 0].max() > 5


def test_randomize_range_overrides_one_draw(tmp_path):
    """``--randomize-range focal_scale=2,2`` doubles every scene's focal length against ``1,1`` with the
    same seed (the draw is made either way, so the rest of the scene is the same)."""
    import torch

    from prismonet.cli import main
    from prismonet.data.dataset import SceneDataset

    for f in ("1", "2"):
        assert main(["data", "clevr", "--objects", "2", "--randomize-range", f"focal_scale={f},{f}", "--split", "0,0,4",
                     "--workers", "1", "--quiet", "--out", str(tmp_path / f)]) == 0
    a, b = (SceneDataset(tmp_path / f, "test").batch(range(4)) for f in ("1", "2"))
    assert torch.allclose(b.K[:, 0, 0], 2 * a.K[:, 0, 0], rtol=1e-6)
    assert torch.equal(a.T_world_cam, b.T_world_cam) and torch.equal(a.obj_position, b.obj_position)


def test_shadow_directions_are_the_light_and_a_cone_around_it():
    from prismonet.data.raycast_gt import SHADOW_RAYS, SHADOW_SPREAD_DEG, shadow_directions

    light = np.array([0.35, -0.55, 1.0]) / np.linalg.norm([0.35, -0.55, 1.0])
    dirs = shadow_directions(light)
    assert dirs.shape == (SHADOW_RAYS, 3) and np.allclose(np.linalg.norm(dirs, axis=1), 1.0)
    assert np.allclose(dirs[0], light)
    assert np.allclose(np.degrees(np.arccos(dirs[1:] @ light)), SHADOW_SPREAD_DEG)
    assert np.allclose(dirs[1:].mean(0) / np.linalg.norm(dirs[1:].mean(0)), light)  # evenly around it


def test_a_sphere_casts_its_shadow_where_the_light_line_meets_the_ground():
    """A sphere of radius 0.5 at (0, 0, 1) under a light along (1, 0, 1): the ground point (-1, 0, 0) lies on the
    line from the centre away from the light (fully shadowed), (2, 0, 0) is lit, and between the two a point whose
    central shadow ray passes at the rim is partly shadowed."""
    import open3d as o3d

    from prismonet.data.raycast_gt import shadow_fraction

    spec = SceneSpec((ObjectSpec(0, 0, 1, 0.5, (0.0, 0.0, 1.0), 0.0),), clevr_camera(CFG), 0.0, CFG.ground_color)
    v, f = spec.objects[0].world_mesh()
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(v.astype(np.float32)), o3d.core.Tensor(f.astype(np.uint32)))
    light = np.array([1.0, 0.0, 1.0]) / np.sqrt(2.0)
    # the central ray from (x, 0, 0) passes the centre at distance |x + 1| / sqrt(2): at the rim for x = -1 + 0.5 sqrt(2)
    xs = np.array([-1.0, -1.0 + 0.5 * np.sqrt(2.0), 2.0])
    pts = np.stack([xs, np.zeros(3), np.zeros(3)], 1)
    frac = shadow_fraction(scene, pts, np.tile([0.0, 0.0, 1.0], (3, 1)), light)
    assert frac[0] == 1.0 and frac[2] == 0.0 and 0.0 < frac[1] < 1.0


def test_cast_shadows_darken_only_and_keep_the_scene():
    """With ``cast_shadows`` the same scene has the same depth and instances; no pixel gets brighter; shadowed ground
    pixels lose exactly the light's share ``diffuse cos / (ambient + diffuse cos)`` where fully blocked."""
    from dataclasses import replace

    cfg = ClevrConfig(num_objects=4)
    spec = sample_scene(np.random.default_rng(3), cfg)
    plain, shadowed = render_scene(spec, cfg), render_scene(spec, replace(cfg, cast_shadows=True))
    assert np.array_equal(plain.depth, shadowed.depth) and np.array_equal(plain.instance, shadowed.instance)
    assert np.all(shadowed.rgb.astype(int) <= plain.rgb.astype(int))
    ground = plain.instance == 0
    darker = ground & (shadowed.rgb.sum(-1) < plain.rgb.sum(-1))
    assert darker.sum() > 20  # a shadow on the ground in view
    light = np.asarray(cfg.light_dir) / np.linalg.norm(cfg.light_dir)
    share = cfg.diffuse * light[2] / (cfg.ambient + cfg.diffuse * light[2])
    umbra = np.asarray(cfg.ground_color) * (1.0 - share)
    deepest = shadowed.rgb[darker].astype(float).min(0)
    assert np.allclose(deepest, np.rint(umbra), atol=1.0)
    assert ClevrConfig(**{**cfg.to_dict(), "cast_shadows": True}).cast_shadows  # read back from a dataset's meta
