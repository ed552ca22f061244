"""A hue for a greyscale photo: what is lighter than the table turns yellowish, and (``both``) what is darker bluish.

The photo models are trained on coloured objects on a hueless ground, and learn that shortcut: a hueless region is
table. A greyscale photo has no hue anywhere, so its objects are read by luminance alone (``anchor_gray_tol``) and
light ones are missed: on the grey photo stand-ins, `tabletop_keep` found 68 of the 473 objects lighter than 1.25x the
table (EVALUATION.md, session 85). Tinting gives back what the model looks for. Each pixel's luminance ratio to the
table's, ``r``, sets how far it moves, and the ramps start outside ``[DARK_FROM, LIGHT_FROM]``, so the table itself and
what is nearly as light keep no hue:

- lighter (``r > LIGHT_FROM``): the blue channel scaled by ``1 - s``, ``s = LIGHT_SATURATION * clip((r - LIGHT_FROM) /
  LIGHT_RAMP, 0, 1)``: yellow, a colour the Clevr palette has;
- darker (``r < DARK_FROM``, ``both`` only): red and green scaled by ``1 - s``, ``s = DARK_SATURATION * clip((DARK_FROM -
  r) / DARK_RAMP, 0, 1)``: blue. A cast shadow turns blue too; in a greyscale photo it was read as an object already (the
  shadow rule cannot act there), and the model then reads the photo in colour, where the rule acts again on what the
  tint leaves grey.

The ramps were set once, before any reading (``runs/s85/rule_gray_tint.txt``). The saturations were swept once on the
grey validation stand-ins (0.4 / 0.8 light, 0.3 / 0.7 dark, against the first 0.6 / 0.5) and (0.8, 0.3) taken by a rule
written before the sweep, confirmed on the grey test stand-ins once their labels stopped counting objects too small to
label (EVALUATION.md, session 86). Colour photos are not changed (``is_gray_view``).
"""

from __future__ import annotations

import numpy as np

from prismonet.data.gray import GRAY_SPREAD, LUMA
from realdata.color import estimate_table_color

TINTS = ("off", "light", "both")
"""``--gray-tint``: none; what is lighter than the table; that and what is darker."""
GRAY_VIEW_SPREAD = GRAY_SPREAD
"""A prepared view is grey when no pixel's channels differ by more than this: the model's own test
(``prismonet.data.gray.is_gray``), so that the views tinted are those the model would read by luminance. The colour
mapping keeps a grey photo exactly grey (its target, the training ground, is grey)."""
LIGHT_FROM, LIGHT_RAMP, LIGHT_SATURATION = 1.1, 0.4, 0.8
DARK_FROM, DARK_RAMP, DARK_SATURATION = 0.9, 0.3, 0.3


def is_gray_view(image: np.ndarray) -> bool:
    """Whether ``image (H, W, 3)`` in [0, 1] is grey: every pixel's channels within ``GRAY_VIEW_SPREAD``."""
    return float((image.max(-1) - image.min(-1)).max()) <= GRAY_VIEW_SPREAD


def tint_gray(image: np.ndarray, mode: str) -> np.ndarray:
    """``image (H, W, 3)`` in [0, 1] (a grey view, ``is_gray_view``) tinted by ``mode`` (``TINTS``), relative to its
    table's luminance (``realdata.color.estimate_table_color``); ``"off"`` returns it as it is."""
    if mode not in TINTS:
        raise ValueError(f"gray tint: expected {', '.join(TINTS)}, got {mode!r}")
    if mode == "off":
        return image
    luma = np.asarray(LUMA, np.float32)
    table = float(estimate_table_color(image) @ luma)
    r = (image @ luma) / max(table, 1e-3)
    out = image.astype(np.float32).copy()
    out[..., 2] *= 1 - np.clip((r - LIGHT_FROM) / LIGHT_RAMP, 0, 1) * LIGHT_SATURATION
    if mode == "both":
        dark = 1 - np.clip((DARK_FROM - r) / DARK_RAMP, 0, 1) * DARK_SATURATION
        out[..., 0] *= dark
        out[..., 1] *= dark
    return np.clip(out, 0, 1).astype(image.dtype, copy=False)
