"""Colour normalisation: estimate the table colour robustly and map it onto the synthetic ground.

The paper adjusted brightness and contrast of its real photos by hand until the background looked
like the synthetic ground. Here the table colour is the median of the largest cluster of
similar colours in the lower half of the photo (the table fills the bottom of a tabletop view),
and a per-channel gain maps it exactly onto the target; the mapping is returned so it can be
recorded, and a manual one can be passed instead.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

TABLE_QUANT = 16
"""Colour bins per channel for finding the dominant (table) colour."""
MIN_CHANNEL = 1e-3
"""Channels darker than this are not scaled up (no division by ~0)."""
MAX_GAIN = 4.0
"""No channel is scaled by more than this or less than its inverse: a table that dark or that bright is
more likely a misread (e.g. a saucer taken for the table) than a table."""
MAX_TINT = 2.0
"""The largest channel gain is at most this times the smallest: the mapping corrects a tint, it does not
turn a deep red into grey."""


@dataclass(frozen=True)
class ColorMapping:
    """``out = clip(gain * in + offset, 0, 1)`` per RGB channel."""

    gain: tuple[float, float, float]
    offset: tuple[float, float, float]

    def apply(self, image: np.ndarray) -> np.ndarray:
        return np.clip(image * np.asarray(self.gain, np.float32) + np.asarray(self.offset, np.float32), 0.0, 1.0)

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


def mapping_limited(table_rgb: np.ndarray, target_rgb: np.ndarray, mapping: ColorMapping) -> bool:
    """Whether ``mapping`` (from ``table_mapping``) misses mapping the table exactly onto the target."""
    t = np.maximum(np.asarray(table_rgb, np.float64), MIN_CHANNEL)
    return not np.allclose(np.asarray(mapping.gain) * t, np.asarray(target_rgb, np.float64), rtol=1e-9, atol=1e-12)
