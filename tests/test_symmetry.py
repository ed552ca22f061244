"""``prismonet.shapes.symmetry.yaw_period`` on meshes whose symmetry about z is known by construction."""

import math

import numpy as np
import pytest
import trimesh

from prismonet.shapes.symmetry import ANY, NONE, yaw_period


def _mesh(m: trimesh.Trimesh):
    return np.asarray(m.vertices), np.asarray(m.faces)


def test_round_shapes():
    assert yaw_period(*_mesh(trimesh.creation.cylinder(radius=0.6, height=2.0, sections=24))) == ANY
    assert yaw_period(*_mesh(trimesh.creation.icosphere(subdivisions=3))) == ANY
    cup = trimesh.creation.annulus(r_min=0.5, r_max=0.6, height=1.5, sections=32)  # a thin-walled tube, inside and out
    assert yaw_period(*_mesh(cup)) == ANY


def test_boxes():
    assert yaw_period(*_mesh(trimesh.creation.box(extents=(1.6, 1.6, 1.0)))) == pytest.approx(math.pi / 2)
    assert yaw_period(*_mesh(trimesh.creation.box(extents=(2.0, 1.0, 1.0)))) == pytest.approx(math.pi)


def test_a_mug_with_a_handle():
    body = trimesh.creation.cylinder(radius=0.6, height=1.6, sections=32)
    handle = trimesh.creation.box(extents=(0.3, 0.1, 0.8))
    handle.apply_translation((0.75, 0.0, 0.0))
    assert yaw_period(*_mesh(trimesh.util.concatenate([body, handle]))) == NONE


def test_no_surface():
    with pytest.raises(ValueError, match="no surface"):
        yaw_period(np.zeros((3, 3)), np.array([[0, 1, 2]]))


def test_the_clevr_shapes_match_their_known_symmetry():
    """The 27 Clevr meshes against ``metrics.symmetry_period``, which reads it off each shape's category and
    half-extents: round spheres and cylinders any angle, square cubes 90 degrees, the stretched ones 180."""
    from prismonet.evaluation.metrics import symmetry_period
    from prismonet.shapes.symmetry import library_yaw_periods

    found = library_yaw_periods("clevr")
    assert len(found) == 27
    assert found == pytest.approx([symmetry_period(i) for i in range(27)])
