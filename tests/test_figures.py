"""Figure helpers with exact answers: ``scripts/recon_figure.py``'s depth shading."""

import numpy as np


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
