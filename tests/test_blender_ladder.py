"""The photoreal ladder (``prismonet.data.blender``): camera conversion, scene identity with the generator,
and, opt-in (``-m blender``, needs ``scripts/setup_blender.sh``), a real Cycles render."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from prismonet.data.blender import RUNGS, BlenderRung, ladder_scenes, random_ground_color
from prismonet.data.blender_worker import blender_camera, project_blender, srgb_encode
from prismonet.data.clevr import ClevrConfig
from prismonet.geometry.camera import intrinsics_matrix, look_at, project


@pytest.mark.parametrize("size,c", [((64, 64), None), ((80, 60), (41.3, 27.9))])
def test_blender_camera_projects_like_opencv(size, c):
    W, H = size
    f = 70.0
    cx, cy = c if c is not None else ((W - 1) / 2, (H - 1) / 2)
    K = intrinsics_matrix(f, f, cx, cy, dtype=torch.float64)
    T = look_at(torch.tensor([7.5, -6.5, 5.3], dtype=torch.float64), torch.zeros(3, dtype=torch.float64))
    x = torch.tensor([[0.0, 0.0, 0.0], [1.0, -0.5, 0.3], [-1.2, 0.8, 0.7], [0.4, 1.4, 0.0]], dtype=torch.float64)
    T_cw = torch.linalg.inv(T)
    uv_cv = project(x @ T_cw[:3, :3].T + T_cw[:3, 3], K).numpy()
    cam = blender_camera(K.numpy(), T.numpy(), W, H)
    np.testing.assert_allclose(project_blender(cam, W, H, x.numpy()), uv_cv, atol=1e-9)
    if c is None:  # a centred principal point needs no lens shift
        assert cam["shift_x"] == pytest.approx(0) and cam["shift_y"] == pytest.approx(0)
    # the principal point alone moves the lens shift, in units of the larger image side
    assert cam["shift_x"] == pytest.approx((W / 2 - 0.5 - cx) / W)
    assert cam["lens"] == pytest.approx(f * 32.0 / max(W, H))


def test_blender_camera_refuses_what_blender_cannot_model():
    K = np.array([[70.0, 0, 32], [0, 60.0, 32], [0, 0, 1]])
    with pytest.raises(ValueError, match="square pixels"):
        blender_camera(K, np.eye(4), 64, 64)


def test_srgb_encode_known_values():
    out = srgb_encode(np.array([0.0, 0.0031308, 0.5, 1.0, 2.0]))
    np.testing.assert_allclose(out, [0.0, 0.0031308 * 12.92, 1.055 * 0.5 ** (1 / 2.4) - 0.055, 1.0, 1.0], atol=1e-12)


def test_ladder_scenes_are_the_generators_scenes(tmp_path):
    from prismonet.data.dataset import SceneDataset
    from prismonet.data.generate import generate_clevr

    cfg = ClevrConfig(image_size=32)
    generate_clevr(tmp_path / "d", cfg, split=(2, 0, 3), seed=7, workers=1, progress=False)
    ds = SceneDataset(tmp_path / "d", "test")
    arrays, reference, jobs, materials = ladder_scenes(cfg, RUNGS["c"], 3, seed=7, first_index=2)
    for k in ("depth", "instance", "K", "T_world_cam", "obj_count", "obj_shape", "obj_color", "obj_position", "obj_yaw", "ground_color"):
        np.testing.assert_array_equal(arrays[k], ds.arrays[k][:3], err_msg=k)
    np.testing.assert_array_equal(reference, ds.arrays["rgb"][:3])  # the training renderer's images
    assert [len(m) for m in materials] == list(ds.arrays["obj_count"][:3])
    assert all(m in ("rubber", "metal") for ms in materials for m in ms)
    # each object's 4x4 pose maps the shape's frame like the generator's world mesh: x = s R x + p
    o = jobs[0]["objects"][0]
    M = np.array(o["matrix"])
    assert M[:3, 3].tolist() == pytest.approx(ds.arrays["obj_position"][0, 0].tolist(), abs=1e-6)
    assert np.linalg.det(M[:3, :3]) == pytest.approx(ds.arrays["obj_scale"][0, 0] ** 3, rel=1e-5)
    # the rung's own draws (materials, ground) leave the layouts alone: rung a gives the same arrays
    a_arrays, *_ = ladder_scenes(cfg, RUNGS["a"], 3, seed=7, first_index=2)
    np.testing.assert_array_equal(a_arrays["instance"], arrays["instance"])


def test_rungs_and_ground_colours():
    assert RUNGS["a"].lights == "flat" and RUNGS["b"].lights == "clevr" and RUNGS["c"].metal == 0.5
    assert RUNGS["d"].random_ground and RUNGS["d"].camera_jitter == 0.5
    rng = np.random.default_rng(0)
    cols = np.array([random_ground_color(rng) for _ in range(200)])
    assert cols.min() >= 65 and cols.max() <= 235 and (cols[:, 0] >= cols[:, 1]).all() and (cols[:, 1] >= cols[:, 2]).all()
    with pytest.raises(ValueError, match="lights"):
        BlenderRung(lights="studio")
    with pytest.raises(ValueError, match="metal"):
        BlenderRung(metal=1.5)


def test_the_ladder_refuses_towers_and_a_python_without_bpy(tmp_path):
    from prismonet.data.blender import generate_blender
    from prismonet.data.clevr import BLOCK_TOWERS
    from prismonet.files import InputError

    with pytest.raises(ValueError, match="Clevr's own shapes"):
        generate_blender(tmp_path / "t", "a", cfg=BLOCK_TOWERS, scenes=1, python="/bin/true")
    with pytest.raises(InputError, match="cannot import bpy"):
        generate_blender(tmp_path / "t", "a", scenes=1, python="/bin/true")


@pytest.mark.blender
def test_cycles_render_of_rung_a_matches_the_training_renderer(tmp_path):
    """Opt-in: renders 2 scenes with Blender; rung a must be close to the training renderer's images
    and aligned with them (the camera conversion is right to a fraction of a pixel)."""
    import cv2

    from prismonet.data.blender import find_blender_python, generate_blender
    from prismonet.data.dataset import SceneDataset
    from prismonet.files import InputError

    try:
        find_blender_python()
    except InputError:
        pytest.skip("no Python with bpy (scripts/setup_blender.sh)")
    meta = generate_blender(tmp_path / "a", "a", ClevrConfig(image_size=48), scenes=2, first_index=3, progress=False)
    vs = meta["blender"]["vs_training_renderer"]
    assert vs["PSNR"] > 30 and vs["mean_abs_ground"] < 0.01
    ds = SceneDataset(tmp_path / "a", "test")
    _, reference, _, _ = ladder_scenes(ClevrConfig(image_size=48), RUNGS["a"], 2, 0, 3)
    for img, ref in zip(ds.arrays["rgb"], reference):
        (dx, dy), _ = cv2.phaseCorrelate(ref.astype(np.float32).mean(2), img.astype(np.float32).mean(2))
        assert abs(dx) < 0.25 and abs(dy) < 0.25
