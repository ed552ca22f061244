"""Camera and pose geometry against exact answers, and against kornia and OpenCV themselves."""

import math

import numpy as np
import pytest
import torch
from kornia.geometry.conversions import axis_angle_to_rotation_matrix

from prismonet.data.clevr import ClevrConfig, clevr_camera
from prismonet.geometry import (
    Camera,
    T_world_obj_from_extrinsics,
    camera_rays,
    compose,
    crop_intrinsics,
    intrinsics_matrix,
    invert_similarity,
    look_at,
    pixel_grid,
    project,
    resize_intrinsics,
    rotation_from_axis_cos_sin,
    transform_points,
    unproject,
    yaw_to_cos_sin,
)

K = intrinsics_matrix(100.0, 120.0, 32.0, 30.0, dtype=torch.float64)


def test_project_known_point():
    uv = project(torch.tensor([[1.0, 2.0, 10.0]], dtype=torch.float64), K)
    assert torch.allclose(uv, torch.tensor([[42.0, 54.0]], dtype=torch.float64))


def test_project_unproject_round_trip(gen):
    x = torch.rand(50, 3, generator=gen, dtype=torch.float64) * 4 - 2
    x[:, 2] = x[:, 2].abs() + 0.5
    x2 = unproject(project(x, K), x[:, 2:], K)
    assert torch.allclose(x, x2, atol=1e-12)


def test_unproject_rejects_bad_shapes():
    with pytest.raises(ValueError, match=r"depth: expected shape \(5, 1\)"):
        unproject(torch.zeros(5, 2), torch.zeros(5), K.float())
    with pytest.raises(ValueError, match=r"K: expected shape \(\.\.\., 3, 3\)"):
        project(torch.zeros(5, 3), torch.eye(4))


def test_camera_rays_have_unit_z_and_hit_their_pixels():
    rays = camera_rays(K, 6, 8)
    assert rays.shape == (6, 8, 3)
    assert torch.all(rays[..., 2] == 1)
    assert torch.allclose(project(rays * 3.7, K), pixel_grid(6, 8, dtype=torch.float64), atol=1e-12)


def test_pixel_grid_is_u_column_v_row():
    g = pixel_grid(2, 3)
    assert g[1, 2].tolist() == [2.0, 1.0]


def test_look_at_axes_follow_opencv():
    T = look_at(torch.tensor([0.0, -10.0, 0.0], dtype=torch.float64), torch.zeros(3, dtype=torch.float64))
    R = T[:3, :3]
    assert torch.allclose(R[:, 0], torch.tensor([1.0, 0, 0], dtype=torch.float64))  # x right = world x
    assert torch.allclose(R[:, 1], torch.tensor([0.0, 0, -1], dtype=torch.float64))  # y down = -world z
    assert torch.allclose(R[:, 2], torch.tensor([0.0, 1, 0], dtype=torch.float64))  # z forward
    cam = Camera(K, T, 60, 64)
    uv = cam.world_to_pixels(torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64))
    assert torch.allclose(uv[0], torch.tensor([32.0, 30.0], dtype=torch.float64))
    assert torch.allclose(uv[1], torch.tensor([32.0, 30.0 - 12.0], dtype=torch.float64))  # up is up in the image


def test_look_at_rejects_vertical_view():
    with pytest.raises(ValueError, match="parallel"):
        look_at(torch.tensor([0.0, 0.0, 5.0]), torch.zeros(3))


def test_camera_matches_kornia_pinhole_and_round_trips_dict():
    T = look_at(torch.tensor([3.0, -4.0, 2.0], dtype=torch.float64), torch.zeros(3, dtype=torch.float64))
    cam = Camera(K, T, 60, 64)
    x_world = torch.tensor([[0.3, -0.2, 0.1], [1.0, 1.0, 0.0]], dtype=torch.float64)
    x_cam = transform_points(cam.T_cam_world, x_world)
    assert torch.allclose(cam.world_to_pixels(x_world), project(x_cam, K), atol=1e-10)
    again = Camera.from_dict(cam.to_dict())
    assert torch.allclose(again.K.double(), K) and torch.allclose(again.T_world_cam.double(), T, atol=1e-6)
    with pytest.raises(ValueError, match="missing field 'K'"):
        Camera.from_dict({"T_world_cam": T.tolist(), "height": 1, "width": 1})


def test_crop_intrinsics_shifts_pixels(gen):
    x = torch.rand(20, 3, generator=gen, dtype=torch.float64) + torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    uv_crop = project(x, crop_intrinsics(K, 5, 7))
    assert torch.allclose(uv_crop, project(x, K) - torch.tensor([5.0, 7.0], dtype=torch.float64))


def test_resize_intrinsics_matches_opencv_resize():
    """A linear ramp image whose value is its own u coordinate, resized by cv2: the value at each
    new pixel is the old coordinate that the updated intrinsics map it to."""
    import cv2

    H, W = 8, 16
    ramp = np.tile(np.arange(W, dtype=np.float32), (H, 1))
    big = cv2.resize(ramp, (W * 2, H * 2), interpolation=cv2.INTER_LINEAR)
    K2 = resize_intrinsics(K, 2.0, 2.0)
    x = torch.tensor([[0.05, 0.01, 1.0]], dtype=torch.float64)  # some ray
    u_old = project(x, K)[0, 0].item()
    u_new = project(x, K2)[0, 0].item()
    assert u_new == pytest.approx((u_old + 0.5) * 2 - 0.5)
    # interior pixels of the resized ramp hold exactly (u' + 0.5) / 2 - 0.5
    cols = np.arange(2, 2 * W - 2)
    assert np.allclose(big[3, cols], (cols + 0.5) / 2 - 0.5, atol=1e-5)


def test_camera_resized_and_cropped_keep_geometry():
    cam = Camera(K.float(), torch.eye(4), 60, 64)
    r = cam.resized(30, 32)
    assert (r.height, r.width) == (30, 32)
    assert r.K[0, 0].item() == pytest.approx(50.0) and r.K[0, 2].item() == pytest.approx(15.75)
    c = cam.cropped(4, 6, 20, 20)
    assert c.K[0, 2].item() == pytest.approx(28.0) and c.K[1, 2].item() == pytest.approx(24.0)


def test_yaw_quarter_turn_maps_x_to_y():
    T = T_world_obj_from_extrinsics(
        torch.tensor([1.0, 2.0, 0.5], dtype=torch.float64),
        yaw_to_cos_sin(torch.tensor(math.pi / 2, dtype=torch.float64)),
        torch.tensor(0.5, dtype=torch.float64),
    )
    x = transform_points(T, torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64))
    assert torch.allclose(x, torch.tensor([[1.0, 2.5, 0.5], [1.0, 2.0, 1.0]], dtype=torch.float64), atol=1e-12)


def test_rotation_matches_kornia_axis_angle(gen):
    axis = torch.randn(20, 3, generator=gen, dtype=torch.float64)
    axis = axis / axis.norm(dim=-1, keepdim=True)
    angle = torch.rand(20, generator=gen, dtype=torch.float64) * 2 * math.pi - math.pi
    ours = rotation_from_axis_cos_sin(yaw_to_cos_sin(angle), axis)
    theirs = axis_angle_to_rotation_matrix(axis * angle[:, None])
    assert torch.allclose(ours, theirs, atol=1e-10)
    assert torch.allclose(ours @ ours.transpose(-1, -2), torch.eye(3, dtype=torch.float64).expand(20, 3, 3), atol=1e-12)


def test_cos_sin_pair_need_not_be_unit_and_zero_is_finite():
    R1 = rotation_from_axis_cos_sin(torch.tensor([0.6, 0.8], dtype=torch.float64))
    R2 = rotation_from_axis_cos_sin(torch.tensor([6.0, 8.0], dtype=torch.float64))
    assert torch.allclose(R1, R2, atol=1e-12)
    cs = torch.zeros(2, dtype=torch.float64, requires_grad=True)
    R0 = rotation_from_axis_cos_sin(cs)
    R0.sum().backward()
    assert torch.isfinite(R0).all() and torch.isfinite(cs.grad).all()


def test_object_world_camera_chain_and_inverse(gen):
    T_wo = T_world_obj_from_extrinsics(
        torch.tensor([0.3, -0.7, 0.4], dtype=torch.float64),
        torch.tensor([0.2, -0.9], dtype=torch.float64),
        torch.tensor(0.65, dtype=torch.float64),
        axis=torch.tensor([0.3, 0.1, 0.9], dtype=torch.float64),
    )
    T_wc = look_at(torch.tensor([7.48, -6.51, 5.34], dtype=torch.float64), torch.zeros(3, dtype=torch.float64))
    T_co = compose(invert_similarity(T_wc), T_wo)
    x_obj = torch.rand(10, 3, generator=gen, dtype=torch.float64)
    x_cam = transform_points(T_co, x_obj)
    via_world = transform_points(invert_similarity(T_wc), transform_points(T_wo, x_obj))
    assert torch.allclose(x_cam, via_world, atol=1e-12)
    back = transform_points(invert_similarity(T_co), x_cam)
    assert torch.allclose(back, x_obj, atol=1e-12)
    assert torch.allclose(invert_similarity(T_wo) @ T_wo, torch.eye(4, dtype=torch.float64), atol=1e-12)
    assert torch.allclose(invert_similarity(T_wo), torch.linalg.inv(T_wo), atol=1e-12)


def test_pose_gradcheck():
    args = (
        torch.tensor([0.3, -0.7, 0.4], dtype=torch.float64, requires_grad=True),
        torch.tensor([0.2, -0.9], dtype=torch.float64, requires_grad=True),
        torch.tensor(0.65, dtype=torch.float64, requires_grad=True),
        torch.tensor([0.3, 0.1, 0.9], dtype=torch.float64, requires_grad=True),
    )
    assert torch.autograd.gradcheck(T_world_obj_from_extrinsics, args)


def test_pose_rejects_bad_shapes():
    with pytest.raises(ValueError, match=r"scale: expected shape \(4,\), got \(4, 1\)"):
        T_world_obj_from_extrinsics(torch.zeros(4, 3), torch.ones(4, 2), torch.ones(4, 1))
    with pytest.raises(ValueError, match=r"cos_sin: expected shape"):
        rotation_from_axis_cos_sin(torch.ones(4, 3))


def test_clevr_camera_fills_image_with_placement_area():
    cfg = ClevrConfig(image_size=64)
    cam = clevr_camera(cfg)
    assert torch.allclose(cam.center, torch.tensor([7.4811, -6.5076, 5.3437]), atol=1e-5)
    a = cfg.area_half
    corners = torch.tensor([[a, a, 0.0], [a, -a, 0.0], [-a, a, 0.0], [-a, -a, 0.0]])
    uv = cam.world_to_pixels(corners)
    assert (uv >= -0.5 - 1e-3).all() and (uv <= 63.5 + 1e-3).all()
    # tight: the widest corner touches the image border
    extent = (uv - 31.5).abs().max().item()
    assert extent == pytest.approx(32.0, abs=1e-3)
    assert torch.allclose(cam.world_to_pixels(torch.zeros(1, 3)), torch.tensor([[31.5, 31.5]]), atol=1e-3)


def test_orbit_elevation_keeps_target_distance_and_heading():
    """A CLEVR camera moved to 75 degrees: its axis meets the ground at the same point from the same
    distance and heading, at exactly 75 degrees; moved to its own elevation it is unchanged."""
    from prismonet.geometry.camera import orbit_elevation

    T = clevr_camera(ClevrConfig()).T_world_cam.double()
    eye, axis = T[:3, 3], T[:3, 2]
    own = math.degrees(math.asin(-float(axis[2])))
    assert torch.allclose(orbit_elevation(T, 0.0, own), T, atol=1e-9)
    T2 = orbit_elevation(T, 0.0, 75.0)
    eye2, axis2 = T2[:3, 3], T2[:3, 2]
    assert math.degrees(math.asin(-float(axis2[2]))) == pytest.approx(75.0, abs=1e-9)
    t, t2 = -eye[2] / axis[2], -eye2[2] / axis2[2]
    assert float(t2) == pytest.approx(float(t), abs=1e-9)  # the same distance to the ground point
    assert torch.allclose(eye + t * axis, eye2 + t2 * axis2, atol=1e-9)  # the same ground point
    heading = lambda e, a: math.atan2(float(-a[1]), float(-a[0]))
    assert heading(eye2, axis2) == pytest.approx(heading(eye, axis), abs=1e-9)
    assert torch.allclose(T2[:3, :3] @ T2[:3, :3].T, torch.eye(3, dtype=T2.dtype), atol=1e-12)
    for bad in (0.0, 90.0, -5.0):
        with pytest.raises(ValueError, match="elevation"):
            orbit_elevation(T, 0.0, bad)
    with pytest.raises(ValueError, match="look down"):
        orbit_elevation(T, 100.0, 45.0)
