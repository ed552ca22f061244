"""Wooden blocks (boxes, hexagonal prisms, wedges) as a shape set, and scenes of them stacked so that
they balance: exact geometry, hand-made balance cases, and sampled scenes checked block by block."""

import json
import math
from dataclasses import replace

import numpy as np
import pytest

from prismonet.data.clevr import BLOCK_TOWERS, COLOR_RGB, RandomizeConfig
from prismonet.data.stacks import MAX_LEVELS, inside_convex, platforms, sample_stacks, stack_balances, world_top
from prismonet.shapes.blocks import block_mesh, block_specs, top_face, volume, write_blocks
from prismonet.shapes.library import shape_library


@pytest.mark.parametrize("spec", block_specs(), ids=lambda s: s["name"])
def test_block_meshes_are_closed_normalised_and_measured(spec):
    import trimesh

    v, f = block_mesh(spec["category"], spec["half_extents"])
    mesh = trimesh.Trimesh(v, f, process=False)
    assert mesh.is_watertight and mesh.volume > 0
    lo, hi = v.min(0), v.max(0)
    np.testing.assert_allclose(hi, spec["half_extents"], atol=1e-12)  # centred: the box is symmetric
    np.testing.assert_allclose(-lo, spec["half_extents"], atol=1e-12)
    assert max(spec["half_extents"]) == 1.0  # Clevr's normalisation: the base at -h_z
    assert volume(spec["category"], spec["half_extents"]) == pytest.approx(mesh.volume, rel=1e-9)
    top = top_face(spec["category"], spec["half_extents"])
    if spec["category"] == "wedge":
        assert top is None
    else:  # the flat top: its area is the mesh's cross-section (volume / height)
        x, y = top[:, 0], top[:, 1]
        area = 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))  # > 0: counter-clockwise
        assert area == pytest.approx(mesh.volume / (2 * spec["half_extents"][2]), rel=1e-9)


def test_hexagon_by_hand():
    v, _ = block_mesh("hexprism", (1.0, math.cos(math.pi / 6), 0.4))
    assert np.abs(v[:, 1]).max() == pytest.approx(math.sqrt(3) / 2)  # flat to flat: sqrt(3) for circumradius 1
    assert volume("hexprism", (1.0, 0.866, 0.4)) == pytest.approx(3 * math.sqrt(3) / 2 * 0.8)


def test_block_set_folder_recolours_its_objects(tmp_path):
    write_blocks(tmp_path / "b")
    lib = shape_library(str(tmp_path / "b"))
    assert not lib.own_colors and len(lib.specs) == len(block_specs())
    assert set(lib.categories) == {"box", "hexprism", "wedge"}
    assert json.loads((tmp_path / "b" / "models.json").read_text())["own_colors"] is False
    with pytest.raises(ValueError, match="not empty"):
        write_blocks(tmp_path / "b")


def test_point_in_convex_polygon():
    sq = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    assert inside_convex(np.array([0.5, 0.5]), sq) and inside_convex(np.array([1.0, 0.3]), sq)  # edges count
    assert not inside_convex(np.array([1.01, 0.5]), sq) and not inside_convex(np.array([-0.2, 0.2]), sq)


def _block(category, he, scale, xy, yaw=0.0):
    return {"category": category, "half_extents": he, "scale": scale, "xy": np.asarray(xy, float), "yaw": yaw}


def test_balance_by_hand():
    cube, board = (1.0, 1.0, 1.0), (1.0, 0.6, 0.15)
    # a cube of half-side 0.5 on another: its centre must stay 0.45 inside the top (margin 0.1)
    assert stack_balances([_block("box", cube, 0.5, (0, 0)), _block("box", cube, 0.5, (0.44, 0))], 0.1)
    assert not stack_balances([_block("box", cube, 0.5, (0, 0)), _block("box", cube, 0.5, (0.46, 0))], 0.1)
    # nothing rests on a wedge
    assert not stack_balances([_block("wedge", (1.0, 1.0, 0.8), 0.5, (0, 0)), _block("box", cube, 0.2, (0, 0))], 0.1)
    # a heavy cube (mass 1) on the far end of a light board (mass 0.09 * 0.6... by volume) pulls the pair's
    # centre of mass past the edge of the base: the board alone rests there, the pair does not
    base = _block("box", cube, 0.5, (0, 0))
    plank = _block("box", board, 1.0, (0.4, 0))  # its centre 0.4 off, inside the 0.45 limit
    heavy = _block("box", cube, 0.5, (1.0, 0))   # on the plank's far end (the plank's top reaches x = 1.4)
    assert stack_balances([base, plank], 0.1)
    m_plank, m_heavy = 8 * 0.6 * 0.15, 8 * 0.125
    com = (m_plank * 0.4 + m_heavy * 1.0) / (m_plank + m_heavy)  # 0.80: past 0.45
    assert com > 0.45 and not stack_balances([base, plank, heavy], 0.1)
    # a hexagonal slab's top is its hexagon: a point 0.95 along a corner is inside, along an edge normal it is not
    hexa = world_top("hexprism", (1.0, math.cos(math.pi / 6), 0.3), 1.0, np.zeros(2), 0.0)
    assert inside_convex(np.array([0.95, 0.0]), hexa) and not inside_convex(np.array([0.0, 0.95]), hexa)


def test_sampled_stacks_rest_on_flat_tops_and_keep_apart(tmp_path):
    write_blocks(tmp_path / "b")
    lib = shape_library(str(tmp_path / "b"))
    cfg = replace(BLOCK_TOWERS, shapes=str(tmp_path / "b"), num_objects=6, min_objects=1, area_half=1.5,
                  scale_range=(0.3, 0.65), towers=replace(BLOCK_TOWERS.towers, max_towers=3, colors=tuple(range(8))),
                  randomize=RandomizeConfig())
    stacked = 0
    for i in range(40):
        spec = sample_stacks(np.random.default_rng([7, i]), cfg)
        objs = spec.objects
        assert 1 <= len(objs) <= 6
        level = {}
        for o in sorted(objs, key=lambda o: o.position[2]):
            s = lib.specs[o.shape_id]
            assert 0 <= o.color_id < len(COLOR_RGB) and 0.3 <= o.scale <= 0.65
            foot = o.position[2] - o.scale * s.half_extents[2]
            if foot < 1e-9:
                level[id(o)] = 1
                continue  # on the ground
            # on some block's flat top: the top's height, and its centre over that top
            below = [b for b in objs if b is not o and top_face(lib.specs[b.shape_id].category, lib.specs[b.shape_id].half_extents) is not None
                     and abs(b.position[2] + b.scale * lib.specs[b.shape_id].half_extents[2] - foot) < 1e-9]
            assert below, f"scene {i}: a block floats"
            tops = [world_top(lib.specs[b.shape_id].category, lib.specs[b.shape_id].half_extents, b.scale,
                              np.asarray(b.position[:2]), b.yaw) for b in below]
            support = [b for b, t in zip(below, tops) if inside_convex(np.asarray(o.position[:2]), t)]
            assert support
            level[id(o)] = 1 + min(level[id(b)] for b in support)
            stacked += 1
        assert max(level.values()) <= MAX_LEVELS
    assert stacked > 10  # stacks are common, not an accident


def test_towers_cli_refuses_randomised_cubes(tmp_path, capsys):
    from prismonet.cli import main

    assert main(["data", "towers", "--randomize", "--out", str(tmp_path / "t")]) != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--randomize" in err[0] and not (tmp_path / "t").exists()


def test_stacked_block_scenes_render_with_ground_truth(tmp_path):
    from prismonet.data.generate import generator_name, render_range

    write_blocks(tmp_path / "b")
    cfg = replace(BLOCK_TOWERS, shapes=str(tmp_path / "b"), num_objects=5, min_objects=2, area_half=1.5,
                  scale_range=(0.3, 0.65), towers=replace(BLOCK_TOWERS.towers, max_towers=2, colors=tuple(range(8))),
                  randomize=RandomizeConfig())
    assert generator_name(cfg) == "stacks" and generator_name(BLOCK_TOWERS) == "towers"
    a = render_range(cfg.to_dict(), 5, 0, 6)
    b = render_range(cfg.to_dict(), 5, 0, 6)
    assert all(np.array_equal(a[k], b[k]) for k in a)  # deterministic
    lib = shape_library(str(tmp_path / "b"))
    for j in range(6):
        n = int(a["obj_count"][j])
        assert 2 <= n <= 5 and (a["obj_shape"][j, n:] == -1).all()
        assert set(np.unique(a["instance"][j])) <= set(range(n + 1)) and (a["instance"][j] > 0).sum() > 25
        for k in range(n):  # each block's centre is its half-height above the ground or above another block's top
            he = lib.specs[int(a["obj_shape"][j, k])].half_extents
            foot = a["obj_position"][j, k, 2] - a["obj_scale"][j, k] * he[2]
            tops = [a["obj_position"][j, i, 2] + a["obj_scale"][j, i] * lib.specs[int(a["obj_shape"][j, i])].half_extents[2]
                    for i in range(n) if i != k]
            assert abs(foot) < 1e-5 or min(abs(foot - t) for t in tops) < 1e-5


def test_platform_scenes_carry_stacks_on_one_wide_flat_block(tmp_path):
    write_blocks(tmp_path / "b")
    lib = shape_library(str(tmp_path / "b"))
    towers = replace(BLOCK_TOWERS.towers, max_towers=3, colors=tuple(range(8)), platform_share=1.0, platform_scale=(1.3, 1.6))
    cfg = replace(BLOCK_TOWERS, shapes=str(tmp_path / "b"), num_objects=6, min_objects=2, area_half=2.0,
                  scale_range=(0.3, 0.5), towers=towers, randomize=RandomizeConfig())
    wide = {s.shape_id for s in platforms(cfg)}
    # the wide, low blocks with a flat top: four boards and slabs and the flattest hexagonal prism
    assert sorted((lib.specs[i].category, lib.specs[i].half_extents[2]) for i in wide) == \
        [("box", 0.15), ("box", 0.15), ("box", 0.25), ("box", 0.25), ("hexprism", 0.2)]
    carried = 0
    for i in range(30):
        objs = sample_stacks(np.random.default_rng([3, i]), cfg).objects
        big = [o for o in objs if o.scale > 0.5]
        assert len(big) == 1, f"scene {i}: one platform, not {len(big)}"
        plat, he = big[0], lib.specs[big[0].shape_id].half_extents
        assert plat.shape_id in wide and 1.3 <= plat.scale <= 1.6
        assert abs(plat.position[2] - plat.scale * he[2]) < 1e-9  # on the ground
        top_z = plat.position[2] + plat.scale * he[2]
        top = world_top(lib.specs[plat.shape_id].category, he, plat.scale, np.asarray(plat.position[:2]), plat.yaw)
        on = [o for o in objs if abs(o.position[2] - o.scale * lib.specs[o.shape_id].half_extents[2] - top_z) < 1e-9]
        assert 1 <= len(on) <= 4 and all(inside_convex(np.asarray(o.position[:2]), top) for o in on)
        for o in on:  # each stack on the platform balances on it, the blocks above it included
            above = sorted([o] + [b for b in objs if b.position[2] > o.position[2] and
                                  np.linalg.norm(np.subtract(b.position[:2], o.position[:2])) < o.scale * 1.5],
                           key=lambda b: b.position[2])
            stack = [_block(lib.specs[b.shape_id].category, lib.specs[b.shape_id].half_extents, b.scale, b.position[:2], b.yaw)
                     for b in [plat, *above]]
            assert stack_balances(stack[:2], towers.margin)
        carried += len(on)
    assert carried >= 30


def test_no_platform_share_draws_the_scenes_it_drew_before(tmp_path):
    # a share of 0 makes no extra draw, so data made before platforms existed is made again draw for draw
    # (the figures below were printed by the generator before platforms: 26 blocks in these 10 scenes, and scene 0)
    write_blocks(tmp_path / "b")
    base = replace(BLOCK_TOWERS, shapes=str(tmp_path / "b"), num_objects=5, min_objects=1, area_half=1.5,
                   scale_range=(0.3, 0.65), towers=replace(BLOCK_TOWERS.towers, max_towers=3, colors=tuple(range(8))),
                   randomize=RandomizeConfig())
    a = [sample_stacks(np.random.default_rng([5, i]), base).objects for i in range(10)]
    assert sum(len(x) for x in a) == 26
    assert [(o.shape_id, round(o.scale, 4)) for o in a[0]] == [(3, 0.6142), (18, 0.5368)]
    some = replace(base, towers=replace(base.towers, platform_share=0.5))
    assert a != [sample_stacks(np.random.default_rng([5, i]), some).objects for i in range(10)]


@pytest.mark.parametrize("args, words", [
    (["--scale", "0.3,0.6"], "--scale"),                   # the cube towers keep one scale range
    (["--platforms", "0.5"], "--platforms"),               # the cube towers have no platform
    (["--shapes", "data/blocks", "--platforms", "1.5"], "--platforms"),  # a share above 1
    (["--shapes", "/nonexistent/blocks"], "shape library"),  # no such set
    (["--shapes", "OWN"], "not a block set"),              # an import whose models keep their own colours
])
def test_towers_cli_refuses_bad_block_options_in_one_line(tmp_path, capsys, args, words):
    from prismonet.cli import main

    write_blocks(tmp_path / "own")
    record = json.loads((tmp_path / "own" / "models.json").read_text())
    (tmp_path / "own" / "models.json").write_text(json.dumps({**record, "own_colors": True}))
    args = [str(tmp_path / "own") if a == "OWN" else a for a in args]
    assert main(["data", "towers", *args, "--out", str(tmp_path / "t")]) != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and words in err[0] and not (tmp_path / "t").exists()


def test_towers_cli_refuses_a_bad_scale_range(capsys):
    from prismonet.cli import main

    assert main(["data", "towers", "--shapes", "data/blocks", "--scale", "0.6,0.3", "--out", "/tmp/never"]) != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "0 < LO <= HI" in err[0]


@pytest.mark.parametrize("flat", [True, False])
def test_towers_cli_refuses_platforms_it_cannot_build_in_one_line(tmp_path, capsys, flat):
    from prismonet.cli import main

    write_blocks(tmp_path / "b")
    args = ["--platform-scale", "2.0,1.2"]  # LO > HI
    if not flat:  # a block set of cubes and tall blocks only: nothing wide and low to stand on
        record = json.loads((tmp_path / "b" / "models.json").read_text())
        record["models"] = [m for m in record["models"] if m["half_extents"][2] >= 0.5]
        (tmp_path / "b" / "models.json").write_text(json.dumps(record))
        args = ["--platforms", "0.5"]
    assert main(["data", "towers", "--shapes", str(tmp_path / "b"), *args, "--out", str(tmp_path / "t")]) != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and ("0 < LO <= HI" in err[0] if flat else "no wide, low block" in err[0])
    assert not (tmp_path / "t").exists()
