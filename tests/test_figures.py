"""Figure scripts: `scripts/recon_figure.py`'s depth shading (exact answers), its figure and its one-line refusals."""

import numpy as np
import pytest


def test_shaded_depth_of_planes(script):
    shaded = script("recon_figure").shaded_depth
    fx = 100.0
    front = shaded(np.full((9, 9), 4.0), fx)
    # facing the camera: n = (0, 0, -1), light (-0.4, -0.5, -1) / |.|: 0.2 + 0.8 / 1.18743 = 0.87373 -> 223
    assert front.dtype == np.uint8 and front.shape == (9, 9, 3) and (front == 223).all()
    v = np.arange(9, dtype=np.float64)[:, None].repeat(9, 1)
    up = shaded(4.0 - 0.04 * v, fx)[4, 4, 0]  # nearer lower down the image: a floor, facing up (-y)
    down = shaded(4.0 + 0.04 * v, fx)[4, 4, 0]  # a ceiling
    assert up > 223 > down
    hole = np.full((9, 9), 4.0)
    hole[2, 2] = 0
    assert (shaded(hole, fx)[2, 2] == 0).all()


def test_recon_figure_draws_the_shipped_scenes(script, tmp_path):
    from prismonet.assets import shipped_samples
    from prismonet.files import read_image

    out = tmp_path / "f.png"
    script("recon_figure").main(["shipped", "--data", str(shipped_samples()), "--split", "test", "--rows", "2", "--out", str(out)])
    image = read_image(out)
    assert image.shape[0] > 2 * 128 and image.shape[1] > 4 * 128  # two rows; input, depth, the model's image and depth


@pytest.mark.parametrize("argv, says", [(["--rows", "0"], "--rows must be at least 1"),
                                        (["--names", "a,b"], "--names: 2 labels for 1 models"),
                                        (["--category", "7"], "has an object of category 7"),
                                        (["--data", "/nonexistent/data"], "recon_figure: /nonexistent/data"),
                                        (["--steps", "--search 2 --shape-trials"], "need --search 3 or more, got 2")])
def test_recon_figure_refuses_bad_input_in_one_line(argv, says, script, tmp_path):
    from prismonet.assets import shipped_samples

    base = {"--data": str(shipped_samples()), "--split": "test", "--out": str(tmp_path / "f.png")}
    for flag, value in zip(argv[::2], argv[1::2]):
        base[flag] = value
    with pytest.raises(SystemExit) as e:
        script("recon_figure").main(["shipped", *[x for kv in base.items() for x in kv]])
    assert says in str(e.value) and "\n" not in str(e.value)


def test_recon_figure_takes_test_time_steps_per_model(script, tmp_path):
    """``--steps`` gives each column its own test-time steps (a colour fit changes that column's reconstruction, not the
    figure's layout); one string per model."""
    from prismonet.assets import shipped_samples
    from prismonet.files import read_image

    base = ["shipped", "shipped", "--data", str(shipped_samples()), "--split", "test", "--rows", "1"]
    script("recon_figure").main([*base, "--out", str(tmp_path / "a.png"), "--steps", "", "--fit-color 50"])
    script("recon_figure").main([*base, "--out", str(tmp_path / "c.png"), "--steps", "", ""])
    image, plain = read_image(tmp_path / "a.png"), read_image(tmp_path / "c.png")
    assert image.shape == plain.shape and image.shape[1] > 6 * 128  # input, depth, then two models' image and depth
    assert (image != plain).any()
    with pytest.raises(SystemExit) as e:
        script("recon_figure").main([*base, "--out", str(tmp_path / "b.png"), "--steps", "--fit-color 5"])
    assert "--steps: 1 strings for 2 models" in str(e.value)
