"""Labelled real photos and ``prismonet real evaluate``: hand-computed box measures, the view-to-photo
mapping, label validation, and the command on the shipped photos."""

import json
from pathlib import Path

import numpy as np
import pytest

from realdata.boxes import box_iou, mask_box, view_to_photo
from realdata.evaluate import box_ap_ar
from realdata.labels import LabelError, load_label, load_labels, pool_labels

LABELS = Path(__file__).resolve().parents[1] / "realdata" / "samples" / "labels"


def test_box_iou_by_hand():
    a = np.array([[0, 0, 10, 10]])
    b = np.array([[5, 0, 15, 10], [20, 20, 30, 30], [0, 0, 10, 10]])
    assert np.allclose(box_iou(a, b), [[50 / 150, 0.0, 1.0]])


def test_box_ap_ar_by_hand():
    truth = np.array([[0, 0, 10, 10], [20, 0, 30, 10]])
    # three predictions: the best-scored hits box 0, the second misses, the third hits box 1
    pred = np.array([[0, 0, 10, 10], [50, 50, 60, 60], [20, 0, 30, 11]])
    ap, ar = box_ap_ar(pred, np.array([3.0, 2.0, 1.0]), truth)
    # precision 1, 1/2, 2/3 at recall 1/2, 1/2, 1: interpolated AP = 0.5 * 1 + 0.5 * 2/3
    assert ap == pytest.approx(0.5 + 0.5 * 2 / 3) and ar == 1.0
    assert box_ap_ar(pred[:0], np.zeros(0), truth) == (0.0, 0.0)
    # one prediction on two true boxes that overlap it equally counts once
    assert box_ap_ar(np.array([[0, 0, 10, 10]]), np.array([1.0]), np.array([[0, 0, 10, 10], [0, 0, 10, 10]]))[1] == 0.5


def test_view_to_photo_maps_masks_to_photo_boxes():
    # a 64-px view that is a 2x crop of the photo starting at (100, 50)
    outline = [[99.5, 49.5], [227.5, 49.5], [227.5, 177.5], [99.5, 177.5]]
    H = view_to_photo(outline, 64)
    mask = np.zeros((64, 64), bool)
    mask[10:20, 30:35] = True
    assert np.allclose(mask_box(mask, H), (100 + 2 * 30 - 0.5, 50 + 2 * 10 - 0.5, 100 + 2 * 35 - 0.5, 50 + 2 * 20 - 0.5), atol=1e-4)


def test_shipped_labels_load():
    labels = load_labels(LABELS)
    assert [lab.photo.name for lab in labels] == ["blox.jpg", "coffee.jpg", "coins.png", "smarties.png", "stuff.jpg"]
    assert [len(lab.boxes) for lab in labels] == [9, 3, 24, 14, 5]
    assert all(w[0] and w[1] for lab in labels for w in lab.words)
    assert [lab.elevation_deg for lab in labels] == [30.0, 55.0, 85.0, 85.0, 85.0]


def test_bad_labels_are_refused(tmp_path):
    f = tmp_path / "x.json"
    f.write_text(json.dumps({"photo": "nothere.jpg", "objects": []}))
    with pytest.raises(LabelError, match="not there"):
        load_label(f)
    (tmp_path / "p.jpg").write_bytes(b"")
    for objects, words in (([{"box": [1, 2, 3]}], "four finite"), ([{"box": [5, 5, 1, 9]}], "x1 > x0"), (["a"], "not a JSON object")):
        f.write_text(json.dumps({"photo": "p.jpg", "objects": objects}))
        with pytest.raises(LabelError, match=words):
            load_label(f)
    for elev in (0, 90, "80", True):
        f.write_text(json.dumps({"photo": "p.jpg", "objects": [], "elevation_deg": elev}))
        with pytest.raises(LabelError, match="elevation_deg must be"):
            load_label(f)
    (tmp_path / "empty").mkdir()
    with pytest.raises(LabelError, match="no photo labels"):
        load_labels(tmp_path / "empty")
    with pytest.raises(LabelError, match="no such folder"):
        load_labels(tmp_path / "missing")


def test_pooled_labels_point_at_their_own_copies(tmp_path):
    """Two folders whose photos share a name pool into one: each photo copied under its prefix, each label pointing at
    its copy with the same boxes; a bad folder is refused before anything is written."""
    for prefix, box, byte in (("a", [1, 2, 3, 4], b"A"), ("b", [5, 6, 7, 8], b"B")):
        (tmp_path / prefix / "photos").mkdir(parents=True)
        (tmp_path / prefix / "photos" / "scene_0000.png").write_bytes(byte)
        (tmp_path / prefix / "scene_0000.json").write_text(json.dumps(
            {"photo": "photos/scene_0000.png", "elevation_deg": 40, "objects": [{"box": box, "colour": "red", "kind": "cube"}]}))
    assert pool_labels({"a": tmp_path / "a", "b": tmp_path / "b"}, tmp_path / "pooled") == 2
    labels = load_labels(tmp_path / "pooled")
    assert [lab.label_file.name for lab in labels] == ["a_scene_0000.json", "b_scene_0000.json"]
    assert [lab.photo.name for lab in labels] == ["a_scene_0000.png", "b_scene_0000.png"]
    assert [lab.photo.read_bytes() for lab in labels] == [b"A", b"B"]
    assert [lab.boxes for lab in labels] == [((1.0, 2.0, 3.0, 4.0),), ((5.0, 6.0, 7.0, 8.0),)]
    assert all(lab.elevation_deg == 40 and lab.photo.parent == tmp_path / "pooled" / "photos" for lab in labels)
    with pytest.raises(LabelError, match="no such folder"):
        pool_labels({"a": tmp_path / "a", "c": tmp_path / "missing"}, tmp_path / "refused")
    assert not (tmp_path / "refused").exists()


def test_real_evaluate_on_the_shipped_photos(tmp_path, capsys):
    from prismonet.cli import main

    assert main(["real", "evaluate", str(LABELS), "--out", str(tmp_path / "e"), "--quiet"]) == 0
    table = capsys.readouterr().out
    assert "| blox.jpg | 9 (9) |" in table and "| **all** | 55" in table
    r = json.loads((tmp_path / "e" / "real_evaluation.json").read_text())
    assert len(r["photos"]) == 5 and 0 <= r["overall"]["box_AP0.5"] <= 1 and 0 <= r["overall"]["foreground_IoU"] <= 1
    assert all(Path(p["figure"]).is_file() for p in r["photos"])
    assert {p["model"] for p in r["photos"]} == {"tabletop_keep"} and "(model tabletop_keep;" in table  # the photo default
    settings = json.loads((tmp_path / "e" / "settings.json").read_text())
    assert settings["model"] == "tabletop_keep" and settings["flags"]["labels"] == str(LABELS) and settings["preset"] is None
    within = sum(abs(p["objects_found"] - p["true_in_view"]) <= 2 for p in r["photos"])
    assert r["overall"]["count_within_slack"] == within and f"within ±2 of the objects in view on {within} of 5 photos" in table


def test_real_evaluate_hands_the_labels_elevations_to_a_camera_frame_model(tmp_path):
    """Asked to, a model that takes the camera as an input sees each uncalibrated photo from its label's
    elevation; ``--elevation`` overrides them; a one-camera model ignores them (it knows one view)."""
    from dataclasses import replace

    from prismonet.model.io import load_model, save_model
    from prismonet.model.prismonet import PriSMONet
    from realdata.evaluate import evaluate_photos

    net, info = load_model("shipped")
    cam_net = PriSMONet(replace(net.cfg, pose_frame="camera"))
    cam_net.load_state_dict(net.state_dict())
    save_model(cam_net, tmp_path / "cam_model", {k: v for k, v in info.items() if k.startswith("camera") or k == "ground_z"})
    labels = tmp_path / "labels"
    labels.mkdir()
    for name in ("coffee", "stuff"):
        d = json.loads((LABELS / f"{name}.json").read_text())
        d["photo"] = str((LABELS / d["photo"]).resolve())
        (labels / f"{name}.json").write_text(json.dumps(d))
    cams = lambda r: [p["camera"] for p in r["photos"]]
    r = evaluate_photos(labels, tmp_path / "a", tmp_path / "cam_model", progress=False, label_elevations=True)
    assert cams(r) == [f"model's training camera moved to {e} deg elevation (assumed)" for e in (55, 85)]
    r = evaluate_photos(labels, tmp_path / "b", tmp_path / "cam_model", progress=False, elevation=40.0, label_elevations=True)
    assert cams(r) == ["model's training camera moved to 40 deg elevation (assumed)"] * 2
    r = evaluate_photos(labels, tmp_path / "d", tmp_path / "cam_model", progress=False)  # not asked: the training camera
    assert cams(r) == ["model's training camera (assumed)"] * 2
    r = evaluate_photos(labels, tmp_path / "c", "shipped", progress=False, label_elevations=True)
    assert cams(r) == ["model's training camera (assumed)"] * 2


def _row(stem: str, scores, hits, true: int, found: int) -> dict:
    return {"photo": f"/x/{stem}.png", "scores": scores, "hits": hits, "true_objects": true, "true_in_view": true,
            "objects_found": found, "foreground_IoU": 0.5, "psnr": {"encoder": 20.0}, "box_AP0.5": 0.0, "box_AR0.5": 0.0}


def test_merge_evaluations_takes_each_photo_from_one_reading(tmp_path):
    """Two readings of photos a and b: a from the first, b from the second. The overall row is computed again, by hand:
    boxes pooled by score (0.9 hit, 0.8 miss, 0.7 hit) over 3 true objects: AR 2/3, AP (1 + 2/3) / 3; a counted within
    +-2, b (5 found for 1) not. A photo taken twice, one no reading gives, or one not in a reading is refused; the
    command line writes the merged file."""
    import json
    import subprocess
    import sys

    from realdata.evaluate import merge_evaluations, overall_measures

    one = {"photos": [_row("a", [0.9, 0.8], [True, False], 2, 2), _row("b", [0.5], [False], 1, 1)]}
    two = {"photos": [_row("a", [0.1], [False], 2, 1), _row("b", [0.7, 0.1, 0.1, 0.1, 0.1], [True] + [False] * 4, 1, 5)]}
    m = merge_evaluations([(one, {"a"}), (two, None)])
    o = m["overall"]
    assert [r["photo"] for r in m["photos"]] == ["/x/a.png", "/x/b.png"]
    assert o["box_AR0.5"] == pytest.approx(2 / 3) and o["box_AP0.5"] == pytest.approx((1 + 2 / 3) / 3)
    assert o["objects_found"] == 7 and o["count_within_slack"] == 1 and o == overall_measures(m["photos"])
    assert merge_evaluations([(one, None)])["overall"] == overall_measures(one["photos"])
    with pytest.raises(ValueError, match="taken from two"):
        merge_evaluations([(one, None), (two, {"b"})])
    with pytest.raises(ValueError, match="no part gives: b"):
        merge_evaluations([(one, {"a"})])
    with pytest.raises(ValueError, match="not in that evaluation: c"):
        merge_evaluations([(one, {"c"}), (two, None)])
    for name, res in (("one", one), ("two", two)):
        (tmp_path / name).mkdir()
        (tmp_path / name / "real_evaluation.json").write_text(json.dumps(res))
    script = Path(__file__).resolve().parents[1] / "scripts" / "merge_real_evaluations.py"
    run = subprocess.run([sys.executable, str(script), "--out", str(tmp_path / "m"), f"{tmp_path / 'one'}:a", str(tmp_path / "two")],
                         capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    assert json.loads((tmp_path / "m" / "real_evaluation.json").read_text())["overall"] == pytest.approx(o)
    bad = subprocess.run([sys.executable, str(script), "--out", str(tmp_path / "n"), str(tmp_path / "one"), f"{tmp_path / 'two'}:b"],
                         capture_output=True, text=True)
    assert bad.returncode == 2 and "taken from two evaluations" in bad.stderr.strip().splitlines()[-1]


def _ignore_label(tmp_path, ignore=((40, 0, 50, 10),)):
    """A 100 x 60 photo labelled with one object at (0, 0, 10, 10) and ignore boxes (default one at (40, 0, 50, 10))."""
    import cv2

    cv2.imwrite(str(tmp_path / "p.png"), np.zeros((60, 100, 3), np.uint8))
    f = tmp_path / "p.json"
    f.write_text(json.dumps({"photo": "p.png", "objects": [{"box": [0, 0, 10, 10]}], "ignore": [list(b) for b in ignore]}))
    return f


def test_ignore_boxes_count_for_nothing(tmp_path):
    """Three detections on a photo with one labelled object and one ignore box: on the object (score 3, a hit), on the
    ignore box (score 2: neither hit nor false, not found) and on nothing (score 1, false). By hand: found 2, AP over
    [hit, miss] = 1 at recall 1, AR 1; without the ignore box the same detections give found 3 and the same AP and AR
    (the false one ranks last either way), and the middle one ranked first would cost precision. A detection on the
    ignore box that matches the labelled object better is a hit (labels first). The ignore box's area is left out of the
    foreground IoU on both sides. Bad ignore boxes are refused in one line."""
    from realdata.evaluate import photo_measures

    lab = load_label(_ignore_label(tmp_path))
    assert lab.ignore == ((40.0, 0.0, 50.0, 10.0),)
    outline = [[-0.5, -0.5], [99.5, -0.5], [99.5, 59.5], [-0.5, 59.5]]
    det = {"boxes": [[0, 0, 10, 10], [41, 0, 50, 10], [70, 40, 80, 50]], "scores": [3.0, 2.0, 1.0]}
    m = photo_measures(lab, det, [outline], (60, 100))
    assert m["objects_found"] == 2 and m["hits"] == [True, False] and m["scores"] == [3.0, 1.0]
    assert m["ignored_boxes"] == [[41.0, 0.0, 50.0, 10.0]] and m["box_AP0.5"] == 1.0 and m["box_AR0.5"] == 1.0
    assert m["foreground_IoU"] == pytest.approx(100 / 200)  # the object, and the false box; the ignored box not at all
    first = photo_measures(lab, {"boxes": det["boxes"], "scores": [2.0, 3.0, 1.0]}, [outline], (60, 100))
    assert first["box_AP0.5"] == 1.0 and first["objects_found"] == 2  # ranked first, an ignored one costs nothing
    plain = photo_measures(replace_ignore(lab, ()), {"boxes": det["boxes"], "scores": [2.0, 3.0, 1.0]}, [outline], (60, 100))
    assert plain["objects_found"] == 3 and plain["box_AP0.5"] == pytest.approx(0.5) and plain["ignored_boxes"] == []
    both = photo_measures(replace_ignore(lab, ((0, 0, 10, 10),)), {"boxes": [[0, 0, 10, 10]], "scores": [1.0]}, [outline], (60, 100))
    assert both["hits"] == [True] and both["objects_found"] == 1
    for ignore, words in (("x", "ignore must be a list"), ([[1, 2, 3]], "ignore box 0: box must be")):
        f = tmp_path / "bad.json"
        f.write_text(json.dumps({"photo": "p.png", "objects": [], "ignore": ignore}))
        with pytest.raises(LabelError, match=words):
            load_label(f)


def replace_ignore(lab, ignore):
    from dataclasses import replace

    return replace(lab, ignore=tuple(tuple(float(v) for v in b) for b in ignore))


def test_rescore_measures_a_finished_run_against_new_labels(tmp_path, capsys):
    """A run's summary.json measured again: against labels with an ignore box the detection there drops out; the written
    file and the command line's (`real evaluate --rescore`, no model run) agree; a photo the run did not read is refused."""
    from prismonet.cli import main
    from realdata.evaluate import photo_measures, rescore

    (tmp_path / "labels").mkdir()
    f = _ignore_label(tmp_path / "labels")
    run = tmp_path / "run"
    run.mkdir()
    outline = [[-0.5, -0.5], [99.5, -0.5], [99.5, 59.5], [-0.5, 59.5]]
    rec = {"photo": str(tmp_path / "labels" / "p.png"), "detections": {"boxes": [[0, 0, 10, 10], [40, 0, 50, 10]], "scores": [3.0, 2.0]},
           "outlines": [outline], "psnr": {"encoder": 20.0}, "figure": "f.png", "camera": "assumed"}
    (run / "summary.json").write_text(json.dumps([rec]))
    r = rescore(run, tmp_path / "labels")
    want = photo_measures(load_label(f), rec["detections"], [outline], (60, 100))
    assert r["photos"][0]["objects_found"] == want["objects_found"] == 1 and r["photos"][0]["hits"] == want["hits"] == [True]
    assert json.loads((run / "real_evaluation.json").read_text())["overall"] == r["overall"]
    assert main(["real", "evaluate", str(tmp_path / "labels"), "--out", str(run), "--rescore"]) == 0
    assert "| p.png | 1 (1) | 1 |" in capsys.readouterr().out
    (run / "summary.json").write_text(json.dumps([{**rec, "photo": "/elsewhere/q.png"}]))
    with pytest.raises(ValueError, match="did not read p.png"):
        rescore(run, tmp_path / "labels")


def test_standin_labels_ignore_the_small_objects():
    """``scripts/labelled_photos.py``: an object of at least ``min_fraction`` of the image is labelled, a smaller
    visible one becomes an ignore box (pixel corners, as the hand labels)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("labelled_photos", Path(__file__).resolve().parents[1] / "scripts" / "labelled_photos.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    inst = np.zeros((20, 20), np.int32)
    inst[2:6, 3:8] = 1  # 20 px: 0.05 of the image
    inst[10:12, 10:12] = 2  # 4 px: 0.01
    boxes, small = mod.scene_label(inst, 0.02)
    assert boxes == [[2.5, 1.5, 7.5, 5.5]] and small == [[9.5, 9.5, 11.5, 11.5]]


def test_overall_measures_without_psnr():
    """Rows measured offline (no reconstruction readings) pool the same, with PSNR None."""
    from realdata.evaluate import overall_measures

    rows = [_row("a", [0.9, 0.8], [True, False], 2, 2), _row("b", [0.5], [True], 1, 1)]
    bare = [{k: v for k, v in r.items() if k != "psnr"} for r in rows]
    o, b = overall_measures(rows), overall_measures(bare)
    assert b["PSNR"] is None and o["PSNR"] == 20.0 and {k: v for k, v in o.items() if k != "PSNR"} == {k: v for k, v in b.items() if k != "PSNR"}
