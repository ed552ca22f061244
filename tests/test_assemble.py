"""One 3-D scene from tiles (``realdata.assemble``): a tile that is the view maps objects onto themselves; otherwise an
object keeps its place in the photo, its size there, and its height over its size; end to end on a tiled photo."""

import numpy as np
import torch

from realdata.assemble import tile_to_view, view_box


def _camera():
    from prismonet.data.clevr import ClevrConfig, clevr_camera

    return clevr_camera(ClevrConfig(image_size=64))


def _objects(n=6, seed=0):
    g = torch.Generator().manual_seed(seed)
    scale = 0.3 + 0.5 * torch.rand(n, generator=g, dtype=torch.float64)
    xy = (torch.rand(n, 2, generator=g, dtype=torch.float64) - 0.5) * 5
    return torch.cat([xy, scale[:, None]], 1), scale  # resting on the ground z = 0: centre height = scale


def _project(cam, p):
    K, T = cam.K.double(), cam.T_world_cam.double()
    pc = (p - T[:3, 3]) @ T[:3, :3]
    return (pc @ K.T)[:, :2] / pc[:, 2:], pc[:, 2]


def test_view_box_is_the_square_around_the_region():
    assert view_box((10, 20, 300, 200)) == (10, -30, 300, 300)
    assert view_box((0, 0, 100, 100)) == (0, 0, 100, 100)


def test_a_tile_that_is_the_view_maps_objects_onto_themselves():
    pos, scale = _objects()
    p2, s2 = tile_to_view(pos, scale, _camera(), 0.0, (5, 7, 200, 200), (5, 7, 200, 200))
    assert torch.allclose(p2, pos, atol=1e-9) and torch.allclose(s2, scale, atol=1e-12)


def test_an_object_keeps_its_photo_pixel_its_photo_size_and_its_height_over_size():
    cam = _camera()
    pos, scale = _objects(seed=1)
    tile, view = (120, 40, 110, 110), (0, 0, 300, 300)
    p2, s2 = tile_to_view(pos, scale, cam, 0.0, tile, view)
    uv_t, d_t = _project(cam, pos)
    uv_v, d_v = _project(cam, p2)
    S = 64.0
    photo_t = torch.stack([tile[0] + (uv_t[:, 0] + 0.5) * tile[2] / S, tile[1] + (uv_t[:, 1] + 0.5) * tile[2] / S], 1)
    photo_v = torch.stack([view[0] + (uv_v[:, 0] + 0.5) * view[2] / S, view[1] + (uv_v[:, 1] + 0.5) * view[2] / S], 1)
    assert torch.allclose(photo_t, photo_v, atol=1e-6)  # the same photo pixel
    f = float(cam.K[0, 0])
    size_t, size_v = f * scale / d_t * tile[2] / S, f * s2 / d_v * view[2] / S  # photo pixels across
    assert torch.allclose(size_t, size_v, rtol=1e-6)  # (the camera is float32)
    assert torch.allclose(p2[:, 2] / s2, pos[:, 2] / scale, rtol=1e-6)  # still resting on the ground
    assert (s2 < scale).all()  # a tile is a zoomed-in view: its objects are smaller in the whole


def test_a_tiled_photo_gets_one_scene_and_one_mesh(tmp_path):
    import json
    from pathlib import Path

    from prismonet.scene import LatentScene
    from realdata.reconstruct import reconstruct_photos
    from realdata.tiles import TileConfig

    photo = Path(__file__).resolve().parents[1] / "realdata" / "samples" / "smarties.png"
    r = reconstruct_photos([photo], tmp_path / "r", "tabletop_keep", tiling=TileConfig(2), progress=False, resolution=16)[0]
    scene = LatentScene.load(r["scene"])
    assert scene.num_objects == r["objects_found"] > 0 and Path(r["mesh"]).is_file()
    assert json.loads((tmp_path / "r" / "summary.json").read_text())[0]["scene"] == r["scene"]
    assert np.isfinite(scene.position.numpy()).all() and (scene.scale > 0).all()


def test_a_photo_whose_tiles_find_nothing_somewhere_still_assembles(tmp_path):
    """The coffee close-up read by ``tabletop_wide``: some tiles find no object (their scene files hold none); the photo's
    scene is made from the tiles that do, or is absent when none does. (``tabletop_keep`` finds something in every
    tile since it takes back the slots its keep output drops, session 72.)"""
    from pathlib import Path

    from prismonet.scene import LatentScene
    from realdata.reconstruct import reconstruct_photos
    from realdata.tiles import TileConfig

    photo = Path(__file__).resolve().parents[1] / "realdata" / "samples" / "coffee.jpg"
    r = reconstruct_photos([photo], tmp_path / "r", "tabletop_wide", tiling=TileConfig(2), progress=False, meshes=False)[0]
    assert any(t["objects_found"] == 0 for t in r["tiles"])
    for t in r["tiles"]:  # a tile's scene file, where it has one, loads
        assert t["scene"] is None or LatentScene.load(t["scene"]).num_objects >= t["objects_found"]
    if r["objects_found"]:
        assert LatentScene.load(r["scene"]).num_objects == r["objects_found"]
    else:
        assert r["scene"] is None
