"""Seeking the unexplained: which slots seek, where to, and the loss's value and gradient, by hand."""

import pytest
import torch

from prismonet.model.seek import seek_foreground, seek_loss, seek_targets

H = W = 32
FX, CX = 20.0, 15.5
DEPTH = 4.0


def _K():
    return torch.tensor([[FX, 0.0, CX], [0.0, FX, CX], [0.0, 0.0, 1.0]])[None]


def _square(r0, c0, n):
    m = torch.zeros(H, W, dtype=torch.bool)
    m[r0:r0 + n, c0:c0 + n] = True
    return m


def _scene(masks):
    """Two objects: a 6x6 square at rows/cols 2-7 and an 8x8 one at rows 20-27, cols 18-25, at depth 4
    (camera = world). The render's winners: where slots overlap, the first."""
    fg = _square(2, 2, 6) | _square(20, 18, 8)
    depth = torch.full((1, H, W), DEPTH)
    instance = torch.zeros(H, W, dtype=torch.long)
    for k in reversed(range(len(masks))):
        instance[masks[k]] = k + 1
    return instance[None], len(masks), fg[None], depth, _K(), torch.eye(4)[None], torch.zeros(1)


def _centre(r0, c0, n):
    """World point of a square's centre pixel at depth 4 (the mean over any square centred there)."""
    u = c0 + (n - 1) / 2
    v = r0 + (n - 1) / 2
    return torch.tensor([(u - CX) * DEPTH / FX, (v - CX) * DEPTH / FX, DEPTH])


def test_a_slot_that_explains_nothing_seeks_the_largest_region_left():
    empty = torch.zeros(H, W, dtype=torch.bool)
    # slot 0 covers the small square; slot 1 is empty: it seeks the large one (its centroid is the square's
    # centre); slot 2 finds nothing left (the small square is covered, the large one claimed)
    targets, weight = seek_targets(*_scene([_square(2, 2, 6), empty, empty]))
    assert weight.tolist() == [[0.0, 1.0, 0.0]]
    assert torch.allclose(targets[0, 1], _centre(20, 18, 8), atol=1e-5)


def test_a_duplicate_slot_seeks_and_explaining_slots_do_not():
    empty = torch.zeros(H, W, dtype=torch.bool)
    big, small = _square(20, 18, 8), _square(2, 2, 6)
    # slot 1 repeats slot 0's object behind it: it wins no pixel, so it seeks the small square (36 px)
    targets, weight = seek_targets(*_scene([big, big, empty]))
    assert weight.tolist() == [[0.0, 1.0, 0.0]]
    assert torch.allclose(targets[0, 1], _centre(2, 2, 6), atol=1e-5)
    # with a threshold above the small square's 36 px there is nothing to seek
    _, weight = seek_targets(*_scene([big, big, empty]), min_pixels=37)
    assert weight.tolist() == [[0.0, 0.0, 0.0]]
    # rims around a slot's silhouette (here a 1-px ring of 60 px) are not a region
    ring = _square(19, 17, 10) & ~_square(20, 18, 8)
    inst, n, fg, depth, K, T, gz = _scene([big, empty])
    fg = fg.clone()
    fg[0] = fg[0] | ring
    _, weight = seek_targets(inst, n, fg & ~_square(2, 2, 6)[None], depth, K, T, gz)
    assert weight.tolist() == [[0.0, 0.0]]
    # both objects explained: nobody seeks
    _, weight = seek_targets(*_scene([big, small, empty]))
    assert weight.sum() == 0


def test_targets_follow_the_camera_pose():
    """A camera moved by t in the world: every target moves by t."""
    empty = torch.zeros(H, W, dtype=torch.bool)
    inst, n, fg, depth, K, T, gz = _scene([empty, empty])
    T = T.clone()
    T[0, :3, 3] = torch.tensor([1.0, -2.0, 0.5])
    targets, weight = seek_targets(inst, n, fg, depth, K, T, gz)
    assert weight.tolist() == [[1.0, 1.0]]  # the large square first, then the small one
    assert torch.allclose(targets[0, 0], _centre(20, 18, 8) + T[0, :3, 3], atol=1e-5)
    assert torch.allclose(targets[0, 1], _centre(2, 2, 6) + T[0, :3, 3], atol=1e-5)


def test_a_region_beyond_the_depth_clip_is_placed_by_its_foot_on_the_ground():
    """A camera at height 2 looking along +y, tilted down by 45 degrees (OpenCV axes: x right, y down, z
    forward): a far region (depth at the clip) is targeted where the ray through the middle of its lowest
    row meets the ground z = 0, computed here by hand."""
    import math

    c, s_ = math.cos(math.radians(45)), math.sin(math.radians(45))
    # columns of R_world_cam: the camera's x, y, z axes in the world
    R = torch.tensor([[1.0, 0.0, 0.0], [0.0, -s_, c], [0.0, -c, -s_]])
    T = torch.eye(4)
    T[:3, :3] = R
    T[:3, 3] = torch.tensor([0.0, 0.0, 2.0])
    region = _square(10, 12, 6)  # rows 10-15, cols 12-17: lowest row 15, its middle u = 14.5
    fg = region[None]
    depth = torch.where(region, torch.tensor(12.0), torch.tensor(5.0))[None]
    targets, weight = seek_targets(torch.zeros(1, H, W, dtype=torch.long), 1, fg, depth, _K(), T[None], torch.zeros(1), far_depth=12.0)
    assert weight.tolist() == [[1.0]]
    ray = torch.tensor([(14.5 - CX) / FX, (15 - CX) / FX, 1.0])
    d = R @ ray
    expect = T[:3, 3] + (0.0 - 2.0) / d[2] * d
    assert torch.allclose(targets[0, 0], expect, atol=1e-5) and abs(float(targets[0, 0, 2])) < 1e-5
    # without the clip it is the depth centroid (at depth 12) instead
    near, _ = seek_targets(torch.zeros(1, H, W, dtype=torch.long), 1, fg, depth, _K(), T[None], torch.zeros(1))
    assert not torch.allclose(near[0, 0], expect, atol=1e-2)


def test_seek_foreground_adds_off_colour_pixels_only_at_the_far_clip():
    rgb = torch.full((1, 3, H, W), 0.5)
    rgb[0, 0, :4, :4] = 0.9  # off-colour, at the clip: foreground
    rgb[0, 0, 10:14, :4] = 0.9  # off-colour but depth says ground: not foreground
    rgb[0, 1, 20:24, :4] = 0.55  # within the colour tolerance, at the clip: not foreground
    depth = torch.full((1, 1, H, W), 5.0)
    depth[..., :4, :4] = 12.0
    depth[..., 20:24, :4] = 12.0
    depth[..., 28:, 28:] = 4.0  # in front of the ground (at 5): foreground by depth
    bg_depth = torch.full((1, 1, H, W), 5.0)
    fg = seek_foreground(rgb, depth, bg_depth, torch.full((1, 3), 0.5), 12.0, 0.05)
    expect = torch.zeros(1, H, W, dtype=torch.bool)
    expect[0, :4, :4] = True
    expect[0, 28:, 28:] = True
    assert torch.equal(fg, expect)
    assert torch.equal(seek_foreground(rgb, depth, bg_depth, torch.full((1, 3), 0.5), None, 0.05)[0, :4, :4], torch.zeros(4, 4, dtype=torch.bool))


def test_seek_loss_value_and_gradient():
    pos = torch.tensor([[[1.0, 2.0, 3.0], [0.0, 0.0, 9.0]], [[-1.0, 0.5, 0.0], [2.0, 2.0, 2.0]]], dtype=torch.float64, requires_grad=True)
    targets = torch.tensor([[[0.0, 0.0, 0.0], [1.0, 1.0, 0.0]], [[0.0, 0.0, 0.0], [0.0, 0.0, 0.0]]], dtype=torch.float64)
    weight = torch.tensor([[1.0, 1.0], [1.0, 0.0]], dtype=torch.float64)
    loss = seek_loss(pos, targets, weight)
    # scene 0: the mean of its two seeking slots' distances (3 and 2); scene 1: 1.5; z is not pulled
    assert loss.item() == pytest.approx(((3 + 2) / 2 + 1.5) / 2)
    loss.backward()
    expect = torch.zeros_like(pos)
    expect[0, 0, :2] = torch.tensor([0.25, 0.25])
    expect[0, 1, :2] = torch.tensor([-0.25, -0.25])
    expect[1, 0, :2] = torch.tensor([-0.5, 0.5])
    assert torch.equal(pos.grad, expect)
    assert seek_loss(pos, targets, torch.zeros_like(weight)).item() == 0.0


def test_bad_shapes_are_refused():
    inst, n, fg, depth, K, T, gz = _scene([torch.zeros(H, W, dtype=torch.bool)])
    with pytest.raises(ValueError, match="foreground and depth"):
        seek_targets(inst, n, fg[:, :-1], depth, K, T, gz)
