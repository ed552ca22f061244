"""The ``prismonet`` command line: the demo, the data commands, one-line errors with exit code 2."""

import cv2
import pytest

from prismonet.cli import main


def test_demo_decomposes_the_shipped_scenes(tmp_path, capsys):
    import json

    out = tmp_path / "demo"
    assert main(["demo", "--out", str(out), "--scenes", "2", "--quiet"]) == 0
    fig = cv2.imread(str(out / "scene_001.png"))
    assert fig is not None and fig.shape[0] > 2 * 64 and fig.shape[1] > 4 * 64
    metrics = json.loads((out / "metrics.json").read_text())
    assert len(metrics["scenes"]) == 2 and 0 <= metrics["mean"]["AP0.5"] <= 1 and metrics["mean"]["PSNR"] > 10
    assert metrics["model"] == "clevr3_r4"  # the demo's start since session 108 (clevr3_sharp in sessions 90-107)
    printed = capsys.readouterr().out
    assert "| **mean** |" in printed and str(out / "metrics.json") in printed
    assert ("encoder, then 4 pose-search rounds, shapes tabulated at 24^3 in the first 3, every code of each category tried "
            "at the slot's footprint, 50 colour-fit steps") in printed
    assert main(["demo", "--out", str(out), "--scenes", "1", "--quiet"]) == 0  # re-runnable over its own output
    metrics = json.loads((out / "metrics.json").read_text())
    search = metrics["inference"]["search"]
    assert (search["rounds"], search["grid"], search["exact_rounds"], search["shape_trials"], search["shape_footprint"],
            metrics["inference"]["color_fit"]["steps"]) == (4, 24, 1, True, True, 50)


def test_demo_shape_trials_by_the_model_unless_told(tmp_path, capsys):
    """The demo's search takes the shape trials for the Clevr models of a fixed count (where they were measured: the shipped
    3-object model, `clevr2`), not for another model (the cars'; the block towers', whose prior is the same), and never
    with ``--no-shape-trials``; each figure and latent scene is written."""
    import json

    from prismonet.demo import run_demo
    from prismonet.model.inference import InferenceConfig

    out = tmp_path / "off"
    assert main(["demo", "--out", str(out), "--scenes", "1", "--fit-color", "0", "--no-shape-trials", "--quiet"]) == 0
    assert json.loads((out / "metrics.json").read_text())["inference"]["search"]["shape_trials"] is False
    assert "every code" not in capsys.readouterr().out
    cars = run_demo(tmp_path / "cars", 1, "cars", inference=InferenceConfig.of(search=3), progress=False, shape_trials=None)
    assert cars["inference"]["search"]["shape_trials"] is False and "every code" not in cars["steps"]
    assert (tmp_path / "cars" / "scene_000.png").is_file() and (tmp_path / "cars" / "scene_000.json").is_file()
    two_obj = run_demo(tmp_path / "c2", 1, "clevr2", inference=InferenceConfig.of(search=3), progress=False, shape_trials=None)
    assert two_obj["inference"]["search"]["shape_trials"] is True and two_obj["inference"]["search"]["grid"] == 0  # the MLP
    mlp = run_demo(tmp_path / "mlp", 1, inference=InferenceConfig.of(search=3), progress=False, shape_trials=None, trial_grid=0)
    assert (mlp["inference"]["search"]["rounds"], mlp["inference"]["search"]["grid"]) == (3, 0)  # --search-grid 0
    towers = run_demo(tmp_path / "tw", 1, "blocktowers", inference=InferenceConfig.of(search=3), progress=False, shape_trials=None)
    assert towers["inference"]["search"]["shape_trials"] is False
    told = run_demo(tmp_path / "twt", 1, "blocktowers", inference=InferenceConfig.of(search=3, shape_trials=True), progress=False)
    assert told["inference"]["search"]["shape_trials"] is True
    two = run_demo(tmp_path / "two", 2, inference=InferenceConfig.of(search=0), progress=False, shape_trials=None)
    assert two["steps"] == "encoder only, as the paper"  # no search: nothing to add the trials to
    assert [r["scene"] for r in two["scenes"]] == ["scene_000", "scene_001"]


def test_demo_feed_forward_as_the_paper(tmp_path, capsys):
    import json

    out = tmp_path / "demo"
    assert main(["demo", "--out", str(out), "--scenes", "1", "--search", "0", "--fit-color", "0", "--quiet"]) == 0
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["steps"] == "encoder only, as the paper" and (out / "scene_000.png").is_file()
    assert "encoder only, as the paper" in capsys.readouterr().out


def test_data_commands(tmp_path, capsys):
    ds = tmp_path / "ds"
    assert main(["data", "clevr", "--objects", "2", "--out", str(ds), "--split", "3,1,2", "--workers", "1", "--quiet"]) == 0
    assert "wrote 6 scenes" in capsys.readouterr().out
    assert main(["data", "verify", str(ds)]) == 0
    assert "test: 2 scenes ok" in capsys.readouterr().out
    assert main(["data", "sheet", str(ds), "--out", str(tmp_path / "s.png"), "--split", "val"]) == 0
    assert cv2.imread(str(tmp_path / "s.png")) is not None
    assert main(["data", "to-folder", str(ds), str(tmp_path / "f")]) == 0
    assert len(list((tmp_path / "f" / "rgb").glob("*.png"))) == 2
    more = tmp_path / "more"
    assert main(["data", "clevr", "--objects", "2", "--out", str(more), "--split", "2,0,0", "--seed", "5", "--workers", "1", "--quiet"]) == 0
    assert main(["data", "join", str(ds), str(more), str(tmp_path / "j"), "--count", "1"]) == 0
    assert "4 training scenes (3 of" in capsys.readouterr().out
    assert main(["data", "verify", str(tmp_path / "j")]) == 0


@pytest.mark.parametrize(
    "argv, message",
    [
        (["data", "clevr", "--objects", "0", "--out", "{tmp}/x"], "--objects: must be in [1, 64]"),
        (["data", "clevr", "--objects", "40", "--out", "{tmp}/x"], "impossible placement"),
        (["data", "clevr", "--scenes", "0", "--out", "{tmp}/x"], "--scenes must be positive"),
        (["data", "clevr", "--out", "{tmp}"], "output folder is not empty"),
        (["data", "sheet", "{tmp}/nothing", "--out", "{tmp}/s.png"], "no such dataset folder"),
        (["data", "verify", "{tmp}"], "not a packed dataset"),
        (["demo", "--out", "{tmp}/d", "--search", "-1"], "rounds and weights must be non-negative"),
        (["demo", "--out", "{tmp}/d", "--search-scales", "0.9,x"], "--search-scales: expected comma-separated finite numbers"),
        (["demo", "--out", "{tmp}/d", "--search-scales", "0.8,-1"], "scales positive"),
    ],
)
def test_errors_are_one_line_with_exit_code_2(tmp_path, capsys, argv, message):
    (tmp_path / "occupied").write_text("x")
    argv = [a.format(tmp=tmp_path) for a in argv]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("prismonet: error: ") and message in err and "\n" not in err


def test_bad_split_syntax_is_a_usage_error(tmp_path, capsys):
    assert main(["data", "clevr", "--out", str(tmp_path / "x"), "--split", "1,2"]) == 2
    err = capsys.readouterr().err
    assert "expected three comma-separated counts" in err and err.count("\n") == 1  # one line, no usage block


def test_every_command_has_help(capsys):
    """``--help`` of every command and sub-command prints and exits 0 (argparse formats each help text then)."""
    import argparse

    from prismonet.cli import build_parser

    def commands(parser, prefix):
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                for name, sub in action.choices.items():
                    yield from commands(sub, prefix + [name])
                return
        yield prefix

    found = list(commands(build_parser(), []))
    assert len(found) >= 25
    for argv in found:
        assert main([*argv, "--help"]) == 0, argv
        assert "usage: prismonet" in capsys.readouterr().out
