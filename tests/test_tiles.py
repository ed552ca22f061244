"""Tiled reading of crowded photos (``realdata.tiles``): the tile grid, cut detections, merging by hand, and
``real evaluate --tiles`` end to end on a photo made of two copies of one scene."""

import json
from pathlib import Path

import numpy as np
import pytest

from realdata.tiles import TileConfig, inner_edges, mask_cut, merge_detections, tile_boxes


def test_tile_grid_covers_the_region_with_the_overlap_asked():
    # 2 along the shorter side (356) sharing a quarter: side ceil(356 / 1.75) = 204, starts 0 and 152
    tiles = tile_boxes((28, 0, 413, 356), 2, 0.25)
    assert {t[2] for t in tiles} == {204} and all(t[2] == t[3] for t in tiles)
    xs, ys = sorted({t[0] for t in tiles}), sorted({t[1] for t in tiles})
    assert ys == [0, 152] and xs[0] == 28 and xs[-1] + 204 == 28 + 413
    assert len(tiles) == len(xs) * len(ys) == 6  # (413 - 204) / (0.75 * 204) = 1.37 -> 3 columns
    # neighbours share at least the overlap asked, and every pixel of the region is in some tile
    assert all(b - a <= 0.75 * 204 for a, b in zip(xs, xs[1:])) and ys[1] - ys[0] <= 0.75 * 204
    cover = np.zeros((356, 413 + 28), bool)
    for x, y, s, _ in tiles:
        cover[y : y + s, x : x + s] = True
    assert cover[:, 28:].all() and not cover[:, :28].any()
    assert tile_boxes((5, 6, 100, 80), 1, 0.25) == [(5, 6, 80, 80), (25, 6, 80, 80)]  # one across the short side
    assert tile_boxes((0, 0, 90, 90), 1, 0.5) == [(0, 0, 90, 90)]
    with pytest.raises(ValueError, match="overlap"):
        tile_boxes((0, 0, 90, 90), 2, 1.0)


def test_inner_edges_and_cut_masks():
    region = (0, 0, 300, 200)
    assert inner_edges((0, 0, 120, 120), region) == (False, False, True, True)
    assert inner_edges((180, 80, 120, 120), region) == (True, True, False, False)
    m = np.zeros((8, 8), bool)
    m[3:5, 6:8] = True  # touches the right edge
    assert mask_cut(m, (False, False, True, False)) and not mask_cut(m, (True, True, False, True))


def test_merge_keeps_whole_before_cut_and_drops_duplicates_by_hand():
    boxes = np.array([[0, 0, 20, 20],     # 0: whole
                      [0, 0, 8, 8],       # 1: a cut part of the same object: IoU 0.16, but all of it inside box 0 -> dropped
                      [20, 0, 30, 10],    # 2: cut, nothing else there -> kept
                      [50, 0, 60, 10],    # 3: whole, small score
                      [51, 0, 61, 10],    # 4: whole, larger score, IoU 9/11 with 3 -> 3 dropped
                      [70, 0, 80, 10]])   # 5: whole, alone
    scores = np.array([50.0, 90.0, 40.0, 10.0, 20.0, 5.0])
    cut = np.array([False, True, True, False, False, False])
    assert merge_detections(boxes, scores, cut).tolist() == [0, 4, 5, 2]
    # a box inside another by less than the cover asked, and overlapping it by IoU under the bar, stays
    kept = merge_detections(np.array([[0, 0, 10, 10], [7, 0, 17, 10]]), np.array([2.0, 1.0]), np.zeros(2, bool))
    assert kept.tolist() == [0, 1]  # IoU 30 / 170 = 0.18, 0.3 of the smaller inside
    assert merge_detections(np.zeros((0, 4)), np.zeros(0), np.zeros(0, bool)).tolist() == []


def test_real_evaluate_in_tiles_finds_a_scene_twice_side_by_side(tmp_path):
    """Two copies of one rendered scene side by side make a photo with twice its objects; read in tiles, the
    merged detections are scored against the true boxes of both copies, and each tile has its own outputs."""
    import cv2

    from prismonet.assets import SHIPPED_SAMPLES, asset_path
    from prismonet.data.dataset import SceneDataset
    from realdata.evaluate import evaluate_photos

    b = SceneDataset(asset_path(SHIPPED_SAMPLES), "test").batch([0])
    rgb = (b.rgb[0].permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)
    photo = np.concatenate([rgb, rgb], 1)  # 128 x 64: the region is one tile high, so tiles run across
    cv2.imwrite(str(tmp_path / "twice.png"), photo[..., ::-1])
    instance, boxes = b.instance[0].numpy(), []
    for k in np.unique(instance[instance > 0]):
        v, u = np.nonzero(instance == k)
        if len(u) >= 25:
            for dx in (0, 64):
                boxes.append([float(u.min()) - 0.5 + dx, float(v.min()) - 0.5, float(u.max()) + 0.5 + dx, float(v.max()) + 0.5])
    labels = tmp_path / "labels"
    labels.mkdir()
    (labels / "twice.json").write_text(json.dumps({"photo": "../twice.png", "objects": [{"box": b} for b in boxes]}))
    r = evaluate_photos(labels, tmp_path / "e", "shipped", progress=False, box=(0, 0, 128, 64), tiling=TileConfig(2, 0.0))
    p = r["photos"][0]
    assert p["true_objects"] == len(boxes) and p["true_in_view"] == len(boxes)
    summary = json.loads((tmp_path / "e" / "summary.json").read_text())[0]
    assert [t["prepare"]["crop_box"] for t in summary["tiles"]] == [[0, 0, 64, 64], [64, 0, 64, 64]]
    assert all(Path(t["figure"]).is_file() and Path(t["scene"]).is_file() for t in summary["tiles"])
    assert Path(p["figure"]).is_file() and p["objects_found"] == len(summary["detections"]["boxes"])
    from realdata.evaluate import format_real_table

    assert "| twice.png | 2 tiles | " in format_real_table(r) and "| read |" in format_real_table(r)
    assert any("read as 1 tile across, not 2" in w for w in summary["warnings"])  # 64 px high: one tile across
    # each tile is the scene itself, as the shipped model was trained on it: most objects are found in both
    assert p["box_AR0.5"] >= 0.5
    # the size rule: objects of a median size under 1e6 px are "small" (tiled); none is under 1 px (kept whole);
    # the PSNR rule: every reading is under 1,000 dB (tiled)
    for below, psnr, reading in ((1e6, None, "tiles"), (1.0, None, "whole"), (1.0, 1e3, "tiles")):
        run = tmp_path / f"rule{below:g}_{psnr}"
        r = evaluate_photos(labels, run, "shipped", progress=False, box=(0, 0, 128, 64),
                            tiling=TileConfig(2, 0.0, below_px=below, below_psnr=psnr))
        s = json.loads((run / "summary.json").read_text())[0]
        assert s["reading"] == reading and s["whole_median_px"] > 1.0 and ("tiles" in s) == (reading == "tiles")
        assert s["tiles_across"] == (2.0 if reading == "tiles" else 1.0) and 5.0 < s["whole_psnr"] < 60.0


def test_tiles_are_refused_with_a_calibration(tmp_path):
    from realdata.pipeline import prepare_photos

    with pytest.raises(ValueError, match="uncalibrated"):
        prepare_photos([str(tmp_path / "x.png")], tmp_path / "o", calibration=tmp_path / "c.yaml", tiling=TileConfig(2))


def test_views_decoded_together_give_what_one_at_a_time_gives(tmp_path, monkeypatch):
    """``reconstruct_photos`` decodes ``BATCH`` views at once: the same objects, boxes and scores as one by one."""
    import realdata.reconstruct as rc

    photos = [str(Path(rc.__file__).parent / "samples" / n) for n in ("smarties.png", "stuff.jpg")]
    together = rc.reconstruct_photos(photos, tmp_path / "a", "tabletop_keep", tiling=TileConfig(2), progress=False, meshes=False)
    monkeypatch.setattr(rc, "BATCH", 1)
    alone = rc.reconstruct_photos(photos, tmp_path / "b", "tabletop_keep", tiling=TileConfig(2), progress=False, meshes=False)
    assert len(together[0]["tiles"]) > 1
    for x, y in zip(together, alone):
        assert x["objects_found"] == y["objects_found"] and x["detections"]["scores"] == y["detections"]["scores"]
        assert np.allclose(x["detections"]["boxes"], y["detections"]["boxes"], atol=1e-6)
        assert all(t["mesh"] is None for t in x["tiles"])


def test_a_second_run_into_the_same_folder_reads_only_its_own_photos(tmp_path):
    """``reconstruct_photos`` prepares into ``OUT/prepared``: an earlier run's prepared views there are cleared first."""
    from realdata.reconstruct import reconstruct_photos

    samples = Path(__file__).resolve().parents[1] / "realdata" / "samples"
    reconstruct_photos([samples / "smarties.png"], tmp_path, "tabletop_keep", tiling=TileConfig(2), progress=False, meshes=False)
    r = reconstruct_photos([samples / "stuff.jpg"], tmp_path, "tabletop_keep", progress=False, meshes=False)
    assert [Path(x["photo"]).name for x in r] == ["stuff.jpg"]
    assert sorted(p.name for p in (tmp_path / "prepared" / "rgb").iterdir()) == ["stuff.png"]


def test_tiles_sized_to_the_objects_by_hand():
    from realdata.tiles import MAX_ZOOM

    cfg = TileConfig(overlap=0.25, target_px=400.0)
    assert cfg.tiles_for(100.0) == pytest.approx(1 + (2.0 - 1) / 0.75)  # zoom sqrt(400 / 100) = 2
    assert cfg.tiles_for(350.0) == 1.0  # zoom 1.07: read whole
    assert cfg.tiles_for(0.0) == pytest.approx(1 + (MAX_ZOOM - 1) / 0.75)  # nothing found: the most zoom
    # a fractional count sets the side to the region's short side over the zoom
    assert tile_boxes((0, 0, 300, 200), cfg.tiles_for(100.0), 0.25)[0][2] == 100
    with pytest.raises(ValueError, match="size target"):
        TileConfig(target_px=0.0)


def test_the_whole_reading_picks_the_tiles_by_hand():
    """``TileConfig.tiles_after``: fine tiles for the smallest objects, the plain count where objects are small, none
    are found or the reading is poor, else whole; in that order."""
    cfg = TileConfig(2, below_px=120.0, below_psnr=18.0, fine_tiles=3, fine_below_px=80.0)
    assert cfg.reads_whole_first
    assert cfg.tiles_after(60.0, 12, 25.0) == 3.0  # small objects: the finest tiles, however well read
    assert cfg.tiles_after(80.0, 12, 25.0) == 2.0  # the fine bound is strict
    assert cfg.tiles_after(100.0, 5, 25.0) == 2.0  # under 120 px
    assert cfg.tiles_after(0.0, 0, 25.0) == 2.0  # nothing found: the plain count, not the fine one
    assert cfg.tiles_after(178.0, 3, 16.0) == 2.0  # large blobs, read poorly
    assert cfg.tiles_after(178.0, 3, 18.0) == 1.0  # the PSNR bound is strict
    assert cfg.tiles_after(178.0, 3, None) == 1.0  # no PSNR measured: whole
    plain = TileConfig(2, below_px=120.0)
    assert plain.tiles_after(178.0, 3, 5.0) == 1.0 and plain.tiles_after(60.0, 3, 30.0) == 2.0
    assert not TileConfig(2).reads_whole_first and TileConfig(1, below_px=120.0, fine_tiles=3, fine_below_px=80.0).reads_whole_first
    record = cfg.record()
    assert record["below_psnr"] == 18.0 and record["fine_tiles"] == 3 and record["fine_below_px"] == 80.0


@pytest.mark.parametrize("kwargs, match", [
    (dict(below_px=120.0, below_psnr=0.0), "PSNR rule"),
    (dict(below_px=120.0, fine_tiles=3), "give both"),
    (dict(below_px=120.0, fine_tiles=0.5, fine_below_px=80.0), "fine tiles"),
    (dict(below_px=120.0, fine_tiles=3, fine_below_px=-1.0), "fine tile size"),
    (dict(below_psnr=18.0), "refine the size rule"),
    (dict(below_px=120.0, zoom_out=2.0), "zoom out: give both"),
    (dict(below_px=120.0, zoom_out=1.0, zoom_out_above_px=300.0), "factor above 1"),
    (dict(zoom_out=2.0, zoom_out_above_px=300.0), "needs the size rule"),
    (dict(target_px=400.0, below_px=120.0, zoom_out=2.0, zoom_out_above_px=300.0), "no --tile-size"),
])
def test_bad_tile_rules_are_refused(kwargs, match):
    with pytest.raises(ValueError, match=match):
        TileConfig(2, **kwargs)


def test_large_objects_are_read_zoomed_out_by_hand():
    """``TileConfig.zoom_out``: after the tile rules, a whole reading whose objects' median is above the bound asks for
    ``1 / zoom_out`` tiles across (the bound strict; nothing found never zooms out); alone, it reads whole first."""
    cfg = TileConfig(2, below_px=120.0, zoom_out=2.0, zoom_out_above_px=300.0)
    assert cfg.reads_whole_first and TileConfig(1, zoom_out=2.0, zoom_out_above_px=300.0).reads_whole_first
    assert cfg.tiles_after(100.0, 5, 25.0) == 2.0 and cfg.tiles_after(0.0, 0, 25.0) == 2.0  # the tile rule first
    assert cfg.tiles_after(300.0, 3, 25.0) == 1.0 and cfg.tiles_after(301.0, 3, 25.0) == 0.5
    assert TileConfig(1, zoom_out=2.0, zoom_out_above_px=300.0).tiles_after(0.0, 0, None) == 1.0
    assert cfg.record()["zoom_out"] == 2.0 and cfg.record()["zoom_out_above_px"] == 300.0


def test_a_zoomed_out_view_by_hand(tmp_path):
    """A 128 x 128 photo, grey 0.5 with a red 16 x 16 square at x, y 56-71, read zoomed out 2x from the box (0, 0, 128,
    128): a 256-pixel square on the same centre, from -64 to 191, four photo pixels to a view pixel; the square lands on
    view pixels 30-33, the rest of the view is the fill (the border's median, grey), and the outline maps a view mask
    back to photo pixels."""
    import cv2

    from realdata.boxes import mask_box, view_to_photo
    from realdata.pipeline import prepare_photos

    img = np.full((128, 128, 3), 128, np.uint8)
    img[56:72, 56:72] = (0, 0, 255)  # BGR red
    cv2.imwrite(str(tmp_path / "p.png"), img)
    rec = prepare_photos([str(tmp_path / "p.png")], tmp_path / "o", box=(0, 0, 128, 128), normalize="none",
                         tiling=TileConfig(0.5))[0]
    assert rec["zoom_out"] == 2.0 and rec["crop_box"] == [-64, -64, 256, 256]
    assert rec["outline"] == [[-64.5, -64.5], [191.5, -64.5], [191.5, 191.5], [-64.5, 191.5]]
    view = cv2.imread(str(tmp_path / "o" / "rgb" / "p.png"))[..., ::-1].astype(int)
    red = np.zeros((64, 64), bool)
    red[30:34, 30:34] = True
    assert (np.abs(view[red] - [255, 0, 0]) <= 1).all() and (np.abs(view[~red] - 128) <= 1).all()
    assert np.allclose(mask_box(red, view_to_photo(rec["outline"], 64)), (55.5, 55.5, 71.5, 71.5), atol=1e-4)
    from realdata.io import PhotoError

    with pytest.raises(PhotoError, match="does not fit"):
        prepare_photos([str(tmp_path / "p.png")], tmp_path / "bad", box=(100, 0, 64, 64), tiling=TileConfig(0.5))


def test_a_close_up_is_read_zoomed_out(tmp_path):
    """Through ``real evaluate``: a photo whose whole reading finds objects above the bound is read again zoomed out
    (its record and table say so; a bound above every object keeps it whole); a calibrated photo is refused."""
    import cv2

    from prismonet.assets import SHIPPED_SAMPLES, asset_path
    from prismonet.data.dataset import SceneDataset
    from realdata.evaluate import evaluate_photos, format_real_table
    from realdata.pipeline import prepare_photos

    b = SceneDataset(asset_path(SHIPPED_SAMPLES), "test").batch([0])
    cv2.imwrite(str(tmp_path / "p.png"), (b.rgb[0].permute(1, 2, 0).numpy()[..., ::-1] * 255).round().astype(np.uint8))
    labels = tmp_path / "labels"
    labels.mkdir()
    (labels / "p.json").write_text(json.dumps({"photo": "../p.png", "objects": [{"box": [0, 0, 10, 10]}]}))
    for above, reading in ((1.0, "zoomed out"), (1e6, "whole")):
        run = tmp_path / f"z{above:g}"
        r = evaluate_photos(labels, run, "shipped", progress=False, tiling=TileConfig(1, zoom_out=2.0, zoom_out_above_px=above))
        s = json.loads((run / "summary.json").read_text())[0]
        assert s["reading"] == reading and s["tiles_across"] == (0.5 if reading == "zoomed out" else 1.0)
        assert ("| p.png | zoomed out 2x |" in format_real_table(r)) == (reading == "zoomed out") and Path(s["figure"]).is_file()
        if reading == "zoomed out":  # scores in the whole view's pixels: four per view pixel at 2x; its views kept apart
            assert s["detections"]["scores"] and all(v % 4 == 0 for v in s["detections"]["scores"])
            assert (run / "prepared_zoom2" / "rgb" / "p.png").is_file() and (run / "whole" / "prepared" / "rgb" / "p.png").is_file()
    with pytest.raises(ValueError, match="uncalibrated"):
        prepare_photos([str(tmp_path / "p.png")], tmp_path / "c", calibration=tmp_path / "c.yaml", tiling=TileConfig(0.5))
