"""Colour normalisation: estimate the table colour robustly and map it onto the synthetic ground.

The paper adjusted brightness and contrast of its real photos by hand until the background looked
like the synthetic ground. Here the table colour is the median of the largest cluster of
similar colours in the lower half of the photo (the table fills the bottom of a tabletop view),
and a per-channel gain maps it exactly onto the target; the mapping is returned so it can be
recorded, and a manual one can be passed instead.

A dark table under bright objects (coins on black) needs a large gain, which would clip the objects to
white. ``spare_highlights`` then compresses the brightness above the table's by a power instead: the table
still maps exactly onto the target, and the photo's bright end (a high percentile) onto full scale.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace

import numpy as np

TABLE_QUANT = 16
"""Colour bins per channel for finding the dominant (table) colour."""
MIN_CHANNEL = 1e-3
"""Channels darker than this are not scaled up (no division by ~0)."""
MAX_GAIN = 4.0
"""No channel is scaled by more than this or less than its inverse: a table that dark or that bright is
more likely a misread (e.g. a saucer taken for the table) than a table."""
HIGHLIGHT_PERCENTILE: float | None = 99.0
"""``spare_highlights``' bright end: this percentile of the photo's pixel brightness (largest channel) maps at most
to 1, so at most 1 % of the pixels clip (None: the plain gain, which clips whatever it lifts beyond 1). Chosen on
synthetic stand-ins with dark tables (99 against 95 and 99.9; EVALUATION.md, "Session 53")."""
MAX_TINT = 2.0
"""The largest channel gain is at most this times the smallest: the mapping corrects a tint, it does not
turn a deep red into grey."""


@dataclass(frozen=True)
class ColorMapping:
    """``y = gain * in + offset`` per RGB channel, then, where ``gamma < 1``, each pixel whose largest channel ``v``
    exceeds ``pivot`` scaled by ``(v / pivot) ** (gamma - 1)`` (its brightness above the pivot compressed by the
    power ``gamma``, its hue kept); clipped to [0, 1]."""

    gain: tuple[float, float, float]
    offset: tuple[float, float, float]
    gamma: float = 1.0
    pivot: float = 1.0

    def apply(self, image: np.ndarray) -> np.ndarray:
        y = image * np.asarray(self.gain, np.float32) + np.asarray(self.offset, np.float32)
        if self.gamma != 1.0:
            v = np.maximum(y.max(-1, keepdims=True), self.pivot)
            y = y * (v / self.pivot) ** (self.gamma - 1.0)
        return np.clip(y, 0.0, 1.0).astype(image.dtype, copy=False)

    def to_dict(self) -> dict:
        return asdict(self)


def estimate_table_color(image: np.ndarray) -> np.ndarray:
    """RGB ``(3,)`` of the table: the median colour of the most common colour bin in the lower half."""
    low = image[image.shape[0] // 2 :].reshape(-1, 3)
    bins = np.clip((low * TABLE_QUANT).astype(np.int64), 0, TABLE_QUANT - 1)
    key = (bins[:, 0] * TABLE_QUANT + bins[:, 1]) * TABLE_QUANT + bins[:, 2]
    mode = np.bincount(key).argmax()
    return np.median(low[key == mode], axis=0)


def table_mapping(table_rgb: np.ndarray, target_rgb: np.ndarray) -> ColorMapping:
    """The per-channel gain that maps the table colour exactly onto the target, within ``MAX_GAIN`` and
    ``MAX_TINT`` (see ``mapping_limited`` for whether they bound it)."""
    t = np.maximum(np.asarray(table_rgb, np.float64), MIN_CHANNEL)
    log_g = np.log(np.asarray(target_rgb, np.float64) / t)
    spread, limit = log_g.max() - log_g.min(), np.log(MAX_TINT)
    if spread > limit:  # shrink the tint about the channels' mean in log space
        mid = log_g.mean()
        log_g = mid + (log_g - mid) * (limit / spread)
    cap = np.log(MAX_GAIN)  # then shift all channels alike into [1/MAX_GAIN, MAX_GAIN] (the tint, <= MAX_TINT, fits)
    log_g = log_g - max(log_g.max() - cap, 0.0) + max(-cap - log_g.min(), 0.0)
    gain = np.exp(log_g)
    return ColorMapping(tuple(gain.tolist()), (0.0, 0.0, 0.0))


def spare_highlights(mapping: ColorMapping, table_rgb: np.ndarray, image: np.ndarray, percentile: float | None) -> ColorMapping:
    """``mapping`` with a tone curve that brings the photo's bright end back under 1 (see ``ColorMapping``): the
    brightness above the mapped table's is compressed by a power ``gamma`` chosen so that the ``percentile``-th
    brightest pixel (its largest channel, after the gain) lands on 1. Hues are kept; the table and everything darker
    are mapped as before. Unchanged when nothing would clip, or when ``percentile`` is None."""
    if percentile is None:
        return mapping
    g = np.asarray(mapping.gain, np.float64)
    t = np.maximum(np.asarray(table_rgb, np.float64), MIN_CHANNEL)
    pivot = float((g * t + np.asarray(mapping.offset, np.float64)).max())
    value = (np.asarray(image, np.float64).reshape(-1, 3) * g + np.asarray(mapping.offset, np.float64)).max(-1)
    bright = float(np.percentile(value, percentile))
    if bright <= 1.0 or pivot >= 1.0 or bright <= pivot:
        return mapping
    gamma = float(np.log(1.0 / pivot) / np.log(bright / pivot))
    return replace(mapping, gamma=gamma, pivot=pivot)


def mapping_limited(table_rgb: np.ndarray, target_rgb: np.ndarray, mapping: ColorMapping) -> bool:
    """Whether ``mapping`` (from ``table_mapping``) misses mapping the table exactly onto the target."""
    t = np.maximum(np.asarray(table_rgb, np.float64), MIN_CHANNEL)
    mapped = np.asarray(mapping.gain) * t + np.asarray(mapping.offset)
    return not np.allclose(mapped, np.asarray(target_rgb, np.float64), rtol=1e-9, atol=1e-12)
