"""``prismonet export``, ``edit`` and ``views`` on the shipped model and sample scenes."""

import cv2
import pytest
import trimesh

from prismonet.assets import shipped_samples
from prismonet.cli import main
from prismonet.scene import LatentScene


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    out = tmp_path_factory.mktemp("export")
    assert main(["export", "--data", str(shipped_samples()), "--index", "2", "--format", "obj", "--resolution", "24", "--out", str(out)]) == 0
    return out


def test_export_from_an_image(exported):
    mesh = trimesh.load(exported / "scene.obj", force="mesh")
    assert len(mesh.vertices) > 100
    assert (exported / "points_input.ply").stat().st_size > 0
    assert LatentScene.load(exported / "scene.json").num_objects == 3


def test_export_from_a_saved_scene(exported, tmp_path):
    assert main(["export", "--scene", str(exported / "scene.json"), "--format", "glb", "--resolution", "24", "--out", str(tmp_path)]) == 0
    assert (tmp_path / "scene.glb").is_file() and not (tmp_path / "points_input.ply").exists()


def test_edit_remove_swap_then_render(exported, tmp_path, capsys):
    out = tmp_path / "e.json"
    argv = ["edit", str(exported / "scene.json"), "--swap-shape", "0,1", "--remove", "2", "--out", str(out),
            "--render", str(tmp_path / "e.png"), "--allow-intersections"]
    assert main(argv) == 0
    src, new = LatentScene.load(exported / "scene.json"), LatentScene.load(out)
    assert new.num_objects == 2
    assert new.z_sh[0].tolist() == src.z_sh[1].tolist() and new.z_sh[1].tolist() == src.z_sh[0].tolist()
    assert new.position.tolist() == src.position[:2].tolist()
    assert cv2.imread(str(tmp_path / "e.png")).shape == (64, 64, 3)
    assert "L_int of the edited scene" in capsys.readouterr().out


def test_edit_that_makes_objects_intersect_is_rejected(exported, tmp_path, capsys):
    src = LatentScene.load(exported / "scene.json")
    x, y, z = src.position[0].tolist()
    out = tmp_path / "bad.json"
    assert main(["edit", str(exported / "scene.json"), "--move", f"1:{x},{y},{z}", "--out", str(out)]) == 2
    assert "objects intersect" in capsys.readouterr().err
    assert not out.exists()


def test_edit_usage_errors(exported, tmp_path, capsys):
    assert main(["edit", str(exported / "scene.json"), "--out", str(tmp_path / "x.json")]) == 2
    assert "no edit given" in capsys.readouterr().err
    assert main(["edit", str(exported / "scene.json"), "--move", "1:0,0", "--out", str(tmp_path / "x.json")]) == 2
    assert "expected 3 comma-separated numbers" in capsys.readouterr().err
    assert main(["edit", str(exported / "scene.json"), "--remove", "7", "--out", str(tmp_path / "x.json")]) == 2
    assert "objects 0..2" in capsys.readouterr().err


def test_views_orbit_and_pose(exported, tmp_path):
    assert main(["views", str(exported / "scene.json"), "--frames", "3", "--size", "32", "--out", str(tmp_path / "o"), "--quiet"]) == 0
    assert len(list((tmp_path / "o").glob("view_*.png"))) == 3 and (tmp_path / "o" / "orbit.gif").is_file()
    assert main(["views", str(exported / "scene.json"), "--eye", "0,-6,5", "--size", "48", "--out", str(tmp_path / "p")]) == 0
    assert cv2.imread(str(tmp_path / "p" / "view.png")).shape == (48, 48, 3)


@pytest.mark.parametrize(
    "argv, message",
    [
        (["demo", "--scenes", "0", "--out", "{tmp}/d"], "--scenes: must be >= 1"),
        (["export", "--out", "{tmp}/e"], "give either --scene FILE or --data DIR"),
        (["export", "--data", "{samples}", "--index", "99", "--out", "{tmp}/e"], "--index"),
        (["export", "--scene", "{tmp}/none.json", "--out", "{tmp}/e"], "no such latent-scene file"),
        (["views", "{scene}", "--frames", "0", "--out", "{tmp}/v"], "--frames: must be in [1, 3600]"),
        (["views", "{scene}", "--eye", "1,2", "--out", "{tmp}/v"], "--eye: expected 3 comma-separated numbers"),
        (["edit", "{scene}", "--swap-shape", "0", "--out", "{tmp}/x.json"], "--swap-shape: expected two object indices"),
        (["edit", "{scene}", "--add", "nofile", "--out", "{tmp}/x.json"], "--add: expected SCENE.json:OBJECT"),
        (["real", "reconstruct", "x.jpg", "--box", "1,2,3", "--out", "{tmp}/r"], "--box (x0,y0,width,height): expected 4 comma-separated integers"),
        (["real", "reconstruct", "x.jpg", "--gain", "a,b,c", "--out", "{tmp}/r"], "--gain (r,g,b): expected 3 comma-separated numbers"),
        (["data", "subset", "{samples}", "{tmp}/s", "--count", "0"], "--count: must be >= 1"),
    ],
)
def test_scene_command_errors_are_one_line(exported, tmp_path, capsys, argv, message):
    subst = {"{tmp}": str(tmp_path), "{samples}": str(shipped_samples()), "{scene}": str(exported / "scene.json")}
    args = []
    for a in argv:
        for k, v in subst.items():
            a = a.replace(k, v)
        args.append(a)
    assert main(args) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1
