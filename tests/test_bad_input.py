"""Every bad path, file and number gets one line and exit status 2; legal oddities are accepted.

Each case runs ``prismonet.cli.main`` in this process on files made in ``tmp_path``, and checks:
exit status 2, exactly one line on stderr that starts with ``prismonet: error:`` and names the
problem, no traceback, and no output path left behind that was not there before.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from prismonet.assets import shipped_model, shipped_samples
from prismonet.cli import main

PHOTO = Path(__file__).resolve().parents[1] / "realdata" / "samples" / "stuff.jpg"
CONFIG = Path(__file__).resolve().parents[1] / "configs" / "clevr3_shipped.json"


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """Small inputs, good and bad, shared by the cases."""
    from prismonet.data.packed import read_meta, write_subset

    root = tmp_path_factory.mktemp("bad_inputs")
    write_subset(shipped_samples(), "test", range(4), root / "good")

    def variant(name, change):
        d = root / name
        shutil.copytree(root / "good", d)
        change(d)
        return d

    def moved_camera(d):
        T = np.load(d / "test" / "T_world_cam.npy", mmap_mode="r+")
        T[2, :3, 3] += 3.0  # scene 2 seen from elsewhere, same K
        T.flush()

    def nan_depth(d):
        a = np.load(d / "test" / "depth.npy", mmap_mode="r+")
        a[1, 5, 5] = np.nan
        a.flush()

    def no_depth(d):
        a = np.load(d / "test" / "depth.npy", mmap_mode="r+")
        a[:] = 0
        a.flush()

    def short_rows(d):
        a = np.load(d / "test" / "depth.npy")
        np.save(d / "test" / "depth.npy", a[:3])
        meta = read_meta(d)
        meta["splits"]["test"]["depth"].update(shape=[3, *a.shape[1:]], bytes=(d / "test" / "depth.npy").stat().st_size)
        (d / "meta.json").write_text(json.dumps(meta))

    f = {"good": root / "good"}
    f["moved_camera"] = variant("moved_camera", moved_camera)
    f["nan_depth"] = variant("nan_depth", nan_depth)
    f["no_depth"] = variant("no_depth", no_depth)
    f["short_rows"] = variant("short_rows", short_rows)
    f["meta_list"] = variant("meta_list", lambda d: (d / "meta.json").write_text("[1, 2]"))
    f["meta_nosplits"] = variant("meta_nosplits", lambda d: (d / "meta.json").write_text(
        json.dumps({k: v for k, v in read_meta(d).items() if k != "splits"})))
    # latent scenes: one good (from the shipped samples' first scene), and broken copies
    from prismonet.data.dataset import SceneDataset
    from prismonet.model.io import load_model
    from prismonet.scene import LatentScene

    import torch

    model, _ = load_model("shipped")
    b = SceneDataset(shipped_samples(), "test").batch([0])
    with torch.no_grad():
        out = model(b.rgb, b.K, b.T_world_cam, b.ground_z)
    good_scene = LatentScene.from_output(out, b, 0, "x").save(root / "scene.json")
    d = json.loads(Path(good_scene).read_text())
    f["scene"] = Path(good_scene)
    f["scene_list"] = root / "scene_list.json"
    f["scene_list"].write_text("[]")
    zero = json.loads(json.dumps(d))
    zero["camera"]["T_world_cam"] = [[0.0] * 4] * 4
    (f.__setitem__("scene_zero_cam", root / "scene_zero_cam.json"), f["scene_zero_cam"].write_text(json.dumps(zero)))
    flat = json.loads(json.dumps(d))
    flat["objects"][0]["scale"] = 0.0
    (f.__setitem__("scene_scale0", root / "scene_scale0.json"), f["scene_scale0"].write_text(json.dumps(flat)))
    notlist = json.loads(json.dumps(d))
    notlist["objects"] = {"a": 1}
    (f.__setitem__("scene_objs", root / "scene_objs.json"), f["scene_objs"].write_text(json.dumps(notlist)))
    # a model whose weights hold a NaN
    from safetensors.torch import load_file, save_file

    stem = shipped_model()
    shutil.copy(stem.with_suffix(".json"), root / "nanmodel.json")
    t = load_file(str(stem.with_suffix(".safetensors")))
    k = next(iter(t))
    t[k] = t[k].clone()
    t[k].view(-1)[0] = float("nan")
    save_file(t, str(root / "nanmodel.safetensors"))
    f["nan_model"] = root / "nanmodel.safetensors"
    # camera files
    f["yaml_trunc"] = root / "trunc.yaml"
    f["yaml_trunc"].write_text("%YAML:1.0\ncamera_matrix: !!opencv-matrix\n   rows: 3\n")
    f["yaml_garbage"] = root / "garbage.yaml"
    f["yaml_garbage"].write_bytes(bytes(range(256)) * 2)
    # ground calibrations for the 640x480 photo: a usable one, one below the table, one whose
    # long lens sees a sliver of the model's view
    from calibration.intrinsics import Calibration
    from calibration.storage import save_calibration
    from prismonet.data.clevr import ClevrConfig, clevr_camera

    T_ok = clevr_camera(ClevrConfig()).T_world_cam.double().numpy().copy()
    T_ok[:3, 3] *= 0.04
    K = np.array([[600.0, 0, 319.5], [0, 600.0, 239.5], [0, 0, 1]])
    save_calibration(Calibration(K, np.zeros(5), (640, 480), 0.1), root / "ground_ok.yml", T_ok)
    T_below = T_ok.copy()
    T_below[2, 3] = -0.2
    save_calibration(Calibration(K, np.zeros(5), (640, 480), 0.1), root / "ground_below.yml", T_below)
    K_long = K.copy()
    K_long[0, 0] = K_long[1, 1] = 30000.0
    save_calibration(Calibration(K_long, np.zeros(5), (640, 480), 0.1), root / "ground_long.yml", T_ok)
    f.update(ground_ok=root / "ground_ok.yml", ground_below=root / "ground_below.yml", ground_long=root / "ground_long.yml")
    (root / "labels").mkdir()
    (root / "labels" / "gone.json").write_text(json.dumps({"photo": "gone.jpg", "objects": []}))
    f["labels_missing_photo"] = root / "labels"
    # photos: a 1x1 one, and a good one under a file name that is not valid UTF-8
    import cv2

    f["tiny"] = root / "tiny.png"
    cv2.imwrite(str(f["tiny"]), np.full((1, 1, 3), 128, np.uint8))
    weird = os.fsdecode(os.fsencode(str(root)) + b"/caf\xe9.jpg")
    shutil.copy(PHOTO, weird)
    f["weird_photo"] = weird
    # folder datasets: annotation objects not a list; depth_scale 0
    main(["data", "to-folder", str(f["good"]), str(root / "folder"), "--count", "2"])
    ann = root / "folder_ann"
    shutil.copytree(root / "folder", ann)
    a = next((ann / "annotations").glob("*.json"))
    a.write_text(json.dumps({**json.loads(a.read_text()), "objects": "three"}))
    f["folder_ann"] = ann
    ds0 = root / "folder_ds0"
    shutil.copytree(root / "folder", ds0)
    meta = json.loads((ds0 / "dataset.json").read_text())
    (ds0 / "dataset.json").write_text(json.dumps({**meta, "depth_scale": 0}))
    f["folder_ds0"] = ds0
    f["a_file"] = root / "a_file.txt"
    f["a_file"].write_text("x")
    return f


# (case id, argv with {name} placeholders, words the message must contain)
CASES = [
    ("sheet unknown ext", ["data", "sheet", "{good}", "--split", "test", "--out", "{tmp}/x.xyz"], "cannot write images"),
    ("sheet count 0", ["data", "sheet", "{good}", "--out", "{tmp}/s.png", "--count", "0"], "--count"),
    ("evaluate json dir", ["evaluate", "shipped", "{good}", "--json", "{tmp}"], "is a folder"),
    ("intrinsics out dir", ["calibrate", "intrinsics", str(PHOTO), "--out", "{tmp}"], "is a folder"),
    ("edit out dir", ["edit", "{scene}", "--out", "{tmp}", "--remove", "0"], "is a folder"),
    ("edit render ext", ["edit", "{scene}", "--out", "{tmp}/e.json", "--remove", "0", "--render", "{tmp}/r.xyz"], "cannot write images"),
    ("subset out file", ["data", "subset", "{good}", "{a_file}", "--split", "test", "--count", "2"], "not a folder"),
    ("train out file", ["train", str(CONFIG), "--out", "{a_file}"], "not a folder"),
    ("demo out file", ["demo", "--out", "{a_file}"], "not a folder"),
    ("export out file", ["export", "--scene", "{scene}", "--out", "{a_file}"], "not a folder"),
    ("views out file", ["views", "{scene}", "--out", "{a_file}"], "not a folder"),
    ("prepare out file", ["real", "prepare", str(PHOTO), "--out", "{a_file}"], "not a folder"),
    ("out under a file", ["export", "--scene", "{scene}", "--out", "{a_file}/sub"], "is a file"),
    ("meta list", ["evaluate", "shipped", "{meta_list}"], "expected a JSON object"),
    ("meta no splits", ["evaluate", "shipped", "{meta_nosplits}"], "'splits'"),
    ("rows disagree", ["evaluate", "shipped", "{short_rows}", "--split", "test"], "disagree"),
    ("scene list", ["views", "{scene_list}", "--out", "{tmp}/v"], "expected a JSON object"),
    ("scene zero camera", ["edit", "{scene_zero_cam}", "--out", "{tmp}/z.json", "--remove", "0"], "rigid"),
    ("scene scale 0", ["export", "--scene", "{scene_scale0}", "--out", "{tmp}/x"], "scale must be positive"),
    ("scene objects not list", ["views", "{scene_objs}", "--out", "{tmp}/v"], "list"),
    ("yaml truncated", ["real", "prepare", str(PHOTO), "--out", "{tmp}/p", "--camera", "{yaml_trunc}"], "FileStorage"),
    ("yaml garbage", ["real", "prepare", str(PHOTO), "--out", "{tmp}/p", "--camera", "{yaml_garbage}"], "FileStorage"),
    ("train on a folder", ["train", "{tmp}", "--out", "{tmp}/run"], "not a file"),
    ("views fps 0", ["views", "{scene}", "--out", "{tmp}/v", "--fps", "0"], "--fps"),
    ("views size huge", ["views", "{scene}", "--out", "{tmp}/v", "--size", "100000"], "4096"),
    ("prepare size 0", ["real", "prepare", str(PHOTO), "--out", "{tmp}/p", "--size", "0"], "--size"),
    ("prepare size huge", ["real", "prepare", str(PHOTO), "--out", "{tmp}/p", "--size", "100000"], "4096"),
    ("export resolution huge", ["export", "--scene", "{scene}", "--out", "{tmp}/x", "--resolution", "5000"], "512"),
    ("slots huge", ["train", str(CONFIG), "--out", "{tmp}/run", "--set", "model.num_slots=1000000"], "at most 64"),
    ("moved camera", ["evaluate", "shipped", "{moved_camera}", "--split", "test"], "camera pose"),
    ("moved camera reconstruct", ["reconstruct", "shipped", "{moved_camera}", "--split", "test", "--out", "{tmp}/r"], "camera pose"),
    ("nan weights", ["evaluate", "{nan_model}", "{good}", "--split", "test"], "NaN"),
    ("nan depth", ["evaluate", "shipped", "{nan_depth}", "--split", "test"], "NaN"),
    ("train nan depth", ["train", str(CONFIG), "--out", "{tmp}/run", "--set", "data={nan_depth}", "--set", "split=test"], "NaN"),
    ("train no depth", ["train", str(CONFIG), "--out", "{tmp}/run", "--set", "data={no_depth}", "--set", "split=test"], "no depth"),
    ("jitter nan", ["data", "clevr", "--out", "{tmp}/c", "--camera-jitter", "nan"], "finite"),
    ("jitter negative", ["data", "clevr", "--out", "{tmp}/c", "--camera-jitter", "-1"], "--camera-jitter"),
    ("depth_scale 0", ["evaluate", "shipped", "{folder_ds0}", "--split", "test"], "depth_scale"),
    ("annotation objects", ["evaluate", "shipped", "{folder_ann}", "--split", "test"], "'objects'"),
    ("edit remove -1", ["edit", "{scene}", "--out", "{tmp}/e.json", "--remove", "-1"], "object -1"),
    ("reconstruct count -2", ["reconstruct", "shipped", "{good}", "--split", "test", "--out", "{tmp}/r", "--count", "-2"], "--count"),
    ("gain nan", ["real", "reconstruct", str(PHOTO), "--out", "{tmp}/r", "--normalize", "manual", "--gain", "nan,1,1"], "--gain"),
    ("gain without manual", ["real", "reconstruct", str(PHOTO), "--out", "{tmp}/r", "--gain", "1,1,1"], "--normalize manual"),
    ("tiny photo", ["real", "prepare", "{tiny}", "--out", "{tmp}/p"], "smaller than"),
    ("reseed negative", ["evaluate", "shipped", "{good}", "--split", "test", "--reseed", "-1"], "--reseed"),
    ("reseed cycles 0", ["evaluate", "shipped", "{good}", "--split", "test", "--reseed", "2", "--reseed-cycles", "0"], "--reseed-cycles"),
    ("distill reseed grow", ["distill", "shipped", "{good}", "--split", "test", "--out", "{tmp}/d", "--reseed", "2", "--reseed-grow", "2"], "--reseed-grow"),
    ("refiner steps 0", ["refiner", "clevr3_fc", "{good}", "--split", "test", "--targets", "{tmp}", "--out", "{tmp}/r", "--steps", "0"], "steps"),
    ("refiner from a refined model", ["refiner", "shipped", "{good}", "--split", "test", "--targets", "{tmp}", "--out", "{tmp}/r"], "already has a refiner"),
    ("refiner no targets", ["refiner", "clevr3_fc", "{good}", "--split", "test", "--targets", "{tmp}", "--out", "{tmp}/r"], "no distillation targets"),
    ("refiner glimpse out of range", ["refiner", "clevr3_fc", "{good}", "--split", "test", "--targets", "{tmp}", "--out", "{tmp}/r",
                                      "--glimpse", "1.5"], "refiner_glimpse must be in"),
    ("box with ground pose", ["real", "prepare", str(PHOTO), "--out", "{tmp}/p", "--camera", "{ground_ok}", "--box", "0,0,64,64"], "--box"),
    ("label for a missing photo", ["real", "evaluate", "{labels_missing_photo}", "--out", "{tmp}/e"], "labels a photo that is not there"),
    ("labels folder missing", ["real", "evaluate", "{tmp}/nolabels", "--out", "{tmp}/e"], "no such folder of photo labels"),
    ("unit zero", ["real", "reconstruct", str(PHOTO), "--out", "{tmp}/r", "--unit", "0"], "--unit"),
    ("tiles zero", ["real", "reconstruct", str(PHOTO), "--out", "{tmp}/r", "--tiles", "0"], "--tiles"),
    ("tile overlap too large", ["real", "reconstruct", str(PHOTO), "--out", "{tmp}/r", "--tiles", "2", "--tile-overlap", "0.95"], "--tile-overlap"),
    ("tile size zero", ["real", "reconstruct", str(PHOTO), "--out", "{tmp}/r", "--tile-size", "0"], "--tile-size"),
    ("highlights zero", ["real", "reconstruct", str(PHOTO), "--out", "{tmp}/r", "--highlights", "0"], "--highlights"),
    ("highlights word", ["real", "evaluate", "{tmp}/nolabels", "--out", "{tmp}/e", "--highlights", "max"], "--highlights"),
    ("tile rule zero", ["real", "evaluate", "{tmp}/nolabels", "--out", "{tmp}/e", "--tiles", "2", "--tile-below", "0"], "--tile-below"),
    ("tile PSNR rule alone", ["real", "evaluate", "{tmp}/nolabels", "--out", "{tmp}/e", "--tiles", "2", "--tile-psnr-below", "18"],
     "--tile-below"),
    ("fine tiles zero", ["real", "evaluate", "{tmp}/nolabels", "--out", "{tmp}/e", "--tiles", "2", "--tile-below", "120",
                         "--tiles-fine", "0", "80"], "--tiles-fine"),
    ("tiles with a calibration", ["real", "reconstruct", str(PHOTO), "--out", "{tmp}/r", "--tiles", "2", "--camera", "{ground_ok}"], "uncalibrated"),
    ("camera below the table", ["real", "prepare", str(PHOTO), "--out", "{tmp}/p", "--camera", "{ground_below}"], "above the table"),
    ("view not covered", ["real", "prepare", str(PHOTO), "--out", "{tmp}/p", "--camera", "{ground_long}"], "of the model's view"),
    ("min pixels negative", ["real", "reconstruct", str(PHOTO), "--out", "{tmp}/r", "--min-pixels", "-5"], "--min-pixels"),
    ("set lr abc", ["train", str(CONFIG), "--out", "{tmp}/run", "--set", "lr=abc"], "lr: expected float"),
    ("unknown shape library", ["data", "clevr", "--shapes", "{tmp}/noshapes", "--out", "{tmp}/d", "--split", "2,0,0"], "unknown shape library"),
    ("towers min over max", ["data", "towers", "--objects", "3", "--min-objects", "4", "--out", "{tmp}/d"], "must not exceed"),
    ("randomize range unknown", ["data", "clevr", "--randomize-range", "focal=1,2", "--out", "{tmp}/d"], "NAME one of"),
    ("randomize range one value", ["data", "clevr", "--randomize-range", "focal_scale=1", "--out", "{tmp}/d"], "NAME=LO,HI"),
    ("randomize range reversed", ["data", "clevr", "--randomize-range", "focal_scale=2,1", "--out", "{tmp}/d"], "low <= high"),
    ("furniture source missing", ["shapes", "import-furniture", "cars", "--source", "{tmp}/nodeb", "--out", "{tmp}/f"], "no furniture source"),
    ("pretrain unknown shapes", ["shapes", "pretrain", "--shapes", "{tmp}/noshapes", "--out", "{tmp}/p"], "unknown shape set"),
    ("unknown model name", ["evaluate", "nosuchmodel", "{good}", "--split", "test"], "shipped models by name"),
    ("baseline figure no run", ["baselines", "figure", "{tmp}/norun", "--data", "{good}", "--out", "{tmp}/f.png"], "no such checkpoint"),
    ("blender python without bpy", ["data", "blender", "--rung", "a", "--out", "{tmp}/l", "--python", "/bin/true"], "cannot import bpy"),
    ("blender unknown rung", ["data", "blender", "--rung", "e", "--out", "{tmp}/l"], "invalid choice"),
    ("unknown command", ["bogus"], "invalid choice"),
]


def run(argv, capsys) -> tuple[int, str, str]:
    try:
        rc = main(argv)
    except SystemExit as e:  # argparse
        rc = e.code
    cap = capsys.readouterr()
    return rc, cap.out, cap.err


@pytest.mark.parametrize("name,argv,words", CASES, ids=[c[0] for c in CASES])
def test_bad_input_gets_one_line(name, argv, words, files, tmp_path, capsys):
    subs = {k: str(v) for k, v in files.items()} | {"tmp": str(tmp_path)}
    argv = [a.format(**subs) for a in argv]
    before = set(tmp_path.rglob("*"))
    rc, out, err = run(argv, capsys)
    lines = [line for line in err.splitlines() if line.strip()]
    assert rc == 2, (rc, err)
    assert len(lines) == 1 and lines[0].startswith("prismonet: error:"), err
    assert "Traceback" not in err + out
    assert words in lines[0], lines[0]
    assert set(tmp_path.rglob("*")) == before, "a refused command left files behind"


def test_legal_oddities_are_accepted(files, tmp_path, capsys):
    # a photo whose file name is not valid UTF-8 (cv2.imread crashed on it)
    rc, out, err = run(["real", "prepare", files["weird_photo"], "--out", str(tmp_path / "p")], capsys)
    assert rc == 0, err
    assert len(list((tmp_path / "p" / "rgb").glob("*.png"))) == 1
    # another camera is allowed when asked for
    rc, out, err = run(["evaluate", "shipped", str(files["moved_camera"]), "--split", "test", "--any-camera", "--quiet"], capsys)
    assert rc == 0, err
    # an existing empty output folder is fine
    (tmp_path / "empty").mkdir()
    rc, out, err = run(["data", "subset", str(files["good"]), str(tmp_path / "empty"), "--split", "test", "--count", "2"], capsys)
    assert rc == 0, err
    # a ground calibration: the photo is rectified to the model's view, the world map recorded (the Clevr model's
    # camera, which the fixture's calibration was made for)
    rc, out, err = run(["real", "prepare", str(PHOTO), "--out", str(tmp_path / "g"), "--camera",
                        str(files["ground_ok"]), "--model", "shipped"], capsys)
    assert rc == 0 and "rectified to the model's view at 0.04 m per model unit (derived)" in out, out + err
    rec = json.loads(next((tmp_path / "g" / "annotations").glob("*.json")).read_text())["prepare"]
    assert rec["coverage"] == 1.0 and rec["world"]["metres_per_unit"] == pytest.approx(0.04)
