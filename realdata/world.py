"""One world scale: the map between a calibrated table (metres, ``calibrate ground``) and the model's
world (the units of its training scenes), and whether a photo's camera is one the model can use.

A model is trained with one camera (``training_camera``: CLEVR's, about 11.3 units from the point its
optical axis meets the ground, 28° above it). A calibrated photo camera is metric and anywhere. The
map is a similarity, ``x_model = s R_z(yaw) (x_table - g_photo) + g_train``, that

- takes the point where the photo camera's optical axis meets the table (``g_photo``) to the point
  where the training camera's meets the ground (``g_train``);
- turns the photo camera's heading (its axis projected on the table) onto the training camera's;
- scales by ``s`` model units per metre: derived so that the photo camera is as far from ``g_photo``
  as the training camera is from ``g_train`` (``WorldMapping.derive``), or stated by the user
  (``metres_per_unit``, e.g. when the objects' real size is known).

With the same elevation, the photo camera then sits exactly where the training camera does, and the
photo is the training view up to intrinsics (``realdata.rectify`` warps it there, exact for every
point). Otherwise the warp through the ground plane is exact on the table and approximate on the
objects; ``camera_warnings`` says when the difference is large enough to matter.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

MAX_ELEVATION_GAP_DEG = 10.0
"""Warn when the photo camera's elevation differs from the training camera's by more than this:
objects are then seen from another angle than any training scene (the table still maps exactly)."""
DISTANCE_RATIO_RANGE = (0.8, 1.25)
"""With a stated scale, warn when the photo camera's distance (in model units) is outside this
range of the training camera's: objects then appear at sizes training never showed."""
MIN_ELEVATION_DEG = 5.0
"""Refuse a camera whose optical axis is this flat or flatter: its axis meets the table far away or never."""


class CameraError(ValueError):
    """A calibrated camera the model cannot use (one line)."""


def _axis_on_ground(T_world_cam: np.ndarray, ground_z: float) -> tuple[np.ndarray, float, float, float]:
    """``(g, distance, heading, elevation_deg)``: where the optical axis meets ``z = ground_z``, the
    camera's distance to it, the axis's heading (radians, in the ground plane) and its elevation
    (degrees below the horizon)."""
    T = np.asarray(T_world_cam, np.float64)
    c, a = T[:3, 3], T[:3, 2]
    height = c[2] - ground_z
    elevation = math.degrees(math.asin(max(-1.0, min(1.0, -a[2]))))
    if height <= 0:
        raise CameraError(f"the camera is {height:.3g} above the table: it must be above it (is the ground pose upside down?)")
    if elevation < MIN_ELEVATION_DEG:
        raise CameraError(f"the camera looks {elevation:.1f}° below the horizon; it must look down at the table "
                          f"(at least {MIN_ELEVATION_DEG:.0f}°) for its view to map onto the model's")
    t = height / -a[2]
    g = c + t * a
    return g, float(t), math.atan2(a[1], a[0]), elevation


@dataclass(frozen=True)
class WorldMapping:
    """``x_model = units_per_metre * R_z(yaw) (x_table - table_anchor) + model_anchor``."""

    units_per_metre: float
    yaw: float
    """Radians about the vertical."""
    table_anchor: tuple[float, float, float]
    model_anchor: tuple[float, float, float]
    scale_source: str
    """``"derived"`` (from the camera distances) or ``"stated"`` (``metres_per_unit``)."""
    photo_elevation_deg: float
    train_elevation_deg: float
    distance_ratio: float
    """Photo camera's distance to its axis point, in model units, over the training camera's."""

    @property
    def metres_per_unit(self) -> float:
        return 1.0 / self.units_per_metre

    @classmethod
    def derive(cls, T_table_cam: np.ndarray, T_world_train: np.ndarray, ground_z: float = 0.0,
               metres_per_unit: float | None = None) -> "WorldMapping":
        """The map for a photo camera ``T_table_cam`` (metres, table at z = 0) and the model's
        training camera ``T_world_train`` (model units, ground at ``ground_z``)."""
        if metres_per_unit is not None and not (math.isfinite(metres_per_unit) and metres_per_unit > 0):
            raise CameraError(f"metres per model unit must be a finite positive number, got {metres_per_unit}")
        g_p, d_p, h_p, e_p = _axis_on_ground(T_table_cam, 0.0)
        g_t, d_t, h_t, e_t = _axis_on_ground(T_world_train, ground_z)
        s = d_t / d_p if metres_per_unit is None else 1.0 / metres_per_unit
        return cls(float(s), float(h_t - h_p), tuple(map(float, g_p)), tuple(map(float, g_t)),
                   "derived" if metres_per_unit is None else "stated", e_p, e_t, float(s * d_p / d_t))

    def matrix(self) -> np.ndarray:
        """``(4, 4)`` similarity taking table points (metres) to model points (units)."""
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        M = np.eye(4)
        M[:3, :3] = self.units_per_metre * R
        M[:3, 3] = np.asarray(self.model_anchor) - self.units_per_metre * R @ np.asarray(self.table_anchor)
        return M

    def to_model(self, points: np.ndarray) -> np.ndarray:
        """``(N, 3)`` table points (metres) -> model points (units)."""
        M = self.matrix()
        return np.asarray(points, np.float64) @ M[:3, :3].T + M[:3, 3]

    def to_table(self, points: np.ndarray) -> np.ndarray:
        """``(N, 3)`` model points (units) -> table points (metres)."""
        M = np.linalg.inv(self.matrix())
        return np.asarray(points, np.float64) @ M[:3, :3].T + M[:3, 3]

    def camera_in_model(self, T_table_cam: np.ndarray) -> np.ndarray:
        """The photo camera's ``T_world_cam`` in the model's world (rotation kept, position mapped)."""
        M = self.matrix()
        T = np.array(T_table_cam, np.float64)
        out = np.eye(4)
        out[:3, :3] = M[:3, :3] / self.units_per_metre @ T[:3, :3]
        out[:3, 3] = M[:3, :3] @ T[:3, 3] + M[:3, 3]
        return out

    @classmethod
    def from_dict(cls, d: dict) -> "WorldMapping":
        """The map ``to_dict`` wrote (its derived fields ignored)."""
        return cls(d["units_per_metre"], d["yaw"], tuple(d["table_anchor"]), tuple(d["model_anchor"]), d["scale_source"],
                   d["photo_elevation_deg"], d["train_elevation_deg"], d["distance_ratio"])

    def to_dict(self) -> dict:
        return {**asdict(self), "metres_per_unit": self.metres_per_unit, "matrix_model_table": self.matrix().tolist()}


def camera_warnings(m: WorldMapping) -> list[str]:
    """One line per way the photo camera differs from what the model was trained on (empty: none)."""
    out = []
    gap = m.photo_elevation_deg - m.train_elevation_deg
    if abs(gap) > MAX_ELEVATION_GAP_DEG:
        out.append(f"the camera looks {m.photo_elevation_deg:.0f}° down, the model was trained at {m.train_elevation_deg:.0f}°: "
                   "the table maps exactly, objects are seen from another angle (expect larger errors)")
    lo, hi = DISTANCE_RATIO_RANGE
    if not lo <= m.distance_ratio <= hi:
        out.append(f"at {m.metres_per_unit:.4g} m per model unit the camera is {m.distance_ratio:.2f}x the training camera's distance: "
                   "objects appear at sizes the model never saw")
    return out
