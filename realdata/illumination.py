"""Uneven light on the table: a smooth brightness field fitted to the table's pixels, and divided out.

Real photos are brighter on one side than the other and darker in the corners (the light's direction, lens
vignetting). The model was trained on evenly lit grounds, and the colour normalisation maps one table colour, so a
table that is 40 % darker at the bottom than at the top comes out too bright above and too dark below (in the coins
photo, white). Here the table's log-brightness is modelled as a polynomial of degree ``ORDER`` in the pixel
coordinates. That is exact for a linear gradient, and near enough for the radial fall-off of vignetting. The fit
uses the pixels whose chromaticity (colour over brightness, which uneven light does not change) is the table's,
robustly: pixels far from the fit (a grey object on a grey table) are dropped and the fit is repeated. The photo is
then divided by the field, normalised to 1 at the table's median. Objects are corrected by the same field, as the
light that falls on them varies the same way.
"""

from __future__ import annotations

import numpy as np

from prismonet.data.gray import GRAY_SPREAD
from realdata.color import estimate_table_color

ORDER = 2
"""Degree of the log-brightness polynomial."""
FIT_SIDE = 96
"""The photo is fitted at most this many pixels on its longer side (the field is smooth)."""
CHROMA_QUANT = 24
"""Chromaticity bins per channel for finding the table's."""
CHROMA_TOLERANCE = 0.06
"""Max chromaticity distance from the table's for a pixel to take part in the fit."""
ROBUST_ROUNDS = 3
MAX_FIELD = 4.0
"""The field is held within [1 / MAX_FIELD, MAX_FIELD] (the colour mapping's gain limit): far from the table's
pixels the polynomial extrapolates."""
ROBUST_K = 2.5
"""Pixels further than ``ROBUST_K`` times the residuals' scaled median absolute deviation are dropped."""
GRAY_BAND: float | None = 0.7
"""In a greyscale photo every pixel has the table's chromaticity, objects too. There the fit starts from the pixels
whose log-brightness is within this of the table's (``realdata.color.estimate_table_color``, as the colour mapping
reads it): a factor of 2 either way. None: chromaticity alone, as for colour photos."""


def _design(x: np.ndarray, y: np.ndarray, order: int) -> np.ndarray:
    return np.stack([x**i * y**j for i in range(order + 1) for j in range(order + 1 - i)], -1)


def illumination_field(image: np.ndarray, order: int = ORDER) -> np.ndarray:
    """``(H, W)`` multiplicative brightness field of an RGB image ``(H, W, 3)`` in [0, 1]: 1 at the median table pixel."""
    import cv2

    H, W = image.shape[:2]
    f = min(1.0, FIT_SIDE / max(H, W))
    small = cv2.resize(image, (max(2, round(W * f)), max(2, round(H * f))), interpolation=cv2.INTER_AREA) if f < 1 else image
    h, w = small.shape[:2]
    lum = small.mean(-1) + 1e-3
    chroma = small / lum[..., None] / 3
    bins = np.clip((chroma * CHROMA_QUANT).astype(np.int64), 0, CHROMA_QUANT - 1).reshape(-1, 3)
    key = (bins[:, 0] * CHROMA_QUANT + bins[:, 1]) * CHROMA_QUANT + bins[:, 2]
    table = np.median(chroma.reshape(-1, 3)[key == np.bincount(key).argmax()], axis=0)
    use = (np.linalg.norm(chroma - table, axis=-1) < CHROMA_TOLERANCE).reshape(-1)
    use &= lum.reshape(-1) > 0.02  # black carries no brightness to fit
    if GRAY_BAND is not None and float((small.max(-1) - small.min(-1)).max()) <= GRAY_SPREAD:  # a greyscale photo
        table_lum = float(estimate_table_color(small).mean()) + 1e-3
        use &= (np.abs(np.log(lum) - np.log(table_lum)) < GRAY_BAND).reshape(-1)
    yy, xx = np.meshgrid(np.linspace(-1, 1, h), np.linspace(-1, 1, w), indexing="ij")
    A = _design(xx.reshape(-1), yy.reshape(-1), order)
    target = np.log(lum).reshape(-1)
    if use.sum() < A.shape[1] * 4:
        return np.ones((H, W))
    for _ in range(ROBUST_ROUNDS):
        coef = np.linalg.lstsq(A[use], target[use], rcond=None)[0]
        r = target - A @ coef
        scale = 1.4826 * np.median(np.abs(r[use] - np.median(r[use]))) + 1e-6
        keep = use & (np.abs(r - np.median(r[use])) < ROBUST_K * scale)
        if keep.sum() < A.shape[1] * 4:
            break
        use = keep
    coef = np.linalg.lstsq(A[use], target[use], rcond=None)[0]
    Y, X = np.meshgrid(np.linspace(-1, 1, H), np.linspace(-1, 1, W), indexing="ij")
    log_field = _design(X, Y, order) @ coef
    return np.clip(np.exp(log_field - np.median((A @ coef)[use])), 1 / MAX_FIELD, MAX_FIELD)


def flatten_light(image: np.ndarray, order: int = ORDER) -> tuple[np.ndarray, np.ndarray]:
    """``(image / field, field)``: the photo as if its table were evenly lit (clipped to [0, 1])."""
    field = illumination_field(image, order)
    return np.clip(image / field[..., None], 0.0, 1.0).astype(image.dtype), field
