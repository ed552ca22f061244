"""``real reconstruct|evaluate --preset``: a preset parses to exactly the flags it stands for, and flags given on the
command line win over it."""

import json

import pytest

from prismonet.cli import _parse
from prismonet.cli.real import PRESETS, preset_flags

# The labelled photos' command of EVALUATION.md (session 86), written out by hand.
SESSION_86 = ("--tiles 2 --tile-below 120 --normalize flat --gray-tint both --gray-no-steps --reseed 4 --reseed-replace "
              "--reseed-cycles 2 --search 3 --fit-color 50 --search-scales 0.8,0.9,1.1,1.25 --prune").split()
IGNORED = {"preset", "preset_parser", "presets", "func"}


def _args(*argv):
    args, status = _parse(list(argv))
    assert status is None
    return {k: v for k, v in vars(args).items() if k not in IGNORED}


@pytest.mark.parametrize("command", [["real", "evaluate", "labels"], ["real", "reconstruct", "photo.jpg"]])
def test_measured_preset_is_the_session_86_line(command):
    base = [*command, "--out", "o"]
    assert _args(*base, "--preset", "measured") == _args(*base, *SESSION_86)
    assert _args(*base, "--preset", "measured") != _args(*base)  # the preset changes something


def test_flags_are_what_preset_flags_says():
    assert preset_flags("measured").split() == SESSION_86
    assert set(PRESETS) == {"measured"}


def test_command_line_flags_win_over_the_preset():
    a = _args("real", "evaluate", "labels", "--out", "o", "--search", "0", "--preset", "measured", "--tiles", "1")
    assert a["search"] == 0 and a["tiles"] == 1 and a["fit_color"] == 50 and a["normalize"] == "flat"


def test_no_preset_keeps_the_defaults():
    a = _args("real", "evaluate", "labels", "--out", "o")
    assert a["search"] == 0 and a["tiles"] == 1 and a["normalize"] == "auto" and not a["prune"]


def test_unknown_preset_is_one_line(capsys):
    args, status = _parse(["real", "evaluate", "labels", "--out", "o", "--preset", "fastest"])
    assert args is None and status == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--preset" in err[0] and "measured" in err[0]


def test_settings_record_the_flags_a_preset_stood_for(tmp_path):
    """``settings.json`` of a photo run: the preset's flags written out, the model's resolved name, the steps."""
    from prismonet.cli.common import inference_config
    from prismonet.cli.real import run_settings, write_settings

    args, _ = _parse(["real", "evaluate", "labels", "--out", str(tmp_path), "--preset", "measured", "--search", "2"])
    s = run_settings(args, inference_config(args, has_depth=False))
    assert s["command"] == "prismonet real evaluate" and s["preset"] == "measured" and s["model"] == "tabletop_keep"
    assert s["flags"]["search"] == 2 and s["flags"]["tiles"] == 2 and s["flags"]["prune"] is True
    assert not IGNORED & set(s["flags"]) and "quiet" not in s["flags"]
    assert json.loads(write_settings(args, inference_config(args, has_depth=False)).read_text())["flags"] == s["flags"]
