"""Import freely licensed meshes for the paper's ShapeNet-style settings (cars, chairs, a tabletop set)
from Sweet Home 3D's furniture libraries, as Debian packages them (``sweethome3d-furniture``: CC0 and
CC-BY 3.0 OBJ models with materials).

The package is an opt-in source: nothing else in the project needs it. Point the importer at the
package file (``.deb``), at its installed folder (``/usr/share/sweethome3d/furniture``) or at a folder
of ``.sh3f`` libraries. Each library is a zip of OBJ models and a ``PluginFurnitureCatalog.properties``
that names every model, its category, creator and orientation.

For each model of a setting the importer:

- loads its OBJ with every material, colouring each part with its material's colour (the mean colour
  of its texture image where it has one, times the diffuse colour);
- turns it upright: the catalogue's ``modelRotation``, then Sweet Home 3D's y-up frame to z-up
  (``x, y, z -> x, -z, y``: the model's front, +z there, faces -y here);
- centres and scales it like the Clevr shapes (bounding-box centre at the origin, largest half-extent
  1, ``prismonet.shapes.normalize``), so that the scene generator's rule "centre at ``s h_z`` above the
  ground" puts it on the ground;
- checks it (finite, not flat, at least ``MIN_FACES`` faces), decimates it towards ``max_faces``
  faces (open3d's quadric decimation, vertex colours kept; a few models whose parts cannot collapse
  keep more, and ``models.json`` says how many), and writes it as a coloured PLY;
- records its source (package, library, catalogue id, model file), creator and licence in
  ``models.json``, with its split: ``seen`` (prior and scenes) or ``unseen`` (the novel-shape test),
  at least a third unseen, by a seeded shuffle of the sorted names.
"""

from __future__ import annotations

import io
import json
import re
import tarfile
import tempfile
import zipfile
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

PACKAGE = "sweethome3d-furniture"
INSTALLED = Path("/usr/share/sweethome3d/furniture")
MIN_FACES = 12
LICENCES = {
    "BlendSwap-CC-0": "CC0-1.0",
    "BlendSwap-CC-BY": "CC-BY-3.0",
    "KatorLegaz": "CC-BY-3.0-US",
    "Reallusion": "CC-BY-3.0-US",
    "Scopia": "CC-BY-3.0",
}
"""Licence of each library, from the package's ``debian/copyright``."""

SETTINGS: dict[str, tuple[tuple[str, ...], tuple[str, ...]]] = {
    # setting: (a name must contain one of, and none of), lower case
    "cars": (("car", "sedan", "beetle", "seat leon", "peugeot", "renault", "suv", "chevrolet", "ford focus"),
             ("carpet", "card", "cart", "scooter", "truck", "bus")),
    "chairs": (("chair", "armchair"), ("wheelchair", "high chair", "armchair ottoman")),
    "tabletop": (("mug", "cup", "bottle", "glass", "can"),
                 ("cupboard", "cup cake", "glass table", "glass door", "sunglasses", "glasses", "cabinet", "plate",
                  "trash", "candle", "candy", "cane", "canopy", "canvas", "scanner")),
}
"""Which catalogue names belong to each setting (whole words; see ``select``)."""

CATEGORIES: dict[str, tuple[tuple[str, str], ...]] = {
    # setting: (word in the name, category), first match wins; else the setting's last category
    "cars": (("car", "car"),),
    "chairs": (("armchair", "armchair"), ("chair", "chair")),
    "tabletop": (("mug", "mug"), ("cup", "mug"), ("bottle", "bottle"), ("glass", "glass"), ("can", "can")),
}
"""The category of each model within its setting (the shape prior's category ids)."""


def category_of(setting: str, name: str) -> str:
    rules = CATEGORIES[setting]
    return next((c for w, c in rules if re.search(rf"\b{re.escape(w)}", name.lower())), rules[-1][1])


class FurnitureError(ValueError):
    """No usable furniture source, an unknown setting, or a model that cannot be imported."""


@dataclass(frozen=True)
class CatalogEntry:
    library: str
    index: int
    id: str
    name: str
    category: str
    model: str
    """Path of the OBJ file inside the library's zip (no leading slash)."""
    creator: str
    rotation: tuple[float, ...] | None
    """Row-major 3x3 ``modelRotation``, or ``None``."""


def _unescape(text: str) -> str:
    """Java properties escapes (``\\uXXXX``, ``\\:``) to text."""
    return re.sub(r"\\u([0-9a-fA-F]{4})", lambda m: chr(int(m.group(1), 16)), text).replace("\\:", ":").replace("\\=", "=")


def parse_catalog(text: str, library: str) -> list[CatalogEntry]:
    """The entries of a ``PluginFurnitureCatalog.properties`` text."""
    props: dict[int, dict[str, str]] = {}
    for line in text.splitlines():
        m = re.match(r"\s*(\w+)#(\d+)\s*=(.*)", line)
        if m:
            props.setdefault(int(m.group(2)), {})[m.group(1)] = _unescape(m.group(3).strip())
    out = []
    for i, p in sorted(props.items()):
        if "model" not in p or "name" not in p:
            continue
        rot = tuple(float(v) for v in p["modelRotation"].split()) if "modelRotation" in p else None
        out.append(CatalogEntry(library, i, p.get("id", f"{library}#{i}"), p["name"], p.get("category", ""),
                                p["model"].lstrip("/"), p.get("creator", ""), rot))
    return out


def _libraries_from_deb(path: Path) -> dict[str, bytes]:
    """The ``.sh3f`` files inside a Debian package (an ar archive holding ``data.tar.*``)."""
    blob = path.read_bytes()
    if not blob.startswith(b"!<arch>\n"):
        raise FurnitureError(f"{path}: not a Debian package")
    pos, libs = 8, {}
    while pos + 60 <= len(blob):
        name, size = blob[pos : pos + 16].decode().strip().rstrip("/"), int(blob[pos + 48 : pos + 58].decode().strip())
        data = blob[pos + 60 : pos + 60 + size]
        pos += 60 + size + (size % 2)
        if name.startswith("data.tar"):
            with tarfile.open(fileobj=io.BytesIO(data)) as tar:
                for m in tar.getmembers():
                    if m.name.endswith(".sh3f"):
                        libs[Path(m.name).stem] = tar.extractfile(m).read()
    return libs


def open_libraries(source: str | Path | None = None) -> dict[str, zipfile.ZipFile]:
    """The furniture libraries (name -> open zip) of a ``.deb``, a folder of ``.sh3f`` files, or
    (``None``) the installed package."""
    src = Path(source) if source is not None else INSTALLED
    if src.is_file() and src.suffix == ".deb":
        blobs = _libraries_from_deb(src)
    elif src.is_dir():
        blobs = {p.stem: p.read_bytes() for p in sorted(src.glob("*.sh3f"))}
    else:
        raise FurnitureError(f"{src}: no furniture source (give the {PACKAGE} .deb, its installed folder {INSTALLED}, "
                             "or a folder of .sh3f files)")
    if not blobs:
        raise FurnitureError(f"{src}: holds no .sh3f furniture library")
    return {name: zipfile.ZipFile(io.BytesIO(b)) for name, b in blobs.items()}


def catalog(libs: dict[str, zipfile.ZipFile]) -> list[CatalogEntry]:
    entries = []
    for name, z in libs.items():
        if "PluginFurnitureCatalog.properties" in z.namelist():
            entries += parse_catalog(z.read("PluginFurnitureCatalog.properties").decode("latin-1"), name)
    return entries


def select(entries: list[CatalogEntry], setting: str) -> list[CatalogEntry]:
    """The entries of ``setting`` (``SETTINGS``): a name holding one of its words and none of its exclusions."""
    if setting not in SETTINGS:
        raise FurnitureError(f"unknown setting {setting!r}; expected one of {', '.join(SETTINGS)}")
    want, avoid = SETTINGS[setting]
    has = lambda name, words: any(re.search(rf"\b{re.escape(w)}", name) for w in words)
    return [e for e in entries if has(e.name.lower(), want) and not has(e.name.lower(), avoid)]


def _part_color(visual) -> np.ndarray:
    """RGB in [0, 1] of one mesh part: its texture's mean colour times the diffuse colour, or the diffuse."""
    mat = getattr(visual, "material", None)
    if mat is None:
        fc = getattr(visual, "face_colors", None)
        return np.asarray(fc[:, :3].mean(0) / 255.0) if fc is not None and len(fc) else np.full(3, 0.5)
    diffuse = np.asarray(getattr(mat, "main_color", [128, 128, 128, 255])[:3], dtype=np.float64) / 255.0
    image = getattr(mat, "image", None)
    if image is not None:
        tex = np.asarray(image.convert("RGB"), dtype=np.float64).reshape(-1, 3).mean(0) / 255.0
        diffuse = tex * (diffuse if diffuse.max() > 0 else 1.0)
    return np.clip(diffuse, 0.0, 1.0)


def load_model_mesh(z: zipfile.ZipFile, entry: CatalogEntry) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(vertices (V, 3), faces (F, 3), vertex colours (V, 3))`` of an entry, upright (z-up), unscaled."""
    import trimesh

    folder = entry.model.rsplit("/", 1)[0] + "/" if "/" in entry.model else ""
    with tempfile.TemporaryDirectory() as tmp:
        for n in z.namelist():
            if n.startswith(folder) and not n.endswith("/"):
                (Path(tmp) / n).parent.mkdir(parents=True, exist_ok=True)
                (Path(tmp) / n).write_bytes(z.read(n))
        scene = trimesh.load(Path(tmp) / entry.model, force="scene", process=False)
    vs, fs, cs, offset = [], [], [], 0
    for g in scene.dump():
        if not isinstance(g, trimesh.Trimesh) or len(g.faces) == 0:
            continue
        vs.append(np.asarray(g.vertices, dtype=np.float64))
        fs.append(np.asarray(g.faces, dtype=np.int64) + offset)
        cs.append(np.broadcast_to(_part_color(g.visual), (len(g.vertices), 3)))
        offset += len(g.vertices)
    if not vs:
        raise FurnitureError(f"{entry.library}/{entry.model}: no triangles")
    v = np.concatenate(vs)
    if entry.rotation is not None:
        v = v @ np.asarray(entry.rotation).reshape(3, 3).T
    v = np.stack([v[:, 0], -v[:, 2], v[:, 1]], 1)  # y-up -> z-up
    return v, np.concatenate(fs), np.concatenate(cs)


def decimate(v: np.ndarray, f: np.ndarray, c: np.ndarray, max_faces: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Towards ``max_faces`` faces by open3d's quadric decimation (vertex colours carried along),
    after merging duplicate vertices and dropping degenerate and duplicate triangles."""
    import open3d as o3d

    m = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(v), o3d.utility.Vector3iVector(f.astype(np.int32)))
    m.vertex_colors = o3d.utility.Vector3dVector(c)
    m = m.merge_close_vertices(1e-6).remove_duplicated_triangles().remove_degenerate_triangles().remove_unreferenced_vertices()
    target = max_faces
    while len(m.triangles) > max_faces and target >= MIN_FACES:  # parts that cannot collapse leave more faces: aim lower
        m = m.simplify_quadric_decimation(target).remove_unreferenced_vertices()
        target //= 2
    return np.asarray(m.vertices), np.asarray(m.triangles, dtype=np.int64), np.clip(np.asarray(m.vertex_colors), 0, 1)


def slug(entry: CatalogEntry) -> str:
    return re.sub(r"[^a-z0-9]+", "-", f"{entry.library}-{entry.index}-{entry.name}".lower()).strip("-")


def assign_splits(names: list[str], seed: int = 0, unseen_fraction: float = 1 / 3) -> dict[str, str]:
    """``seen`` / ``unseen`` per name: a seeded shuffle of the sorted names, the first ``ceil(n / 3)``
    (at least one when there are two or more) unseen."""
    order = sorted(names)
    np.random.default_rng(seed).shuffle(order)
    k = int(np.ceil(len(order) * unseen_fraction)) if len(order) > 1 else 0
    return {n: ("unseen" if i < k else "seen") for i, n in enumerate(order)}


def import_setting(setting: str, out: str | Path, source: str | Path | None = None, max_faces: int = 5000,
                   seed: int = 0, progress: bool = True) -> dict:
    """Import every model of ``setting`` into ``out`` (one PLY per model and ``models.json``); returns the record."""
    from tqdm import tqdm

    import trimesh

    from prismonet.files import write_atomic
    from prismonet.shapes.normalize import MeshError, normalize_mesh

    libs = open_libraries(source)
    entries = select(catalog(libs), setting)
    if not entries:
        raise FurnitureError(f"{source or INSTALLED}: no model of setting {setting!r}")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    models, skipped = [], []
    for e in tqdm(entries, desc=f"import {setting}", unit="model", disable=not progress):
        try:
            v, f, c = load_model_mesh(libs[e.library], e)
            v, _ = normalize_mesh(v, f, slug(e))
            v, f, c = decimate(v, f, c, max_faces)
            v, _ = normalize_mesh(v, f, slug(e))  # decimation can move the bounds a little
            if len(f) < MIN_FACES:
                raise MeshError(f"{slug(e)}: only {len(f)} faces")
        except (MeshError, FurnitureError, ValueError, OSError) as err:
            skipped.append({"id": e.id, "name": e.name, "reason": str(err)})
            continue
        name = slug(e)
        mesh = trimesh.Trimesh(v, f, vertex_colors=np.rint(c * 255).astype(np.uint8), process=False)
        write_atomic(out / f"{name}.ply", mesh.export(file_type="ply"))
        half = (v.max(0) - v.min(0)) / 2
        models.append({"name": name, "title": e.name, "category": category_of(setting, e.name), "file": f"{name}.ply", "faces": int(len(f)),
                       "half_extents": [round(float(h), 6) for h in half], "color": [round(float(x), 4) for x in c.mean(0)],
                       "watertight": bool(mesh.is_watertight), "creator": e.creator, "licence": LICENCES.get(e.library, "unknown"),
                       "source": {"package": PACKAGE, "library": e.library, "id": e.id, "model": e.model}, "entry": asdict(e)})
    splits = assign_splits([m["name"] for m in models], seed)
    for m in models:
        m["split"] = splits[m["name"]]
    record = {"setting": setting, "package": PACKAGE, "max_faces": max_faces, "seed": seed, "models": models, "skipped": skipped,
              "counts": {s: sum(m["split"] == s for m in models) for s in ("seen", "unseen")}}
    write_atomic(out / "models.json", json.dumps(record, indent=1))  # written last: the index of a complete import
    return record
