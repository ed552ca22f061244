"""Block towers: stacked cubes that stand, in view, with Clevr's ground truth; and a loss that lets
objects rest on other objects."""

from collections import Counter
from dataclasses import replace

import numpy as np
import pytest
import torch

from prismonet.data.clevr import BLOCK_TOWERS, ClevrConfig, TowerConfig
from prismonet.data.generate import render_range
from prismonet.data.towers import sample_towers, tower_camera, tower_stands
from prismonet.shapes.clevr_set import shape_mesh


def test_stability_by_hand():
    s, yaw = 0.5, np.zeros(3)
    # two cubes: the top one's centre of mass must stay 0.9 s inside the face below (margin 0.1)
    assert tower_stands(np.array([[0.0, 0.0], [0.4, 0.0]]), yaw[:2], s, 0.1)
    assert not tower_stands(np.array([[0.0, 0.0], [0.46, 0.0]]), yaw[:2], s, 0.1)
    # three cubes stepping 0.3 (0.6 s) the same way: the top pair's centre of mass is 0.9 s = 0.45 off
    # the bottom cube, exactly at the limit; 0.32 steps (0.48 off) make the tower fall
    assert tower_stands(np.array([[0.0, 0.0], [0.3, 0.0], [0.6, 0.0]]), yaw, s, 0.1)
    assert not tower_stands(np.array([[0.0, 0.0], [0.32, 0.0], [0.64, 0.0]]), yaw, s, 0.1)
    # a diagonal shift of (0.4, 0.4) stands on an aligned cube; on a cube turned by 45 degrees the
    # same point lies 0.57 along its axis, outside the face
    diag = np.array([[0.0, 0.0], [0.4, 0.4]])
    assert tower_stands(diag, np.zeros(2), s, 0.1)
    assert not tower_stands(diag, np.array([np.pi / 4, 0.0]), s, 0.1)


def _corners(o) -> np.ndarray:
    v, _ = shape_mesh(o.shape_id)
    box = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=np.float64) * np.abs(v).max(0)
    R = o.rotation()
    return (o.scale * box) @ R.T + np.asarray(o.position)


def test_sampled_towers_stand_touch_and_stay_in_view():
    cfg = replace(BLOCK_TOWERS, towers=replace(BLOCK_TOWERS.towers, max_towers=2), area_half=1.2)
    cam = tower_camera(cfg)
    heights = Counter()
    for i in range(60):
        spec = sample_towers(np.random.default_rng([4, i]), cfg, cam)
        objs = spec.objects
        assert 2 <= len(objs) <= 4
        heights[len(objs)] += 1
        s = objs[0].scale
        assert all(o.scale == s and o.shape_id == 18 and o.color_id in (1, 2, 3, 7) for o in objs)
        for o in objs:
            level = round((o.position[2] / s - 1) / 2)
            assert o.position[2] == pytest.approx(s * (2 * level + 1), abs=1e-12)  # on the ground or on a cube
            if level > 0:  # some cube lies right under it, faces in contact
                below = [b for b in objs if abs(b.position[2] - (o.position[2] - 2 * s)) < 1e-9
                         and np.hypot(b.position[0] - o.position[0], b.position[1] - o.position[1]) < 2 * s]
                assert below
            # every corner of every cube projects inside the image, in front of the camera
            uv = cam.world_to_pixels(torch.tensor(_corners(o), dtype=torch.float32)).numpy()
            assert (uv >= -0.5).all() and (uv <= cfg.image_size - 0.5).all()
    assert set(heights) == {2, 3, 4} and min(heights.values()) >= 10  # uniform: 20 expected each


def test_tower_scenes_render_with_clevr_ground_truth():
    a = render_range(BLOCK_TOWERS.to_dict(), 3, 0, 6)
    b = render_range(BLOCK_TOWERS.to_dict(), 3, 0, 6)
    assert all(np.array_equal(a[k], b[k]) for k in a)  # deterministic
    for j in range(6):
        n = int(a["obj_count"][j])
        assert 2 <= n <= 4
        assert set(np.unique(a["instance"][j])) <= set(range(n + 1))
        assert (a["instance"][j] == 1).sum() > 25  # the bottom cube is in view
        assert (a["obj_shape"][j, :n] == 18).all() and (a["obj_category"][j, :n] == 2).all()
        assert (a["obj_shape"][j, n:] == -1).all()
        z = a["obj_position"][j, :n, 2]
        assert np.allclose(np.sort(z), a["obj_scale"][j, 0] * (2 * np.arange(n) + 1), atol=1e-5)  # one tower


def test_tower_config_is_checked_and_read_back():
    with pytest.raises(ValueError, match="cube"):
        TowerConfig(shape_id=0)  # a sphere does not stack
    with pytest.raises(ValueError, match="colour"):
        TowerConfig(colors=(11,))  # ids 0-10: CLEVR's eight, then white, silver, black
    with pytest.raises(ValueError, match="offset"):
        TowerConfig(offset=1.5)
    back = ClevrConfig(**{**BLOCK_TOWERS.to_dict(), "towers": {**BLOCK_TOWERS.to_dict()["towers"], "colors": [1, 2]}})
    assert back.towers == TowerConfig(colors=(1, 2))


def test_ground_loss_lets_a_cube_rest_on_another():
    """L_gr: zero for a cube on a cube (its foot on the ground lies outside it), positive for a cube
    sunk into the ground: the pose parametrisation and the ground loss allow stacking."""
    from prismonet.model.io import load_model
    from prismonet.model.losses import ground_loss
    from prismonet.render import SceneParams

    model, _ = load_model("shipped")
    z_cube = model.prior.latents[18].view(1, 1, -1).repeat(1, 2, 1)
    s = 0.45

    def params(z_top: float, z_bottom: float = s):
        return SceneParams(z_cube, torch.zeros(1, 2, model.cfg.tex_dim), torch.tensor([[[0.0, 0.0, z_bottom], [0.1, 0.0, z_top]]]),
                           torch.tensor([[[1.0, 0.0], [1.0, 0.0]]]), torch.full((1, 2), s))

    ground = torch.zeros(1)
    top_only = lambda p: SceneParams(p.z_sh[:, 1:], p.z_tex[:, 1:], p.position[:, 1:], p.cos_sin[:, 1:], p.scale[:, 1:])
    with torch.no_grad():
        assert float(ground_loss(model, top_only(params(3 * s)), ground)) == 0.0  # the stacked cube pays nothing
        # the bottom cube's foot is on its own face: at most the prior's error there (in world units)
        assert float(ground_loss(model, params(3 * s), ground)) < 0.005
        assert float(ground_loss(model, params(3 * s, z_bottom=0.5 * s), ground)) > 0.05  # sunk: penalised
