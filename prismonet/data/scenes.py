"""The in-memory scene batch that every dataset format loads into.

A dataset, in either on-disk format, is a set of named arrays with the scene index first
(``SCENE_ARRAYS``). ``SceneBatch`` is the torch view of a slice of them.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np
import torch

SCENE_ARRAYS: dict[str, tuple[str, str]] = {
    # name: (numpy dtype, shape after the scene index N; K = max objects, padded with -1 / 0)
    "rgb": ("uint8", "H W 3"),
    "depth": ("float32", "H W"),  # camera z; 0 where unknown
    "instance": ("uint8", "H W"),  # 0 = background, k = k-th object (1-based)
    "K": ("float32", "3 3"),
    "T_world_cam": ("float32", "4 4"),
    "ground_z": ("float32", ""),
    "ground_color": ("uint8", "3"),
    "obj_count": ("int16", ""),
    "obj_shape": ("int16", "K"),  # Clevr shape id (0..26), -1 if unknown or padding
    "obj_category": ("int8", "K"),  # -1 if unknown or padding
    "obj_color": ("int8", "K"),  # CLEVR colour id, -1 if unknown or padding
    "obj_scale": ("float32", "K"),
    "obj_position": ("float32", "K 3"),
    "obj_yaw": ("float32", "K"),
    "obj_axis": ("float32", "K 3"),
}


@dataclass
class SceneBatch:
    """A batch of B scenes (K = max objects; per-object fields are padded past ``obj_count``).

    Attributes:
        rgb: ``(B, 3, H, W)`` float in [0, 1].
        depth: ``(B, 1, H, W)`` camera z; 0 where unknown.
        instance: ``(B, H, W)`` int64; 0 = background, k = k-th object.
        K: ``(B, 3, 3)`` intrinsics.
        T_world_cam: ``(B, 4, 4)``.
        ground_z: ``(B,)`` height of the ground plane.
        ground_color: ``(B, 3)`` float in [0, 1].
        obj_count: ``(B,)`` number of objects in each scene.
        obj_shape, obj_category, obj_color: ``(B, K)`` int64, -1 where unknown or padded.
        obj_scale: ``(B, K)``; obj_position: ``(B, K, 3)``; obj_yaw: ``(B, K)``; obj_axis: ``(B, K, 3)``.
    """

    rgb: torch.Tensor
    depth: torch.Tensor
    instance: torch.Tensor
    K: torch.Tensor
    T_world_cam: torch.Tensor
    ground_z: torch.Tensor
    ground_color: torch.Tensor
    obj_count: torch.Tensor
    obj_shape: torch.Tensor
    obj_category: torch.Tensor
    obj_color: torch.Tensor
    obj_scale: torch.Tensor
    obj_position: torch.Tensor
    obj_yaw: torch.Tensor
    obj_axis: torch.Tensor

    @staticmethod
    def from_arrays(a: dict[str, np.ndarray]) -> "SceneBatch":
        """Convert numpy arrays (scene index first, as in ``SCENE_ARRAYS``) to a batch."""

        def t(name, dtype):
            return torch.from_numpy(np.ascontiguousarray(a[name])).to(dtype)

        return SceneBatch(
            rgb=t("rgb", torch.float32).permute(0, 3, 1, 2) / 255.0,
            depth=t("depth", torch.float32)[:, None],
            instance=t("instance", torch.int64),
            K=t("K", torch.float32),
            T_world_cam=t("T_world_cam", torch.float32),
            ground_z=t("ground_z", torch.float32),
            ground_color=t("ground_color", torch.float32) / 255.0,
            obj_count=t("obj_count", torch.int64),
            obj_shape=t("obj_shape", torch.int64),
            obj_category=t("obj_category", torch.int64),
            obj_color=t("obj_color", torch.int64),
            obj_scale=t("obj_scale", torch.float32),
            obj_position=t("obj_position", torch.float32),
            obj_yaw=t("obj_yaw", torch.float32),
            obj_axis=t("obj_axis", torch.float32),
        )

    @staticmethod
    def collate(batches: list["SceneBatch"]) -> "SceneBatch":
        """Concatenate batches along B (a ``collate_fn`` for ``torch.utils.data.DataLoader``)."""
        return SceneBatch(**{f.name: torch.cat([getattr(b, f.name) for b in batches]) for f in fields(SceneBatch)})

    def __len__(self) -> int:
        return self.rgb.shape[0]

    def rows(self, which: slice | torch.Tensor) -> "SceneBatch":
        """The scenes ``which`` selects (a slice or an index tensor along B), every field alike."""
        return SceneBatch(**{f.name: getattr(self, f.name)[which] for f in fields(SceneBatch)})

    def to(self, device: torch.device | str) -> "SceneBatch":
        """The batch on ``device`` (itself if it is there)."""
        if self.rgb.device == torch.device(device):
            return self
        return SceneBatch(**{f.name: getattr(self, f.name).to(device) for f in fields(SceneBatch)})


def empty_scene_arrays(n: int, height: int, width: int, max_objects: int) -> dict[str, np.ndarray]:
    """Zeroed arrays for ``n`` scenes; per-object ids are -1 (unknown / padding)."""
    dims = {"H": height, "W": width, "K": max_objects}
    out = {}
    for name, (dtype, shape) in SCENE_ARRAYS.items():
        tail = tuple(dims[s] if s in dims else int(s) for s in shape.split())
        out[name] = np.zeros((n, *tail), dtype=dtype)
        if name in ("obj_shape", "obj_category", "obj_color"):
            out[name][:] = -1
    out["obj_axis"][..., 2] = 1.0
    return out
