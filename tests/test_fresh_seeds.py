"""The README's status rows read again on scenes of a seed the project never trained, chose or tested on (opt-in:
``bash scripts/test.sh -m slow``, about 4 minutes).

Each test makes its scenes with the README's own data command (``prismonet data clevr|towers ... --seed 20261202``), reads
them feed-forward with ``prismonet evaluate`` and holds the shipped model to its issue's target where the model meets it
with room, else to its measured test figure less a sampling margin (about two standard errors at this many scenes; said
per line). A model, renderer or generator change that moves these figures fails here even when the 16 sample scenes of the
default suite still pass.

Measured when written (session 103, 2026-12-02; 1,000 scenes each, 500 of towers): see EVALUATION.md, "Session 103".
"""

from __future__ import annotations

import json

import pytest

from prismonet.cli import main

SEED = "20261202"
"""No data set of the project was made with it (its commands use seeds 0-7, 11, 23, 52-53 and 70-89)."""

pytestmark = pytest.mark.slow


def _read(tmp_path, model: str, data_args: list[str], scenes: int) -> dict:
    data, out = tmp_path / "data", tmp_path / "r.json"
    assert main(["data", *data_args, "--split", f"0,0,{scenes}", "--seed", SEED, "--out", str(data), "--quiet"]) == 0
    assert main(["evaluate", model, str(data), "--split", "test", "--batch", "32", "--quiet", "--json", str(out)]) == 0
    return json.loads(out.read_text())


def test_the_default_model_meets_issue_25s_feed_forward_targets_on_a_new_seed(tmp_path):
    """`clevr3_r4` (`shipped` since session 108): the 2.5K test split reads AP0.5 unfiltered 0.987, AR0.5 0.978, allObj
    0.942, PSNR 27.06 and 0.766 of cubes drawn as cubes; these 1,000 scenes read 0.984 / 0.973 / 0.925 / 27.01 and 0.749
    (`clevr3_sharp`, the default of sessions 92-107: 0.983 / 0.973 / 0.926 / 26.54 and 0.756). Issue 25 asks 0.95 /
    0.95 / 0.85 / 26.5."""
    r = _read(tmp_path, "shipped", ["clevr", "--objects", "3"], 1000)
    assert r["AP0.5_unfiltered"] >= 0.95 and r["AR0.5"] >= 0.95 and r["allObj"] >= 0.85  # the issue's targets
    assert r["PSNR"] >= 26.8  # 27.01 here, 27.06 on test; the per-scene spread is ~1.6 dB: 0.2 dB is ~4 standard errors
    assert r["shape_category"]["cube"] >= 0.70  # 0.766 on test (2,380 cubes); ~330 cubes here: 2 s.e. ~0.05


def test_the_1_to_8_object_model_finds_and_counts_on_a_new_seed(tmp_path):
    """`clevr1to8_refit`: the test split reads AP0.5 0.953, AR0.5 0.941 and the count right in 78.0 % of scenes
    (issue 21 asks 0.90 / 0.90 / 80 %: the count is missed feed-forward, so it is held to its own reading)."""
    r = _read(tmp_path, "clevr1to8_refit", ["clevr", "--objects", "8", "--min-objects", "1", "--area", "2.5"], 1000)
    assert r["AP0.5"] >= 0.90 and r["AR0.5"] >= 0.90  # the issue's targets
    assert r["count_exact"] >= 0.75  # 0.780 on test; one standard error at 1,000 scenes is 0.013


def test_the_tower_model_finds_the_cubes_and_their_heights_on_a_new_seed(tmp_path):
    """`blocktowers`: the test split reads AP0.5 0.998 and a stacked cube's height within 0.034; issue 21 asks 0.90 and
    0.2."""
    r = _read(tmp_path, "blocktowers", ["towers"], 500)
    assert r["AP0.5"] >= 0.90 and r["matched_raised"] >= 200 and r["height_err_raised"] <= 0.2
