"""``prismonet.render.supersample``: the box-filtered render against an analytic disc, and its one-sample case."""

import math

import pytest
import torch

from prismonet.render import RenderSettings, SceneParams, composite, render_objects
from prismonet.render.background import plane_depth
from prismonet.render.supersample import supersampled_image

D64 = torch.float64
F_PX, SIDE = 40.0, 32  # focal length and image side in pixels
R_OBJ, DIST = 0.8, 6.0  # sphere radius (object units, scale 1) and its distance on the optical axis


def sphere_sdf(z, x):
    return x.norm(dim=-1) - R_OBJ


def white(z, x):
    return torch.ones(*x.shape[:-1], 3, dtype=x.dtype)


def scene(dtype=D64):
    """A sphere straight ahead of a camera at the world origin (identity pose), the ground far behind it."""
    K = torch.tensor([[F_PX, 0, (SIDE - 1) / 2], [0, F_PX, (SIDE - 1) / 2], [0, 0, 1]], dtype=dtype)[None]
    T = torch.eye(4, dtype=dtype)[None]
    p = SceneParams(z_sh=torch.zeros(1, 1, 1, dtype=dtype), z_tex=torch.zeros(1, 1, 1, dtype=dtype),
                    position=torch.tensor([[[0.0, 0.0, DIST]]], dtype=dtype),
                    cos_sin=torch.tensor([[[1.0, 0.0]]], dtype=dtype), scale=torch.ones(1, 1, dtype=dtype))
    return p, K, T


SETTINGS = RenderSettings(samples=48, refine_steps=8, far_depth=1e3)


def test_coverage_of_a_disc():
    """White sphere on black: each pixel's value is the share of it the sphere's outline covers. The outline of a
    sphere of radius R at distance d on the axis is a circle of radius f R / sqrt(d^2 - R^2) pixels."""
    p, K, T = scene()
    img = supersampled_image(sphere_sdf, white, p, torch.zeros(1, 3, dtype=D64), K, T, SIDE, SIDE, -1e3, 8, SETTINGS)
    cover = img[0, 0]
    r = F_PX * R_OBJ / math.sqrt(DIST**2 - R_OBJ**2)
    assert torch.equal(img[0, 0], img[0, 1]) and torch.equal(img[0, 0], img[0, 2])
    assert float(cover.sum()) == pytest.approx(math.pi * r * r, rel=0.005)  # 64 rays per pixel
    v, u = torch.meshgrid(torch.arange(SIDE, dtype=D64), torch.arange(SIDE, dtype=D64), indexing="ij")
    rho = ((u - (SIDE - 1) / 2) ** 2 + (v - (SIDE - 1) / 2) ** 2).sqrt()
    assert bool((cover[rho < r - 0.75] == 1).all()) and bool((cover[rho > r + 0.75] == 0).all())  # whole pixels
    edge = cover[(rho > r - 0.3) & (rho < r + 0.3)]
    assert bool(((edge > 0) & (edge < 1)).all())  # the outline's pixels are shared


def test_one_sample_is_the_render():
    p, K, T = scene()
    bg = torch.tensor([[0.2, 0.3, 0.4]], dtype=D64)
    img = supersampled_image(sphere_sdf, white, p, bg, K, T, SIDE, SIDE, -1e3, 1, SETTINGS)
    obj = render_objects(sphere_sdf, white, p, K, T, SIDE, SIDE, SETTINGS)
    ref = composite(obj.depth, obj.mask, obj.color, bg, plane_depth(K, T, SIDE, SIDE, -1e3, 1e3)).image
    assert torch.equal(img, ref)


def test_bad_samples():
    p, K, T = scene()
    with pytest.raises(ValueError, match="samples per pixel side: expected at least 1, got 0"):
        supersampled_image(sphere_sdf, white, p, torch.zeros(1, 3, dtype=D64), K, T, SIDE, SIDE, -1e3, 0)
