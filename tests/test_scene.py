"""The latent scene: save/load, re-rendering, editing with L_int, export, novel views."""

import math

import numpy as np
import pytest
import torch

from prismonet.assets import shipped_samples
from prismonet.data.dataset import SceneDataset
from prismonet.geometry.camera import Camera
from prismonet.model.io import load_model, prior_fingerprint
from prismonet.model.losses import intersection_loss
from prismonet.render import SceneParams
from prismonet.scene import LatentScene, LatentSceneError
from prismonet.scene import edit, export, novel_view
from prismonet.shapes.clevr_set import clevr_shapes


@pytest.fixture(scope="module")
def model():
    return load_model("shipped")[0]


@pytest.fixture(scope="module")
def inferred(model):
    """The shipped model's forward pass on two shipped test scenes."""
    ds = SceneDataset(shipped_samples(), split="test")
    b = ds.batch([0, 1])
    with torch.no_grad():
        out = model(b.rgb, b.K, b.T_world_cam, b.ground_z)
    return b, out


@pytest.fixture
def scene(model, inferred):
    b, out = inferred
    return LatentScene.from_output(out, b, 1, prior_fingerprint(model.prior))


def shape_scene(model, shape_id, positions, yaws_deg, scales, like: LatentScene) -> LatentScene:
    """Objects of a known training shape at given poses, seen by ``like``'s camera."""
    n = len(positions)
    z = model.prior.latents[shape_id].expand(n, -1).clone()
    cs = torch.tensor([[math.cos(math.radians(a)), math.sin(math.radians(a))] for a in yaws_deg])
    return LatentScene(z, like.z_tex[:1].expand(n, -1).clone(), torch.tensor(positions, dtype=torch.float32), cs,
                       torch.tensor(scales, dtype=torch.float32), like.bg_color, like.camera, 0.0, like.prior_fingerprint)


# -- the scene as data ----------------------------------------------------------------------
def test_rerender_with_original_camera_reproduces_model_render(model, inferred):
    b, out = inferred
    for i in range(2):
        s = LatentScene.from_output(out, b, i, prior_fingerprint(model.prior))
        comp, depth, mask, color, _ = s.render(model)
        # the same pipeline; only batched-matmul rounding differs (the model rendered both at once)
        assert torch.allclose(comp.image[0], out.composite.image[i], rtol=0, atol=1e-6)
        assert torch.allclose(comp.depth[0], out.composite.depth[i], rtol=0, atol=1e-5)
        assert torch.equal(comp.instance[0], out.composite.instance[i])
        assert torch.equal(mask[0], out.obj_mask[i])


def test_json_round_trip_renders_the_same(model, scene, tmp_path):
    path = scene.save(tmp_path / "s.json")
    back = LatentScene.load(path)
    for name in ("z_sh", "z_tex", "position", "cos_sin", "scale", "bg_color"):
        assert torch.equal(getattr(back, name), getattr(scene, name)), name
    assert torch.equal(back.render(model)[0].image, scene.render(model)[0].image)


def test_bad_scene_files(model, scene, tmp_path):
    with pytest.raises(LatentSceneError, match="no such"):
        LatentScene.load(tmp_path / "missing.json")
    (tmp_path / "bad.json").write_text("{not json")
    with pytest.raises(LatentSceneError, match="not valid JSON"):
        LatentScene.load(tmp_path / "bad.json")
    d = scene.to_dict()
    with pytest.raises(LatentSceneError, match="format"):
        LatentScene.from_dict({**d, "format": "other"})
    broken = {**d, "objects": [{k: v for k, v in o.items() if k != "z_sh"} for o in d["objects"]]}
    with pytest.raises(LatentSceneError, match="malformed"):
        LatentScene.from_dict(broken)
    nan = {**d, "objects": [{**o, "scale": float("nan")} for o in d["objects"]]}
    with pytest.raises(LatentSceneError, match="non-finite"):
        LatentScene.from_dict(nan)
    other = LatentScene.from_dict({**d, "prior_fingerprint": "0123456789abcdef"})
    with pytest.raises(LatentSceneError, match="shape prior"):
        other.render(model)


# -- editing --------------------------------------------------------------------------------
def test_remove_changes_exactly_that_object(scene):
    out = edit.remove(scene, 1)
    assert out.num_objects == scene.num_objects - 1
    for name in ("z_sh", "z_tex", "position", "cos_sin", "scale"):
        assert torch.equal(getattr(out, name), getattr(scene, name)[[0, 2]])
    assert scene.num_objects == 3  # the input is untouched
    with pytest.raises(LatentSceneError, match="objects 0..2"):
        edit.remove(scene, 3)


def test_swaps_change_exactly_the_intended_objects(scene):
    s = edit.swap_latents(scene, 0, 2, "shape")
    assert torch.equal(s.z_sh[0], scene.z_sh[2]) and torch.equal(s.z_sh[2], scene.z_sh[0])
    assert torch.equal(s.z_sh[1], scene.z_sh[1])
    for name in ("z_tex", "position", "cos_sin", "scale"):
        assert torch.equal(getattr(s, name), getattr(scene, name)), name
    t = edit.swap_latents(scene, 1, 0, "texture")
    assert torch.equal(t.z_tex[[1, 0, 2]], scene.z_tex) and torch.equal(t.z_sh, scene.z_sh)
    p = edit.swap_places(scene, 0, 1)
    assert torch.equal(p.position[[1, 0, 2]], scene.position)
    for name in ("z_sh", "z_tex", "cos_sin", "scale"):
        assert torch.equal(getattr(p, name), getattr(scene, name)), name


def test_move_add_and_render_after_edit(model, scene):
    m = edit.move(scene, 2, position=[0.5, -0.5, 0.3], yaw_deg=90.0, scale=0.4)
    assert m.position[2].tolist() == pytest.approx([0.5, -0.5, 0.3])
    assert float(m.yaw[2]) == pytest.approx(math.pi / 2)
    assert torch.equal(m.position[:2], scene.position[:2])
    a = edit.add(scene, scene, 0, position=[-1.0, 1.0, 0.35])
    assert a.num_objects == 4 and torch.equal(a.z_sh[3], scene.z_sh[0])
    comp, depth, mask, _, _ = a.render(model)
    assert mask.shape[1] == 4 and torch.isfinite(comp.image).all()


def test_intersection_loss_is_exact_for_spheres():
    """Two radius-r spheres with centres d apart: phi_i + phi_j = d - 2r on the segment, so
    L_int = max(2r - d, 0) exactly."""

    class Spheres:
        def sdf_world(self, params, x):  # (B, K, P, 3) -> (B, K, P)
            return (x - params.position[:, :, None]).norm(dim=-1) - params.scale[:, :, None]

    for d, r in [(3.0, 1.0), (2.0, 1.0), (1.5, 1.0), (0.4, 0.5)]:
        p = SceneParams(torch.zeros(1, 2, 1), torch.zeros(1, 2, 1), torch.tensor([[[0.0, 0, 0], [d, 0, 0]]]),
                        torch.tensor([[[1.0, 0], [1.0, 0]]]), torch.tensor([[r, r]]))
        assert float(intersection_loss(Spheres(), p, 16)[0]) == pytest.approx(max(2 * r - d, 0.0), abs=1e-6)


def test_intersection_score_zero_apart_positive_overlapping(model, scene):
    cube = next(s.shape_id for s in clevr_shapes() if s.category == "cube" and s.half_extents == (1.0, 1.0, 1.0))
    apart = shape_scene(model, cube, [[-1.0, -1.0, 0.4], [1.0, 1.0, 0.4]], [0, 30], [0.4, 0.4], scene)
    assert edit.intersection_score(model, apart) == 0.0
    assert edit.checked(model, apart) is apart
    overlap = edit.move(apart, 1, position=[-0.7, -1.0, 0.4])
    assert edit.intersection_score(model, overlap) > 0.05
    with pytest.raises(edit.EditRejected, match="1-0"):
        edit.checked(model, overlap)


# -- export ---------------------------------------------------------------------------------
def test_exported_mesh_bounds_match_pose_and_scale(model, scene, tmp_path):
    spec = next(s for s in clevr_shapes() if s.category == "cube" and s.half_extents == (1.0, 0.5, 0.75))
    pos, s = [0.3, -0.2, 0.45], 0.6
    sc = shape_scene(model, spec.shape_id, [pos], [90.0], [s], scene)
    mesh = export.object_mesh(model, sc, 0, resolution=48)
    # yaw 90 deg turns the object's x half-extent onto world y and its y onto world x
    half = np.array([0.5, 1.0, 0.75]) * s
    lo, hi = mesh.bounds
    assert np.allclose(lo, np.array(pos) - half, atol=0.04), lo
    assert np.allclose(hi, np.array(pos) + half, atol=0.04), hi
    assert mesh.visual.vertex_colors.shape == (len(mesh.vertices), 4)
    # written and read back in each format
    import trimesh

    for ext in ("ply", "obj", "glb"):
        path = export.write_mesh(mesh, tmp_path / f"m.{ext}")
        back = trimesh.load(path, force="mesh")
        assert np.allclose(back.bounds, mesh.bounds, atol=1e-5), ext
    with pytest.raises(ValueError, match="use .ply"):
        export.write_mesh(mesh, tmp_path / "m.stl")


def test_point_cloud_size_and_reprojection(model, scene):
    comp = scene.render(model)[0]
    depth = comp.depth[0, 0]
    far = model.render_settings().far_depth
    pc = export.point_cloud(comp.image[0], depth, scene.camera, max_depth=far)
    valid = (depth > 0) & (depth < far)
    pts = torch.tensor(np.asarray(pc.points), dtype=torch.float32)
    assert len(pts) == int(valid.sum())
    uv = scene.camera.world_to_pixels(pts)
    v, u = torch.nonzero(valid, as_tuple=True)
    assert torch.allclose(uv, torch.stack([u, v], 1).float(), atol=2e-3)
    rgb = torch.tensor(np.asarray(pc.colors), dtype=torch.float32)
    assert torch.allclose(rgb, comp.image[0][:, v, u].T, atol=1e-6)


def test_export_scene_writes_everything(model, inferred, tmp_path):
    b, out = inferred
    sc = LatentScene.from_output(out, b, 0, prior_fingerprint(model.prior))
    w = export.export_scene(model, sc, tmp_path, "obj", resolution=24, input_rgbd=(b.rgb[0], b.depth[0]))
    assert {"scene_json", "scene_mesh", "points_rendered", "points_input", "object_0", "object_2"} <= set(w)
    assert all(p.is_file() and p.stat().st_size > 0 for p in w.values())
    assert LatentScene.load(w["scene_json"]).num_objects == 3


# -- novel views ----------------------------------------------------------------------------
def test_orbit_starts_at_the_original_camera(model, scene, tmp_path):
    cams = novel_view.orbit_cameras(scene, 8)
    assert torch.allclose(cams[0].T_world_cam, scene.camera.T_world_cam, atol=1e-5)
    # a quarter turn keeps the height and the distance to the orbit centre
    c = novel_view.orbit_center(scene)
    e0, e2 = cams[0].T_world_cam[:3, 3], cams[2].T_world_cam[:3, 3]
    assert float(e2[2]) == pytest.approx(float(e0[2]), abs=1e-5)
    assert float((e2 - c).norm()) == pytest.approx(float((e0 - c).norm()), abs=1e-5)
    assert float(torch.dot(e0[:2] - c[:2], e2[:2] - c[:2])) == pytest.approx(0.0, abs=1e-4)
    # the first view renders the original image (up to rounding in look_at)
    img0 = novel_view.render_view(model, scene, cams[0])[0]
    assert (img0 - scene.render(model)[0].image[0]).abs().gt(1e-3).float().mean() < 0.01
    pngs, gif = novel_view.render_orbit(model, scene, tmp_path, frames=4, size=32, progress=False)
    from PIL import Image

    with Image.open(gif) as im:
        assert im.n_frames == 4 and im.size == (32, 32)
    assert len(pngs) == 4 and all(p.is_file() for p in pngs)


def test_render_from_a_given_pose_sees_the_object(model, scene):
    from prismonet.geometry.camera import look_at

    target = scene.position[0]
    cam = Camera(scene.camera.K, look_at(target + torch.tensor([0.0, -4.0, 3.0]), target), scene.camera.height, scene.camera.width)
    img, depth, inst = novel_view.render_view(model, scene, cam)
    assert inst[28:36, 28:36].eq(1).any()  # object 0 is at the image centre


def test_wrong_shapes_are_named(scene):
    from dataclasses import replace

    with pytest.raises(LatentSceneError, match=r"position: expected shape \(3, 3\)"):
        replace(scene, position=scene.position[:, :2])
    with pytest.raises(LatentSceneError, match=r"scale: expected shape \(3,\)"):
        replace(scene, scale=scene.scale[:2])
    with pytest.raises(ValueError, match=r"rgb: expected shape \(3, 64, 64\)"):
        export.point_cloud(torch.zeros(3, 32, 32), torch.ones(64, 64), scene.camera)


def test_from_output_keeps_the_decoded_slots_and_the_whole_background(model, inferred):
    """A stopped or pruned output (``params.active``) gives the active slots only, in order, and the scene's
    background colour whole; ``slots`` picks slots by their index in the output."""
    from dataclasses import replace as dc_replace

    b, out = inferred
    K = out.latents.params.z_sh.shape[1]
    active = torch.zeros(2, K, dtype=torch.bool)
    active[1, [0, K - 1]] = True
    stopped = dc_replace(out, latents=dc_replace(out.latents, params=dc_replace(out.latents.params, active=active)))
    s = LatentScene.from_output(stopped, b, 1, "x")
    assert s.num_objects == 2 and s.bg_color.shape == (3,)
    assert torch.equal(s.position, out.latents.params.position[1, [0, K - 1]])
    assert torch.equal(s.bg_color, out.latents.bg_color[1])
    picked = LatentScene.from_output(out, b, 1, "x", slots=[K - 1])
    assert torch.equal(picked.z_sh, out.latents.params.z_sh[1, [K - 1]])


def test_supersampled_view_keeps_depth_and_instances(clevr3):
    """``supersample``: the image anti-aliased; inside an object, away from its outline, the colour is the one-ray
    render's up to the texture's variation within a pixel; depth and instances are the one-ray render's. On ``clevr3``,
    whose shapes are smooth: the default's cubes have edges inside an object's outline, where shading jumps within a
    pixel as it does at the outline."""
    import torch.nn.functional as F

    model, b, out = clevr3
    scene = LatentScene.from_output(out, b, 1, prior_fingerprint(model.prior))

    one = novel_view.render_view(model, scene, scene.camera)
    aa = novel_view.render_view(model, scene, scene.camera, supersample=3)
    assert torch.equal(one[1], aa[1]) and torch.equal(one[2], aa[2])
    inst = one[2].float()[None, None]
    uniform = (F.max_pool2d(inst, 3, 1, 1) == -F.max_pool2d(-inst, 3, 1, 1))[0, 0]  # a 3 x 3 neighbourhood of one id
    inner = uniform & (one[2] > 0)
    assert inner.sum() > 20
    assert float((aa[0] - one[0]).abs().amax(0)[inner].max()) < 0.05
    edge = ~uniform
    assert float((aa[0] - one[0]).abs().amax(0)[edge].mean()) > 0.02  # the outlines change
