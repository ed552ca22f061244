"""One loader for both on-disk formats (packed, folder)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from prismonet.data.errors import DatasetError
from prismonet.data.scenes import SceneBatch


class SceneDataset(torch.utils.data.Dataset):
    """Scenes from a packed dataset split or a folder dataset.

    ``dataset[i]`` is a ``SceneBatch`` of one scene; ``dataset.batch(indices)`` reads many at
    once with one fancy index per array (the fast path for training from memory-mapped files).
    Use ``collate_fn=SceneBatch.collate`` with a ``DataLoader``.

    Args:
        path: a packed dataset folder (with ``meta.json``) or a folder dataset (``dataset.json``).
        split: the split of a packed dataset (``train``, ``val``, ``test``); ignored for folders.
        verify: also check SHA-256 checksums of packed files.
    """

    def __init__(self, path: str | Path, split: str = "train", verify: bool = False) -> None:
        from prismonet.data import folder, packed

        self.path = Path(path)
        if not self.path.is_dir():
            raise DatasetError(f"{self.path}: no such dataset folder")
        if (self.path / "meta.json").is_file():
            self.arrays = packed.open_split(self.path, split, verify=verify)
            self.meta = packed.read_meta(self.path)
            self.format = "packed"
            self.names = [str(i) for i in range(len(self.arrays["rgb"]))]
        elif (self.path / "dataset.json").is_file():
            self.arrays, self.names, self.meta = folder.read_folder(self.path)
            self.format = "folder"
        else:
            raise DatasetError(f"{self.path}: neither a packed dataset (meta.json) nor a folder dataset (dataset.json)")

    def __len__(self) -> int:
        return len(self.arrays["rgb"])

    def __getitem__(self, index: int) -> SceneBatch:
        if not -len(self) <= index < len(self):
            raise IndexError(f"scene index {index} out of range for {len(self)} scenes")
        return self.batch([index % len(self)])

    def batch(self, indices) -> SceneBatch:
        """Scenes ``indices`` as a batch, row ``j`` being scene ``indices[j]`` (read from the memory
        maps in ascending order, which is faster, then put back in the order asked for)."""
        idx = np.asarray(indices, dtype=np.int64)
        order = np.argsort(idx, kind="stable")
        back = np.empty_like(order)
        back[order] = np.arange(len(order))
        return SceneBatch.from_arrays({k: np.asarray(v[idx[order]])[back] for k, v in self.arrays.items()})

    def numpy(self, indices) -> dict[str, np.ndarray]:
        """Raw arrays of some scenes, as stored."""
        idx = np.asarray(indices, dtype=np.int64)
        return {k: np.asarray(v[idx]) for k, v in self.arrays.items()}
