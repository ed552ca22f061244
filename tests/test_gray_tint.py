"""``realdata.gray_tint``: a hue for greyscale photos, by hand-computed values; colour photos untouched."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from realdata.gray_tint import GRAY_VIEW_SPREAD, TINTS, is_gray_view, tint_gray


def _gray_view() -> np.ndarray:
    """A grey 32 x 32 view: table 0.5 (most of the lower half, so ``estimate_table_color`` reads it), a light patch
    0.8 (r = 1.6), a patch 0.52 (r = 1.04), a dark one 0.3 (r = 0.6) and a slightly dark one 0.4 (r = 0.8)."""
    img = np.full((32, 32, 3), 0.5, np.float32)
    img[2:8, 2:8] = 0.8
    img[2:8, 20:26] = 0.52
    img[20:26, 2:8] = 0.3
    img[20:26, 20:26] = 0.4
    return img


def test_tint_by_hand():
    """Light: s = 0.8 * clip((r - 1.1) / 0.4, 0, 1), blue *= 1 - s; dark (``both``): s = 0.3 * clip((0.9 - r) / 0.3,
    0, 1), red and green *= 1 - s. The table and r within [0.9, 1.1] keep no hue."""
    img = _gray_view()
    light, both = tint_gray(img, "light"), tint_gray(img, "both")
    assert np.allclose(light[4, 4], [0.8, 0.8, 0.8 * 0.2], atol=1e-6)  # r 1.6: s at its 0.8
    assert np.allclose(light[4, 22], 0.52, atol=1e-6)  # r 1.04: below the ramp
    assert np.allclose(light[22, 4], 0.3, atol=1e-6) and np.allclose(light[30, 30], 0.5, atol=1e-6)  # dark and table unchanged
    assert np.allclose(both[4, 4], light[4, 4], atol=1e-6)
    assert np.allclose(both[22, 4], [0.21, 0.21, 0.3], atol=1e-6)  # r 0.6: s at its 0.3
    s = 0.3 * (0.9 - 0.8) / 0.3  # r 0.8: a third of the way down the ramp
    assert np.allclose(both[22, 22], [0.4 * (1 - s), 0.4 * (1 - s), 0.4], atol=1e-6)
    assert np.allclose(both[30, 30], 0.5, atol=1e-6)
    assert tint_gray(img, "off") is img
    with pytest.raises(ValueError, match="gray tint: expected off, light, both"):
        tint_gray(img, "blue")
    assert TINTS == ("off", "light", "both")


def test_is_gray_view():
    img = _gray_view()
    assert is_gray_view(img)
    img[0, 0, 0] += GRAY_VIEW_SPREAD * 1.5
    assert not is_gray_view(img)


def _grey_and_colour(folder, names=("gray.png", "colour.png"), light=np.s_[20:40, 20:40], red=np.s_[60:80, 60:80]) -> list:
    """Two 96 x 96 photos on a grey table (120): the first with a light (220) object at ``light``, the second the same
    with a red object at ``red`` (a colour photo); their paths."""
    gray = np.full((96, 96, 3), 120, np.uint8)
    gray[light] = 220
    colour = gray.copy()
    colour[red] = (40, 60, 200)  # BGR: red
    for name, img in zip(names, (gray, colour)):
        cv2.imwrite(str(folder / name), img)
    return [folder / n for n in names]


def test_prepare_tints_grey_photos_only(tmp_path):
    """Through ``prepare_photos``: a grey photo is tinted and its record says so; a colour photo is written the same
    with the tint asked for as without it; an unknown tint is refused before anything is written."""
    from realdata.pipeline import prepare_photos

    photos = _grey_and_colour(tmp_path)
    plain = prepare_photos(photos, tmp_path / "off", box=(0, 0, 96, 96), size=32)
    tinted = prepare_photos(photos, tmp_path / "light", box=(0, 0, 96, 96), size=32, gray_tint="light")
    read = {d: {n: cv2.imread(str(tmp_path / d / "rgb" / f"{n}.png")) for n in ("gray", "colour")} for d in ("off", "light")}
    assert np.array_equal(read["off"]["colour"], read["light"]["colour"]) and "gray_tint" not in tinted[1]
    assert tinted[0]["gray_tint"] == "light" and "gray_tint" not in plain[0]
    g0, g1 = read["off"]["gray"].astype(int), read["light"]["gray"].astype(int)
    obj, table = (slice(8, 12), slice(8, 12)), (slice(28, 32), slice(0, 4))
    assert (g1[obj][..., 0] < g0[obj][..., 0] - 50).all()  # BGR: the light object lost blue: yellowish
    assert np.array_equal(g1[obj][..., 1:], g0[obj][..., 1:]) and np.array_equal(g1[table], g0[table])
    with pytest.raises(ValueError, match="gray_tint: expected"):
        prepare_photos(photos, tmp_path / "bad", box=(0, 0, 96, 96), size=32, gray_tint="blue")
    assert not (tmp_path / "bad").exists()


def test_real_prepare_says_which_photos_it_tinted(tmp_path, capsys):
    from prismonet.cli import main

    photos = _grey_and_colour(tmp_path)
    assert main(["real", "prepare", *map(str, photos), "--out", str(tmp_path / "o"), "--gray-tint", "both"]) == 0
    lines = {Path(line.split(":")[0].strip()).name: line for line in capsys.readouterr().out.splitlines() if ".png:" in line}
    assert lines["gray.png"].endswith("greyscale: tinted (both)") and "tinted" not in lines["colour.png"]


def test_real_cli_refuses_an_unknown_tint_in_one_line(tmp_path, capsys):
    from prismonet.cli import main

    assert main(["real", "prepare", str(tmp_path / "x.png"), "--out", str(tmp_path / "o"), "--gray-tint", "blue"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--gray-tint" in err[0] and not (tmp_path / "o").exists()


def test_gray_views_take_their_own_inference(tmp_path):
    """``reconstruct_photos(..., gray_inference=...)``: the tinted (greyscale) views are decoded with that config, the
    colour ones with ``inference``; the records come back in the order a reading without it gives (decoded in two
    groups, colour first, put back in order: "grey" sorts before "hue")."""
    from prismonet.model.inference import InferenceConfig
    from realdata.reconstruct import reconstruct_photos

    photos = [str(p) for p in _grey_and_colour(tmp_path, ("grey.png", "hue.png"), np.s_[30:60, 30:60], np.s_[30:60, 30:60])]
    steps = InferenceConfig.of(prune=True)
    plain = reconstruct_photos(photos, tmp_path / "plain", box=(0, 0, 96, 96), inference=steps, gray_tint="both",
                               progress=False, meshes=False)
    assert {r["inference"] == steps.without_depth().record() for r in plain} == {True}
    recs = reconstruct_photos(photos, tmp_path / "mixed", box=(0, 0, 96, 96),
                              inference=steps, gray_tint="both", gray_inference=InferenceConfig(), progress=False, meshes=False)
    assert [r["photo"] for r in recs] == [r["photo"] for r in plain]
    got = {Path(r["photo"]).stem: r["inference"] for r in recs}
    assert got["grey"] == InferenceConfig().without_depth().record() and got["hue"] == steps.without_depth().record()
    assert got["grey"] != got["hue"]
    prep = {Path(r["photo"]).stem: r["prepare"] for r in recs}
    assert prep["grey"]["gray_tint"] == "both" and "gray_tint" not in prep["hue"]


def test_gray_no_steps_needs_a_tint_in_one_line(tmp_path, capsys):
    from prismonet.cli import main

    assert main(["real", "reconstruct", str(tmp_path / "x.png"), "--out", str(tmp_path / "o"), "--gray-no-steps"]) != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--gray-no-steps" in err[0] and not (tmp_path / "o").exists()
