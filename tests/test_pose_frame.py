"""Camera-relative poses (``prismonet.model.pose_frame``): hand-computed rays, round trips and gradients."""

import math

import pytest
import torch

from prismonet.geometry.camera import intrinsics_matrix, look_at
from prismonet.model.pose_frame import camera_heading, centre_from_pixel, pixel_from_centre, rotate_about_z

D = torch.float64


def _camera(eye, target=(0.0, 0.0, 0.0), f=80.0, c=31.5):
    K = intrinsics_matrix(f, f, c, c, dtype=D)[None]
    T = look_at(torch.tensor(eye, dtype=D), torch.tensor(target, dtype=D))[None]
    return K, T


def test_the_principal_ray_meets_the_plane_where_hand_computed():
    # camera at (0, -10, 10) looking at the origin: the principal ray is (0, 1, -1)/sqrt(2); at height h
    # above the ground z = 0 it is at (0, -h, h)
    K, T = _camera((0.0, -10.0, 10.0))
    for h in (0.0, 0.4, 0.9):
        x = centre_from_pixel(torch.zeros(1, 2, dtype=D), torch.tensor([h], dtype=D), K, T, torch.zeros(1, dtype=D), 64, 24.0)
        torch.testing.assert_close(x, torch.tensor([[0.0, -h, h]], dtype=D), atol=1e-12, rtol=0)
    # a raised ground lifts the plane with it
    x = centre_from_pixel(torch.zeros(1, 2, dtype=D), torch.tensor([0.5], dtype=D), K, T, torch.tensor([-1.0], dtype=D), 64, 24.0)
    torch.testing.assert_close(x, torch.tensor([[0.0, 0.5, -0.5]], dtype=D), atol=1e-12, rtol=0)


def test_centre_and_pixel_round_trip_for_other_cameras():
    g = torch.Generator().manual_seed(0)
    K, T = _camera((7.5, -6.5, 5.3), (0.3, -0.2, 0.0), f=70.0, c=30.0)
    ab = (torch.rand(16, 2, generator=g, dtype=D) - 0.5) * 1.6
    h = torch.rand(16, generator=g, dtype=D)
    Kb, Tb = K.expand(16, 3, 3), T.expand(16, 4, 4)
    x = centre_from_pixel(ab, h, Kb, Tb, torch.zeros(16, dtype=D), 64, 24.0)
    torch.testing.assert_close(x[:, 2], h, atol=1e-12, rtol=0)  # at the asked height
    torch.testing.assert_close(pixel_from_centre(x, Kb, Tb, 64), ab, atol=1e-10, rtol=0)  # seen at the asked pixel


def test_rays_that_do_not_descend_are_held_on_the_ray():
    K, T = _camera((0.0, -10.0, 1.0), (0.0, 0.0, 1.0))  # a level camera: the principal ray never descends
    x = centre_from_pixel(torch.zeros(1, 2, dtype=D), torch.tensor([0.4], dtype=D), K, T, torch.zeros(1, dtype=D), 64, 24.0)
    assert torch.isfinite(x).all() and x[0, 1] == pytest.approx(-10.0 + 24.0)  # at t_max along the ray


def test_heading_and_yaw():
    K, T = _camera((0.0, -10.0, 10.0))
    assert camera_heading(T).item() == pytest.approx(math.pi / 2)
    cs = rotate_about_z(torch.tensor([[1.0, 0.0]], dtype=D), camera_heading(T))
    torch.testing.assert_close(cs, torch.tensor([[0.0, 1.0]], dtype=D), atol=1e-12, rtol=0)
    axis = rotate_about_z(torch.tensor([[1.0, 0.0, 0.5]], dtype=D), torch.tensor([math.pi / 2], dtype=D))
    torch.testing.assert_close(axis, torch.tensor([[0.0, 1.0, 0.5]], dtype=D), atol=1e-12, rtol=0)


def test_centre_from_pixel_gradcheck():
    K, T = _camera((7.5, -6.5, 5.3))
    ab = torch.tensor([[0.1, -0.2], [0.3, 0.25]], dtype=D, requires_grad=True)
    h = torch.tensor([0.3, 0.7], dtype=D, requires_grad=True)
    f = lambda a, b: centre_from_pixel(a, b, K.expand(2, 3, 3), T.expand(2, 4, 4), torch.zeros(2, dtype=D), 64, 24.0)
    assert torch.autograd.gradcheck(f, (ab, h))


def test_a_camera_frame_model_puts_a_zero_output_on_the_principal_ray():
    from prismonet.model.config import ModelConfig
    from prismonet.model.prismonet import PriSMONet

    with pytest.raises(ValueError, match="pose_frame"):
        ModelConfig(pose_frame="image")
    model = PriSMONet(ModelConfig(pose_frame="camera"))
    K, T = _camera((0.0, -10.0, 10.0))
    p = model.decode_latent(torch.zeros(1, model.out_dim), K.float(), T.float(), torch.zeros(1))
    torch.testing.assert_close(p.position[0, 0], torch.tensor([0.0, -0.4, 0.4]), atol=1e-5, rtol=0)  # height offset 0.4
    with pytest.raises(ValueError, match="cameras"):
        model.decode_latent(torch.zeros(1, model.out_dim))
    out = model(torch.rand(2, 3, 64, 64), K.float().expand(2, 3, 3), T.float().expand(2, 4, 4), torch.zeros(2))
    assert out.composite.image.shape == (2, 3, 64, 64) and torch.isfinite(out.composite.image).all()
