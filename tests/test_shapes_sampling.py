"""SDF samples from meshes against analytic SDFs; normalisation; bad meshes."""

import numpy as np
import pytest
import trimesh

from prismonet.shapes.clevr_set import UnknownCategoryError, category_id, shape_mesh
from prismonet.shapes.normalize import BOX_HALF, MeshError, normalize_mesh
from prismonet.shapes.sdf_samples import SamplingConfig, cached_sdf_samples, sample_sdf, signed_distance, winding_number


def box_sdf(p, half):
    q = np.abs(p) - np.asarray(half)
    return np.linalg.norm(np.maximum(q, 0), axis=1) + np.minimum(q.max(1), 0)


def test_box_sdf_is_exact():
    v, f = shape_mesh(18)  # cube, half-extents (1, 1, 1)
    p = np.random.default_rng(0).uniform(-1.1, 1.1, (4000, 3))
    assert np.allclose(signed_distance(v, f, p), box_sdf(p, (1, 1, 1)), atol=1e-5)


def test_sphere_sdf_within_tessellation_error():
    v, f = shape_mesh(0)  # icosphere, radius 1
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    sagitta = 1.0 - np.abs((n / np.linalg.norm(n, axis=1, keepdims=True) * v[f[:, 0]]).sum(1)).min()
    p = np.random.default_rng(1).uniform(-1.1, 1.1, (4000, 3))
    exact = np.linalg.norm(p, axis=1) - 1.0
    got = signed_distance(v, f, p)
    assert np.abs(got - exact).max() <= sagitta + 1e-5
    far = np.abs(exact) > sagitta
    assert np.all(np.sign(got[far]) == np.sign(exact[far]))


def test_winding_number_signs_survive_a_hole():
    """A cube with one face (two triangles) removed: ray parity breaks, the winding number holds."""
    v, f = shape_mesh(18)
    top = np.where(v[f].mean(1)[:, 2] > 0.99)[0]
    open_f = np.delete(f, top, axis=0)
    assert not trimesh.Trimesh(v, open_f).is_watertight
    p = np.random.default_rng(2).uniform(-0.8, 0.8, (2000, 3))
    p[:1000] *= 1.8  # half of them mostly outside
    w = winding_number(v, open_f, p)
    exact = box_sdf(p, (1, 1, 1))
    clear = (np.abs(exact) > 0.05) & (p[:, 2] < 0.9)  # away from the surface and the hole
    assert np.all((w[clear] > 0.5) == (exact[clear] < 0))
    sd = signed_distance(v, open_f, p, inside="winding")  # detects the hole and uses the winding number
    assert np.all(np.sign(sd[clear]) == np.sign(exact[clear]))


def test_visibility_vote_needs_no_face_orientation():
    """A closed cube with half its faces turned inwards (as imported models often have them) plus a small
    hole: the winding number goes wrong, the visibility vote stays exact away from the surface."""
    from prismonet.shapes.sdf_samples import inside_mesh

    v, f = shape_mesh(18)
    flipped = f.copy()
    flipped[::2] = flipped[::2, ::-1]  # one triangle of every face turned inwards
    # a crack: split one bottom triangle at a point near its edge ab and drop the sliver [a, b, m]
    bottom = int(np.where(v[f].mean(1)[:, 2] < -0.99)[0][0])
    a, b, c = flipped[bottom]
    mid = (v[a] + v[b]) / 2
    v2 = np.vstack([v, mid + 0.02 * (v[c] - mid)])
    m = len(v)
    holed = np.vstack([np.delete(flipped, bottom, axis=0), [[b, c, m], [c, a, m]]])  # [a, b, m] is missing
    assert not trimesh.Trimesh(v2, holed).is_watertight
    p = np.random.default_rng(3).uniform(-1.6, 1.6, (3000, 3))
    exact = box_sdf(p, (1, 1, 1))
    clear = np.abs(exact) > 0.1
    vote = inside_mesh(v2, holed, p[clear])
    assert np.array_equal(vote, exact[clear] < 0)
    assert not np.array_equal(inside_mesh(v2, holed, p[clear], inside="winding"), exact[clear] < 0)


def test_visibility_vote_empties_a_container_but_not_an_open_floor():
    """A cube without its top is a box: from its middle 1/3 of the upward directions leave through the
    opening, from near its bottom 14 % (outside: a render from above sees into it). Without its bottom
    instead (a car without a floor panel) no upward ray escapes from inside: solid."""
    from prismonet.shapes.sdf_samples import ESCAPE_INSIDE, _scene, escape_fraction

    v, f = shape_mesh(18)
    centres_z = v[f].mean(1)[:, 2]
    open_top = np.delete(f, np.where(centres_z > 0.99)[0], axis=0)
    open_bottom = np.delete(f, np.where(centres_z < -0.99)[0], axis=0)
    p = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.3], [0.0, 0.0, -0.9], [0.0, 0.0, 1.5], [3.0, 0.0, 0.0]])
    # solid angle of the opening (a square of half-side 1 at height h above the point): 4 asin(1 / (1 + h^2)),
    # a share of the hemisphere's 2 pi
    h = 1.0 - p[:3, 2]
    analytic = 4 * np.arcsin(1 / (1 + h**2)) / (2 * np.pi)
    e = escape_fraction(_scene(v, open_top), p)
    assert np.allclose(e[:3], analytic, atol=0.05)  # 64 directions
    assert list(e < ESCAPE_INSIDE) == [False, False, False, False, False]
    e = escape_fraction(_scene(v, open_bottom), p)
    assert list(e < ESCAPE_INSIDE) == [True, True, True, False, False]


def test_normalisation_bounds():
    v, f = shape_mesh(20)
    moved = v * np.array([3.0, 3.0, 3.0]) + np.array([5.0, -2.0, 1.0])
    nv, norm = normalize_mesh(moved, f)
    assert np.allclose(np.abs(nv).max(0).max(), 1.0)
    assert np.allclose((nv.max(0) + nv.min(0)) / 2, 0.0)
    assert norm.scale == pytest.approx(1 / 3) and norm.center == pytest.approx((5.0, -2.0, 1.0))
    pts, sdf = sample_sdf(moved, f, SamplingConfig(num_points=2000, uniform_ratio=0.5), np.random.default_rng(0))
    assert pts.shape == (2000, 3) and sdf.shape == (2000,)
    assert np.abs(pts).max() <= BOX_HALF + 1e-6
    assert (sdf < 0).any() and (sdf > 0).any()


def test_sample_mix_and_cache(tmp_path):
    v, f = shape_mesh(9)
    cfg = SamplingConfig(num_points=1000, uniform_ratio=0.3)
    pts, sdf = cached_sdf_samples(v, f, cfg, 4, tmp_path)
    assert len(list(tmp_path.glob("*.npz"))) == 1
    again = cached_sdf_samples(v, f, cfg, 4, tmp_path)
    assert np.array_equal(pts, again[0]) and np.array_equal(sdf, again[1])
    # 700 near-surface points: most within 3 sigma of the surface
    assert (np.abs(sdf[:700]) < 0.25).mean() > 0.95
    # a damaged cache entry is recomputed, not trusted
    next(tmp_path.glob("*.npz")).write_bytes(b"junk")
    third = cached_sdf_samples(v, f, cfg, 4, tmp_path)
    assert np.array_equal(third[1], sdf)


@pytest.mark.parametrize(
    "vertices, faces, message",
    [
        (np.zeros((0, 3)), np.zeros((0, 3), int), "empty mesh"),
        (np.array([[0, 0, 0], [1, 0, 0], [0, 1, np.nan]]), np.array([[0, 1, 2]]), "NaN or infinite"),
        (np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]]), np.array([[0, 1, 2], [1, 3, 2]]), r"flat\) mesh: its extent along z"),
        (np.eye(3), np.array([[0, 1, 5]]), "out of range"),
    ],
)
def test_bad_meshes(vertices, faces, message):
    with pytest.raises(MeshError, match=message):
        sample_sdf(vertices, faces, SamplingConfig(num_points=10), np.random.default_rng(0))


def test_unknown_category():
    assert category_id("cube") == 2
    with pytest.raises(UnknownCategoryError, match="unknown shape category 'cone'"):
        category_id("cone")


def test_fast_winding_number_equals_the_direct_formula():
    import trimesh

    from prismonet.shapes.sdf_samples import winding_number_direct

    mesh = trimesh.creation.icosphere(subdivisions=2)
    keep = mesh.faces[: len(mesh.faces) - 30]  # a sphere with a hole
    rng = np.random.default_rng(0)
    p = np.concatenate([rng.uniform(-1.2, 1.2, (600, 3)), mesh.vertices[:20] * 1.001])  # some right at the surface
    fast, ref = winding_number(mesh.vertices, keep, p), winding_number_direct(mesh.vertices, keep, p)
    assert np.abs(fast - ref).max() < 1e-9
    assert ((fast > 0.5) == (np.linalg.norm(p, axis=1) < 0.99)).mean() > 0.97  # inside the sphere, despite the hole


def test_generated_training_shapes_are_closed_and_normalised(script):
    """``scripts/revolved_shapes.py``: every kind of revolved profile gives a watertight mesh with largest half-extent 1,
    round about z; ``scripts/stretch_shapes.py``: a unit cube stretched z x 0.5 has half-extents (1, 1, 0.5) after
    normalising, and bad stretches are refused."""
    rev = script("revolved_shapes")
    rng = np.random.default_rng(0)
    for kind in rev.KINDS:
        v, f = rev.revolved_mesh(kind, rng)
        half = (v.max(0) - v.min(0)) / 2
        assert trimesh.Trimesh(v, f, process=False).is_watertight, kind
        assert half.max() == pytest.approx(1.0) and half[0] == pytest.approx(half[1], rel=0.02), kind
    st = script("stretch_shapes")
    box = trimesh.creation.box(extents=(2.0, 2.0, 2.0))
    v = st.stretched(np.asarray(box.vertices), np.asarray(box.faces), st.parse_stretch("z=0.5"))
    assert ((v.max(0) - v.min(0)) / 2).tolist() == pytest.approx([1.0, 1.0, 0.5])
    v = st.stretched(np.asarray(box.vertices), np.asarray(box.faces), st.parse_stretch("x=2,y=2"))
    assert ((v.max(0) - v.min(0)) / 2).tolist() == pytest.approx([1.0, 1.0, 0.5])
    for bad in ("w=2", "z=0", "z"):
        with pytest.raises(ValueError, match="--stretch"):
            st.parse_stretch(bad)
