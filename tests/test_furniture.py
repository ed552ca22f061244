"""Importing furniture meshes for the ShapeNet-style settings, on a small library built here in Sweet
Home 3D's format (the real package is an opt-in download)."""

import io
import json
import tarfile
import zipfile

import numpy as np
import pytest

from prismonet.shapes.furniture import (
    FurnitureError,
    assign_splits,
    catalog,
    import_setting,
    open_libraries,
    parse_catalog,
    select,
)

TEX_RGB = (64, 128, 192)


def _box(x0, x1, y0, y1, z0, z1, first: int) -> tuple[list[str], list[str]]:
    """OBJ lines of a box (vertices and 12 triangles, 1-based from ``first``), with texture coordinates."""
    vs = [f"v {x} {y} {z}" for x in (x0, x1) for y in (y0, y1) for z in (z0, z1)]
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    fs = []
    for a, b, c, d in quads:
        for tri in ((a, b, c), (a, c, d)):
            fs.append("f " + " ".join(f"{first + i}/{1 + (i % 4)}" for i in tri))
    return vs, fs


def _library() -> bytes:
    """A ``.sh3f`` zip: one two-part model (a red box and a textured box; y up, 4 x 2 x 1 overall),
    listed three times: as a toy car, as an armchair turned by a ``modelRotation``, and as a carpet."""
    from PIL import Image

    v1, f1 = _box(-2.0, 0.0, 0.0, 2.0, -0.5, 0.5, 1)
    v2, f2 = _box(0.5, 2.0, 0.0, 2.0, -0.5, 0.5, 9)
    vt = [f"vt {u} {w}" for u, w in ((0, 0), (1, 0), (1, 1), (0, 1))]
    obj = "\n".join(["mtllib m.mtl", *v1, *v2, *vt, "usemtl red", *f1, "usemtl tex", *f2]) + "\n"
    mtl = "newmtl red\nKd 1 0 0\nnewmtl tex\nKd 1 1 1\nmap_Kd t.png\n"
    png = io.BytesIO()
    Image.new("RGB", (4, 4), TEX_RGB).save(png, format="PNG")
    props = "\n".join([
        "id#1=Test#toy", "name#1=Toy car", "category#1=Bedroom", "model#1=/lib/toy/toy.obj", "creator#1=Someone \\u00e9",
        "id#2=Test#arm", "name#2=Armchair", "category#2=Living room", "model#2=/lib/toy/toy.obj",
        "modelRotation#2=0 0 1 0 1 0 -1 0 0",  # 90 degrees about the up axis (y)
        "id#3=Test#carpet", "name#3=Carpet", "category#3=Living room", "model#3=/lib/toy/toy.obj",
    ]) + "\n"
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as z:
        z.writestr("PluginFurnitureCatalog.properties", props)
        z.writestr("lib/toy/toy.obj", obj)
        z.writestr("lib/toy/m.mtl", mtl)
        z.writestr("lib/toy/t.png", png.getvalue())
    return buf.getvalue()


@pytest.fixture()
def source(tmp_path):
    d = tmp_path / "furniture"
    d.mkdir()
    (d / "BlendSwap-CC-BY.sh3f").write_bytes(_library())
    return d


def test_catalog_parsing_and_selection(source):
    entries = catalog(open_libraries(source))
    assert [e.name for e in entries] == ["Toy car", "Armchair", "Carpet"]
    assert entries[0].creator == "Someone \u00e9" and entries[0].model == "lib/toy/toy.obj" and entries[0].rotation is None
    assert entries[1].rotation == (0.0, 0.0, 1.0, 0.0, 1.0, 0.0, -1.0, 0.0, 0.0)
    assert [e.name for e in select(entries, "cars")] == ["Toy car"]  # not the carpet
    assert [e.name for e in select(entries, "chairs")] == ["Armchair"]
    assert select(entries, "tabletop") == []
    with pytest.raises(FurnitureError, match="unknown setting"):
        select(entries, "boats")
    assert parse_catalog("name#4=No model\n", "x") == []


def test_import_normalises_orients_colours_and_records_the_licence(source, tmp_path):
    import trimesh

    r = import_setting("cars", tmp_path / "cars", source, progress=False)
    (m,) = r["models"]
    assert m["licence"] == "CC-BY-3.0" and m["source"]["library"] == "BlendSwap-CC-BY" and m["source"]["id"] == "Test#toy"
    mesh = trimesh.load(tmp_path / "cars" / m["file"], process=False)
    v = np.asarray(mesh.vertices)
    # y-up 4 x 2 x 1 -> z-up: x stays, depth goes to y, height to z; centred, largest half-extent 1
    assert np.allclose(v.min(0), [-1.0, -0.25, -0.5], atol=1e-6) and np.allclose(v.max(0), [1.0, 0.25, 0.5], atol=1e-6)
    assert m["half_extents"] == pytest.approx([1.0, 0.25, 0.5], abs=1e-6)
    colors = np.asarray(mesh.visual.vertex_colors)[:, :3]
    red = v[:, 0] < 0.1  # the red box spans x in [-1, 0] after scaling, the textured one [0.25, 1]
    assert (colors[red] == [255, 0, 0]).all()
    assert np.abs(colors[~red].astype(int) - np.array(TEX_RGB)).max() <= 1  # the texture's mean colour
    saved = json.loads((tmp_path / "cars" / "models.json").read_text())
    assert saved["counts"] == {"seen": 1, "unseen": 0} and saved["models"][0]["name"] == m["name"]
    # the armchair's modelRotation turns it by 90 degrees about the up axis before the frame change
    r = import_setting("chairs", tmp_path / "chairs", source, progress=False)
    assert r["models"][0]["half_extents"] == pytest.approx([0.25, 1.0, 0.5], abs=1e-6)


def test_import_reads_the_debian_package(source, tmp_path):
    tar_buf = io.BytesIO()
    with tarfile.open(fileobj=tar_buf, mode="w:gz") as tar:
        data = (source / "BlendSwap-CC-BY.sh3f").read_bytes()
        info = tarfile.TarInfo("./usr/share/sweethome3d/furniture/BlendSwap-CC-BY.sh3f")
        info.size = len(data)
        tar.addfile(info, io.BytesIO(data))
    members = [(b"debian-binary", b"2.0\n"), (b"data.tar.gz", tar_buf.getvalue())]
    deb = b"!<arch>\n" + b"".join(n.ljust(16) + b"0".ljust(12) + b"0".ljust(6) + b"0".ljust(6) + b"100644".ljust(8)
                                  + str(len(d)).encode().ljust(10) + b"`\n" + d + (b"\n" if len(d) % 2 else b"") for n, d in members)
    (tmp_path / "f.deb").write_bytes(deb)
    assert [e.name for e in catalog(open_libraries(tmp_path / "f.deb"))] == ["Toy car", "Armchair", "Carpet"]
    (tmp_path / "bad.deb").write_bytes(b"not an archive")
    with pytest.raises(FurnitureError, match="not a Debian package"):
        open_libraries(tmp_path / "bad.deb")
    with pytest.raises(FurnitureError, match="no furniture source"):
        open_libraries(tmp_path / "missing")


def test_splits_hold_a_third_unseen_and_depend_only_on_the_seed():
    names = [f"m{i}" for i in range(13)]
    a = assign_splits(names, seed=0)
    assert sum(s == "unseen" for s in a.values()) == 5  # ceil(13 / 3)
    assert a == assign_splits(list(reversed(names)), seed=0)
    assert a != assign_splits(names, seed=1)


def test_an_imported_folder_is_a_shape_set_for_the_prior(source, tmp_path):
    from prismonet.shapes.decoder import SDFDecoderConfig
    from prismonet.shapes.pretrain import PretrainConfig, load_shape_set, pretrain
    from prismonet.shapes.sdf_samples import SamplingConfig

    import_setting("cars", tmp_path / "cars", source, progress=False)
    shapes = load_shape_set(str(tmp_path / "cars"))
    assert shapes.name == "cars:seen" and len(shapes.meshes) == 1 and shapes.category_ids == (0,)
    v, f = shapes.meshes[0]
    assert np.allclose(np.abs(v).max(0), [1.0, 0.25, 0.5], atol=1e-6) and f.shape[1] == 3
    with pytest.raises(ValueError, match="no 'unseen' models"):
        load_shape_set(str(tmp_path / "cars"), split="unseen")
    with pytest.raises(ValueError, match="import-furniture"):
        load_shape_set(str(tmp_path / "nothing"))
    cfg = PretrainConfig(decoder=SDFDecoderConfig(latent_dim=4, width=16, depth=2), sampling=SamplingConfig(num_points=1024),
                         epochs=2, points_per_shape=512)
    prior = pretrain(cfg, tmp_path / "prior", shape_set=shapes, progress=False)
    assert prior.shape_names == ["blendswap-cc-by-1-toy-car"] and prior.info["shape_set"] == "cars:seen"
    # the renderer's box: the car's extents plus the padding of 0.1 (the Clevr prior's: the padded cube)
    lo, hi = prior.bounds
    assert np.allclose(lo, [-1.1, -0.35, -0.6], atol=1e-6) and np.allclose(hi, [1.1, 0.35, 0.6], atol=1e-6)
    from prismonet.shapes.prior import load_prior

    assert load_prior().bounds == ((-1.1,) * 3, (1.1,) * 3)


def test_scenes_of_imported_meshes_keep_their_colours(source, tmp_path):
    from prismonet.data.clevr import ClevrConfig
    from prismonet.data.generate import render_range

    import_setting("cars", tmp_path / "cars", source, progress=False)
    cfg = ClevrConfig(num_objects=2, shapes=str(tmp_path / "cars"), scale_range=(0.6, 0.7))
    out = render_range(cfg.to_dict(), 0, 0, 3)
    assert (out["obj_color"][:, :2] == -1).all() and (out["obj_shape"][:, :2] == 0).all()
    pix = out["rgb"][out["instance"] > 0].astype(np.float64)
    assert len(pix) > 100
    # every object pixel is a shaded red or a shaded texture colour: parallel to one of the two albedos
    albedos = np.array([[255.0, 0.0, 0.0], TEX_RGB])
    cos = (pix / np.linalg.norm(pix, axis=1, keepdims=True)) @ (albedos / np.linalg.norm(albedos, axis=1, keepdims=True)).T
    assert (cos.max(1) > 0.995).all()
    assert (cos.argmax(1) == 0).any() and (cos.argmax(1) == 1).any()


def test_rotation_error_up_to_the_settings_pseudo_symmetry(source, tmp_path):
    """The paper's bracketed rotation errors: cars modulo 180 degrees, chairs modulo 90; Clevr keeps its
    per-shape symmetries and a dataset without an import none."""
    import math
    from types import SimpleNamespace

    from prismonet.evaluation.evaluate import setting_symmetry
    from prismonet.evaluation.metrics import angle_error

    import_setting("cars", tmp_path / "cars", source, progress=False)
    ds = SimpleNamespace(meta={"config": {"shapes": str(tmp_path / "cars")}})
    assert setting_symmetry(ds) == math.pi
    assert angle_error(math.radians(190), 0.0, setting_symmetry(ds)) == pytest.approx(10.0)
    assert setting_symmetry(SimpleNamespace(meta={"config": {"shapes": "clevr"}})) is None
    assert setting_symmetry(SimpleNamespace(meta=None)) is None


def test_generated_shapes_take_a_colour_each_and_the_same_shapes_either_way(source, tmp_path, script):
    """``scripts/revolved_shapes.py --colors random``: each generated model gets one colour of its own, written to its
    PLY (the scenes read those) and to ``models.json``; the meshes are those of ``--colors grey`` for the same seed."""
    from prismonet.shapes.library import shape_library

    rev = script("revolved_shapes")
    import_setting("cars", tmp_path / "cars", source, progress=False)
    assert rev.main([str(tmp_path / "cars"), str(tmp_path / "grey"), "--count", "4"]) == 0
    assert rev.main([str(tmp_path / "cars"), str(tmp_path / "rand"), "--count", "4", "--colors", "random"]) == 0
    grey, rand = shape_library(str(tmp_path / "grey")), shape_library(str(tmp_path / "rand"))
    assert len(grey.specs) == len(rand.specs) == 5  # the imported car and four generated
    record = {m["name"]: m for m in json.loads((tmp_path / "rand" / "models.json").read_text())["models"]}
    seen = []
    for i, path in enumerate(rand.files):
        assert np.array_equal(grey.mesh(i)[0], rand.mesh(i)[0])
        name = path.rsplit("/", 1)[-1][:-4]
        if not name.startswith("generated"):
            continue
        fc = rand.face_colors(i)
        assert (fc == fc[0]).all() and (grey.face_colors(i) == 178).all()  # one colour per model; grey 0.7
        assert np.abs(fc[0] / 255 - np.asarray(record[name]["color"])).max() < 0.003
        seen.append(tuple(fc[0]))
    assert len(set(seen)) == 4
    rng = np.random.default_rng(0)
    c = np.array([rev.random_color(rng) for _ in range(500)])
    assert c.min() >= 0 and c.max() <= 1 and c.max(1).min() >= 0.08 - 1e-9  # HSV value is the largest channel
