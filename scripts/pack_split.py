"""Usage: python3 scripts/pack_split.py pack data/chairs/train OUT_DIR [N] | unpack OUT_DIR data/chairs/train

A dataset split as one xz file per array, its bytes shuffled by significance, and back, bit for bit: to carry a
split to a machine that cannot make it (the GPU machine has no open3d). The 18,000 chairs training scenes
(516 MB of arrays) pack into 25 MB in 66 s on one core and unpack in 4 s.
The dataset's meta.json travels in the pack with this split's entries (shape, bytes, SHA-256, count) made to fit the
first N scenes; unpack writes them into the destination dataset's meta.json (made if absent, other splits kept), so
that packs of several splits of one dataset unpack side by side."""
import hashlib, io, json, lzma, sys
from pathlib import Path
import numpy as np


def _entry(a: np.ndarray) -> dict:
    buf = io.BytesIO()
    np.save(buf, a)
    b = buf.getvalue()
    return {"shape": list(a.shape), "dtype": str(a.dtype), "bytes": len(b), "sha256": hashlib.sha256(b).hexdigest()}

def pack(src: Path, dst: Path, n: int | None = None):
    dst.mkdir(parents=True, exist_ok=True)
    meta, entries = {}, {}
    for f in sorted(src.glob("*.npy")):
        a = np.load(f, mmap_mode="r")
        a = np.ascontiguousarray(a[:n] if n else a)
        b = a.view(np.uint8).reshape(-1, a.itemsize).T.copy().tobytes()
        (dst / (f.stem + ".xz")).write_bytes(lzma.compress(b, preset=6))
        meta[f.stem] = [a.dtype.str, list(a.shape)]
        entries[f.stem] = _entry(a)
    (dst / "arrays.json").write_text(json.dumps(meta))
    if (src.parent / "meta.json").is_file():
        ds_meta = json.loads((src.parent / "meta.json").read_text())
        ds_meta["splits"][src.name] = {k: {**ds_meta["splits"][src.name].get(k, {}), **e} for k, e in entries.items()}
        ds_meta["counts"][src.name] = next(iter(entries.values()))["shape"][0]
        (dst / "meta.json").write_text(json.dumps(ds_meta, indent=1))

def unpack(src: Path, dst: Path):
    dst.mkdir(parents=True, exist_ok=True)
    meta = json.loads((src / "arrays.json").read_text())
    for name, (dt, shape) in meta.items():
        dt = np.dtype(dt)
        b = np.frombuffer(lzma.decompress((src / (name + ".xz")).read_bytes()), np.uint8)
        a = b.reshape(dt.itemsize, -1).T.copy().view(dt).reshape(shape)
        np.save(dst / (name + ".npy"), a)
    if (src / "meta.json").is_file():  # this split's entries into the dataset's meta.json, beside any other split's
        packed = json.loads((src / "meta.json").read_text())
        target = dst.parent / "meta.json"
        ds_meta = json.loads(target.read_text()) if target.is_file() else {**packed, "splits": {}, "counts": {}}
        ds_meta["splits"][dst.name] = packed["splits"][dst.name]
        ds_meta["counts"][dst.name] = packed["counts"][dst.name]
        target.write_text(json.dumps(ds_meta, indent=1))

if __name__ == "__main__":
    if sys.argv[1] == "pack":
        pack(Path(sys.argv[2]), Path(sys.argv[3]), int(sys.argv[4]) if len(sys.argv) > 4 else None)
    else:
        unpack(Path(sys.argv[2]), Path(sys.argv[3]))
