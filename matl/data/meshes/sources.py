"""Canonical sources for the user's textured meshes: ``ycb``, ``apc``, ``arc`` and ``meshes`` (``docs/datasets.md``).

Each source finds one mesh per object in its folder layout, reads a manifest for the objects'
shape types, moves each mesh into its object frame (:mod:`.frames`), and renders the canonical
planes with the procedural catalog's renderer and framing (``fill``, ``supersample``), so real
and procedural sets look alike to the model. They also hand out their models
(:meth:`MeshSource.models`), so rendered queries and anchors work on them too.

Layouts:
    * ``ycb``: ``<root>/<id>_<name>/google_16k/textured.obj``; folders without ``google_16k`` are
      skipped with a log line (not every YCB object has that scan).
    * ``apc``: ``<root>/<object>/textured_meshes/optimized_poisson_texture_mapped_mesh.obj``.
    * ``arc``: ``<root>/<item>/`` holding an ``.obj`` or ``.ply`` (``.obj`` preferred, then the
      first by name).
    * ``meshes``: every ``.obj``/``.ply`` directly in ``<root>`` (object = file stem) or in its
      sub-folders (object = folder name), and any object the manifest gives a ``mesh:`` path.
"""

from __future__ import annotations

import hashlib
import logging
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from matl.data.canonical import CanonicalSet, ProgressFn
from matl.data.catalog.shapes import ProductModel
from matl.data.meshes.frames import guess_layout, layout_planes, object_frame, parse_direction
from matl.data.meshes.io import MESH_SUFFIXES, MeshError, load_mesh_parts
from matl.data.meshes.manifest import Manifest, ManifestEntry
from matl.utils.errors import MatlError

log = logging.getLogger(__name__)

MESH_SOURCE_VERSION = 1
SUBSETS = ("all", "planar", "nonplanar")
PLANES_PER_LAYOUT = {"planar": 2, "rectangular": 6, "cylindrical": 10}


class MeshSource:
    """Base class: a folder of textured meshes as a :class:`~matl.data.canonical.CanonicalSource`.

    Args:
        root: the dataset folder.
        manifest: manifest file (YAML/CSV), a shipped name (``ycb``, ``apc``, ``arc``) or None.
        fill: fraction of the image width covered by each plane's larger extent (as the catalog).
        supersample: render at this multiple of the image size and area-average down.
        subset: ``all``, ``planar`` (simple shapes) or ``nonplanar`` objects (Table 2 split; by the
            manifest's ``shape``, objects not in it count as simple).
        only_manifest: skip objects the manifest does not list (else: warn and guess their shape).
        up, front: directions of the mesh files' up and front ("+z", "-y"), unless the manifest
            says otherwise.
        require_texture: refuse meshes without any texture or colours.
    """

    dataset = "meshes"

    def __init__(
        self,
        root: str | Path,
        manifest: str | Path | None = None,
        fill: float = 0.6,
        supersample: int = 2,
        subset: str = "all",
        only_manifest: bool = False,
        up: str = "+z",
        front: str = "-y",
        require_texture: bool = True,
    ) -> None:
        if root is None or str(root) in ("", "???"):
            raise MatlError(f"data.source.root is not set: pass data.source.root=<folder of the {self.dataset} meshes>")
        self.root = Path(root).expanduser()
        if not self.root.is_dir():
            raise MatlError(f"data.source.root={self.root}: no such folder")
        if subset not in SUBSETS:
            raise MatlError(f"data.source.subset={subset!r} is invalid; valid: {list(SUBSETS)}")
        if not 0.0 < fill <= 1.0:
            raise MatlError(f"data.source.fill={fill} is invalid: use a fraction in (0, 1]")
        for name, value in (("up", up), ("front", front)):
            try:
                parse_direction(value)
            except ValueError as e:
                raise MatlError(f"data.source.{name}={value!r}: {e}") from e
        self.manifest_arg = manifest
        self.manifest = Manifest.load(manifest) if manifest else Manifest.empty()
        self.fill = float(fill)
        self.supersample = int(supersample)
        self.subset = subset
        self.only_manifest = bool(only_manifest)
        self.up, self.front = str(up), str(front)
        self.require_texture = bool(require_texture)
        self._objects: list[tuple[str, Path, ManifestEntry | None]] | None = None

    def __repr__(self) -> str:
        return f"{type(self).__name__}(root={str(self.root)!r}, manifest={self.manifest_arg!r}, subset={self.subset!r})"

    # ------------------------------------------------------------------------------------ discovery
    def find_meshes(self) -> list[tuple[str, Path]]:
        """``(object name, mesh path)`` of every object in the layout, sorted by name."""
        raise NotImplementedError

    def objects(self) -> list[tuple[str, Path, ManifestEntry | None]]:
        """The objects to use, in order, with their manifest entries (None: not in the manifest)."""
        if self._objects is not None:
            return self._objects
        found = self.find_meshes()
        if not found:
            raise MatlError(f"data.source.root={self.root}: no {self.dataset} meshes found ({self.layout_hint()})")
        chosen: list[tuple[str, Path, ManifestEntry | None]] = []
        unlisted: list[str] = []
        for name, path in found:
            entry = self.manifest.lookup(name)
            if entry is None:
                if self.only_manifest:
                    log.info("skipping %s: not in the manifest (only_manifest=true)", name)
                    continue
                unlisted.append(name)
            is_nonplanar = entry is not None and entry.shape == "nonplanar"
            if (self.subset == "planar" and is_nonplanar) or (self.subset == "nonplanar" and not is_nonplanar):
                continue
            chosen.append((name, path, entry))
        # A log warning (one clean line in the run's log), not warnings.warn: this is about the data.
        if unlisted and self.manifest.path is not None:
            log.warning("%d objects are not in the manifest %s; their shape type is guessed from their bounding box "
                        "(add them to the manifest to fix it): %s", len(unlisted), self.manifest.path,
                        ", ".join(unlisted))  # fmt: skip
        elif unlisted:
            log.warning("no manifest given (data.source.manifest): the shape type of all %d objects is guessed from "
                        "their bounding boxes", len(unlisted))  # fmt: skip
        if self.manifest.path is not None:
            names = {n.lower() for n, _ in found}
            bare = {n.lower().split("_", 1)[-1] for n, _ in found}
            missing = [m for m in self.manifest.names if m not in names and m.split("_", 1)[-1] not in bare]
            if missing:
                log.info("%d manifest objects are not under %s: %s", len(missing), self.root, ", ".join(missing))
        if not chosen:
            raise MatlError(f"data.source.subset={self.subset}: no {self.subset} objects under {self.root}")
        self._objects = chosen
        return chosen

    def layout_hint(self) -> str:
        return "expected <root>/*.obj|ply or <root>/<object>/*.obj|ply"

    # ------------------------------------------------------------------------------------ models
    def _direction(self, entry: ManifestEntry | None, key: str) -> np.ndarray:
        value = getattr(entry, key, None) if entry else None
        return parse_direction(value or self.manifest.defaults.get(key) or getattr(self, key))

    def load_model(self, name: str, path: Path, entry: ManifestEntry | None) -> tuple[ProductModel, str]:
        """The object's model in its object frame, and its shape type (the manifest's, or guessed)."""
        parts = load_mesh_parts(path, self.require_texture)
        vertices = np.concatenate([p.vertices for p in parts])
        if not np.isfinite(vertices).all() or np.ptp(vertices, axis=0).max() <= 0:
            raise MeshError(f"{path}: degenerate mesh (non-finite or all vertices at one point)")
        layout = entry.layout if entry else None
        if layout is None:
            layout = guess_layout(vertices)
            if entry is None:
                log.warning("%s: not in the manifest; guessed shape %s from its bounding box (%s)", name, layout, path)
        shape = entry.shape if entry else layout
        frame = object_frame(vertices, layout, self._direction(entry, "up"), self._direction(entry, "front"),
                             entry.yaw_deg if entry else 0.0)  # fmt: skip
        for part in parts:
            part.apply_transform(frame.transform)
        return ProductModel(parts, layout_planes(layout, frame.extents), name), shape

    def models(self) -> Iterator[ProductModel]:
        """Every object's model in object order (meshes are read again on each call)."""
        for name, path, entry in self.objects():
            yield self.load_model(name, path, entry)[0]

    # ------------------------------------------------------------------------------------ source
    def fingerprint(self) -> list[tuple[str, int, int]]:
        """``(path relative to root, size, mtime_ns)`` of every file in each object's mesh folder:
        editing a mesh, its material or a texture beside it changes the cache key."""
        rows = set()
        for _, path, _ in self.objects():
            for f in sorted(path.parent.iterdir()):
                if f.is_file():
                    st = f.stat()
                    rel = f.relative_to(self.root) if f.is_relative_to(self.root) else f
                    rows.add((str(rel), st.st_size, st.st_mtime_ns))
        return sorted(rows)

    def cache_key(self) -> dict[str, Any]:
        files = hashlib.sha1(repr(self.fingerprint()).encode()).hexdigest()
        manifest = hashlib.sha1(self.manifest.path.read_bytes()).hexdigest() if self.manifest.path else None
        return {"type": f"mesh_source/{self.dataset}", "version": MESH_SOURCE_VERSION, "root": str(self.root.resolve()),
                "files": files, "manifest": manifest, "fill": self.fill, "supersample": self.supersample,
                "subset": self.subset, "only_manifest": self.only_manifest, "up": self.up, "front": self.front,
                "objects": [name for name, _, _ in self.objects()]}  # fmt: skip

    @property
    def num_planes(self) -> int:
        """Planes expected from the manifest (6 for objects whose layout is not known yet)."""
        return sum(PLANES_PER_LAYOUT.get((e.layout if e else None) or "", 6) for _, _, e in self.objects())

    def build(self, image_size: int, progress: ProgressFn | None = None) -> CanonicalSet:
        """Load every mesh and render its canonical planes at ``image_size`` px."""
        from matl.data.catalog.rendering import CanonicalRenderer

        images, masks, plane_object, plane_names, names, shapes = [], [], [], [], [], []
        expected = self.num_planes
        with CanonicalRenderer(image_size, self.supersample, self.fill) as renderer:
            for o, (name, path, entry) in enumerate(self.objects()):
                model, shape = self.load_model(name, path, entry)
                imgs, msks = renderer.render(model)
                images.append(imgs)
                masks.append(msks)
                plane_object += [o] * len(model.planes)
                plane_names += [p.name for p in model.planes]
                names.append(name)
                shapes.append(shape)
                if progress is not None:
                    progress(len(plane_names), max(expected, len(plane_names)))
        return CanonicalSet(np.concatenate(images), np.concatenate(masks), np.asarray(plane_object, np.int64),
                            plane_names, names, shapes)  # fmt: skip


def _mesh_files(folder: Path) -> list[Path]:
    files = [f for f in folder.iterdir() if f.is_file() and f.suffix.lower() in MESH_SUFFIXES]
    return sorted(files, key=lambda f: (f.suffix.lower() != ".obj", f.name))


def _subfolders(root: Path) -> list[Path]:
    return sorted(d for d in root.iterdir() if d.is_dir() and not d.name.startswith("."))


class YCBSource(MeshSource):
    """``data=ycb``: YCB object folders ``<root>/<id>_<name>/google_16k/textured.obj``."""

    dataset = "ycb"

    def layout_hint(self) -> str:
        return "expected <root>/<id>_<name>/google_16k/textured.obj"

    def find_meshes(self) -> list[tuple[str, Path]]:
        found = []
        for folder in _subfolders(self.root):
            mesh = folder / "google_16k" / "textured.obj"
            if mesh.is_file():
                found.append((folder.name, mesh))
            else:
                log.info("skipping %s: no google_16k/textured.obj (not every YCB object has that scan)", folder)
        return found


class APCSource(MeshSource):
    """``data=apc``: APC 2015 Berkeley scans
    ``<root>/<object>/textured_meshes/optimized_poisson_texture_mapped_mesh.obj``."""

    dataset = "apc"
    MESH = Path("textured_meshes") / "optimized_poisson_texture_mapped_mesh.obj"

    def layout_hint(self) -> str:
        return f"expected <root>/<object>/{self.MESH}"

    def find_meshes(self) -> list[tuple[str, Path]]:
        found = []
        for folder in _subfolders(self.root):
            mesh = folder / self.MESH
            if mesh.is_file():
                found.append((folder.name, mesh))
            else:
                log.info("skipping %s: no %s", folder, self.MESH)
        return found


class ARCSource(MeshSource):
    """``data=arc``: ARC 2017 item folders, each holding an ``.obj`` or ``.ply``."""

    dataset = "arc"

    def layout_hint(self) -> str:
        return "expected <root>/<item>/<mesh>.obj or .ply"

    def find_meshes(self) -> list[tuple[str, Path]]:
        found = []
        for folder in _subfolders(self.root):
            files = _mesh_files(folder)
            if files:
                if len(files) > 1:
                    log.info("%s: %d meshes, using %s", folder, len(files), files[0].name)
                found.append((folder.name, files[0]))
            else:
                log.info("skipping %s: no .obj or .ply file", folder)
        return found


class MeshFolderSource(MeshSource):
    """``data=meshes``: any folder of textured meshes plus a manifest of their shape types."""

    dataset = "meshes"

    def find_meshes(self) -> list[tuple[str, Path]]:
        found: dict[str, Path] = {}
        for f in _mesh_files(self.root):
            found.setdefault(f.stem, f)
        for folder in _subfolders(self.root):
            files = _mesh_files(folder)
            if files:
                found.setdefault(folder.name, files[0])
        for name, entry in self.manifest.entries.items():
            if entry.mesh:
                path = Path(entry.mesh).expanduser()
                path = path if path.is_absolute() else self.root / path
                if not path.is_file():
                    raise MeshError(f"{path}: no such mesh file (mesh of {name!r} in manifest {self.manifest.path})")
                match = next((k for k in found if k.lower() == name), name)
                found[match] = path
        return sorted(found.items())

