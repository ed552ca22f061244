"""The packed dataset format: one ``.npy`` file per array, memory-mapped when read.

Layout::

    DIR/
      meta.json          format, version, generator settings, seed, counts, and for each split
                         and array its shape, dtype, byte size and SHA-256
      train/rgb.npy      (N, H, W, 3) uint8    -- one file per entry of SCENE_ARRAYS
      train/depth.npy    (N, H, W) float32
      ...
      val/...  test/...

``meta.json`` is written last, and generation writes into a temporary folder that is renamed into
place at the end, so an interrupted run never leaves a folder that loads. Opening checks every
file's presence, header and size (cheap; catches truncation); ``verify=True`` also checks SHA-256.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from prismonet.data.errors import DatasetError
from prismonet.data.scenes import SCENE_ARRAYS
from prismonet.files import sha256_file

PACKED_FORMAT = "prismonet-packed"
PACKED_VERSION = 1


def write_split(split_dir: Path, arrays: dict[str, np.ndarray]) -> dict[str, dict]:
    """Write one split's arrays; returns their entries for ``meta.json``."""
    split_dir.mkdir(parents=True, exist_ok=True)
    entries = {}
    for name in SCENE_ARRAYS:
        path = split_dir / f"{name}.npy"
        np.save(path, np.ascontiguousarray(arrays[name]))
        entries[name] = {
            "shape": list(arrays[name].shape),
            "dtype": str(arrays[name].dtype),
            "bytes": path.stat().st_size,
            "sha256": sha256_file(path),
        }
    return entries


def write_meta(root: Path, meta: dict) -> None:
    tmp = root / "meta.json.tmp"
    tmp.write_text(json.dumps(meta, indent=2))
    tmp.replace(root / "meta.json")


def read_meta(root: Path) -> dict:
    path = Path(root) / "meta.json"
    if not path.is_file():
        raise DatasetError(f"{root}: not a packed dataset (no meta.json)")
    from prismonet.files import InputError, read_json

    try:
        meta = read_json(path, dict)
    except InputError as e:
        raise DatasetError(f"corrupted meta.json: {e}") from None
    if meta.get("format") != PACKED_FORMAT:
        raise DatasetError(f"{path}: format is {meta.get('format')!r}, expected {PACKED_FORMAT!r}")
    if meta.get("version") != PACKED_VERSION:
        raise DatasetError(f"{path}: version {meta.get('version')} is not supported (expected {PACKED_VERSION})")
    splits = meta.get("splits")
    if not isinstance(splits, dict) or not all(isinstance(v, dict) and all(
            isinstance(e, dict) and {"shape", "dtype", "bytes"} <= set(e) for e in v.values()) for v in splits.values()):
        raise DatasetError(f"{path}: 'splits' must map each split to its arrays' shape, dtype and bytes")
    return meta


def open_split(root: Path, split: str, verify: bool = False) -> dict[str, np.ndarray]:
    """Memory-map one split's arrays after checking them against ``meta.json``."""
    root = Path(root)
    meta = read_meta(root)
    if split not in meta["splits"]:
        raise DatasetError(f"{root}: no split {split!r}; it has {sorted(meta['splits'])}")
    arrays = {}
    for name, entry in meta["splits"][split].items():
        path = root / split / f"{name}.npy"
        if not path.is_file():
            raise DatasetError(f"{path}: missing")
        size = path.stat().st_size
        if size != entry["bytes"]:
            raise DatasetError(f"{path}: truncated or altered: {size} bytes, expected {entry['bytes']}")
        if verify and sha256_file(path) != entry["sha256"]:
            raise DatasetError(f"{path}: corrupted: SHA-256 does not match meta.json")
        try:
            arr = np.load(path, mmap_mode="r", allow_pickle=False)
        except (ValueError, OSError, EOFError) as e:
            raise DatasetError(f"{path}: corrupted .npy file ({e})") from None
        if list(arr.shape) != entry["shape"] or str(arr.dtype) != entry["dtype"]:
            raise DatasetError(
                f"{path}: header says {arr.dtype}{list(arr.shape)}, meta.json says {entry['dtype']}{entry['shape']}"
            )
        arrays[name] = arr
    missing = set(SCENE_ARRAYS) - set(arrays)
    if missing:
        raise DatasetError(f"{root}/{split}: meta.json lists no {sorted(missing)}")
    rows = {name: a.shape[0] if a.ndim else -1 for name, a in arrays.items()}
    if len(set(rows.values())) != 1:
        raise DatasetError(f"{root}/{split}: arrays disagree on the number of scenes: {rows}")
    return arrays


def write_subset(src: Path, split: str, indices, dst: Path) -> dict:
    """Copy scenes ``indices`` of ``src``'s ``split`` into a new packed dataset ``dst`` holding only
    that split (same generator settings in ``meta.json``, plus where the scenes came from)."""
    src, dst = Path(src), Path(dst)
    meta = read_meta(src)
    arrays = open_split(src, split)
    idx = np.asarray(list(indices), dtype=np.int64)
    if idx.size == 0 or idx.min() < 0 or idx.max() >= len(arrays["rgb"]):
        raise DatasetError(f"{src}/{split}: scene indices must lie in [0, {len(arrays['rgb'])}), got {idx.tolist()[:5]}...")
    if (dst / "meta.json").exists():
        raise DatasetError(f"{dst}: already holds a dataset")
    entries = write_split(dst / split, {k: np.asarray(v[idx]) for k, v in arrays.items()})
    out = {**meta, "counts": {split: int(idx.size)}, "splits": {split: entries},
           "subset_of": {"path": str(src), "split": split, "indices": idx.tolist()}}
    write_meta(dst, out)
    return out


def write_joined(first: Path, more: Path, dst: Path, count: int | None = None) -> dict:
    """A new packed dataset ``dst`` whose training split is ``first``'s followed by the first ``count`` (default all)
    training scenes of ``more``, and whose other splits are ``first``'s: more training scenes for a run that already
    holds per-scene products (distillation targets) of ``first``'s, whose scene indices stay valid. Both must come
    from the same generator settings (``config``), so that the added scenes are of the same kind."""
    first, more, dst = Path(first), Path(more), Path(dst)
    a_meta, b_meta = read_meta(first), read_meta(more)
    if a_meta.get("config") != b_meta.get("config") or a_meta.get("generator") != b_meta.get("generator"):
        raise DatasetError(f"{more}: made with other generator settings than {first}; cannot join their training scenes")
    if a_meta.get("generator") is not None and a_meta.get("seed") == b_meta.get("seed"):
        raise DatasetError(f"{more}: the same seed as {first}, so its training scenes repeat {first}'s")
    if (dst / "meta.json").exists():
        raise DatasetError(f"{dst}: already holds a dataset")
    added = open_split(more, "train")
    n = len(added["rgb"]) if count is None else int(count)
    if not 0 < n <= len(added["rgb"]):
        raise DatasetError(f"{more}/train: count must be in 1..{len(added['rgb'])}, got {n}")
    splits, counts = {}, {}
    for split in a_meta["splits"]:
        arrays = open_split(first, split)
        if split == "train":
            arrays = {k: np.concatenate([v, added[k][:n]]) for k, v in arrays.items()}
        splits[split] = write_split(dst / split, arrays)
        counts[split] = int(len(arrays["rgb"]))
    out = {**a_meta, "counts": counts, "splits": splits,
           "joined": {"first": str(first), "train_from": str(more), "train_added": n,
                      "train_seed": b_meta.get("seed"), "first_train": int(a_meta["counts"]["train"])}}
    write_meta(dst, out)
    return out
