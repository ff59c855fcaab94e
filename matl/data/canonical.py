"""Canonical images of every plane of every object, and their on-disk cache.

A *canonical image* is the top-down view of one plane (camera axis perpendicular to it, through
the object's centre; ``docs/design.md``). Any dataset, procedural or from the user's disk, provides
its planes as a :class:`CanonicalSource`; :func:`load_canonical` builds a :class:`CanonicalSet`
once and caches it under a key derived from the source's configuration. Mesh-based sources are
also :class:`ModelSource` s: they hand out their 3D models, so views can be rendered from them.
"""

from __future__ import annotations

import hashlib
import inspect
import json
import logging
import warnings
import zipfile
import zlib
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

import numpy as np

from matl.utils.errors import MatlError
from matl.utils.io import atomic_savez

if TYPE_CHECKING:
    from matl.data.catalog.shapes import ProductModel

log = logging.getLogger(__name__)

# Bump when the cache layout or the meaning of its arrays changes: old files then miss the key.
CACHE_FORMAT_VERSION = 1
OBJECT_SHAPES = ("planar", "rectangular", "cylindrical", "nonplanar")
_ARRAYS = ("images", "masks", "plane_object", "plane_names", "object_names", "object_shapes", "key")

ProgressFn = Callable[[int, int], None]
"""``progress(done, total)``, called by a source's build after each rendered unit of work."""


def planes_of_objects(plane_object: np.ndarray, object_indices: Sequence[int] | np.ndarray | None) -> np.ndarray:
    """(K,) int64 indices of the planes of the given objects, in the order given (each object's planes
    in their own order): the planes :meth:`CanonicalSet.subset_objects` keeps. ``None``: every plane."""
    if object_indices is None:
        return np.arange(len(plane_object))
    idx = [int(i) for i in np.asarray(object_indices, dtype=np.int64).reshape(-1)]
    if not idx:
        return np.zeros(0, np.int64)
    return np.concatenate([np.flatnonzero(plane_object == i) for i in idx])


@dataclass(frozen=True, eq=False)
class CanonicalSet:
    """Canonical images of ``P`` planes belonging to ``O`` objects.

    Attributes:
        images: (P, S, S, 3) uint8 RGB, background exactly 0.
        masks: (P, S, S) bool, True on the object's foreground (from the render's depth/alpha).
        plane_object: (P,) int64, index into ``object_names`` of each plane's object.
        plane_names: (P,) plane names such as "front", "top", "side_045".
        object_names: (O,) unique object names.
        object_shapes: (O,) one of :data:`OBJECT_SHAPES` per object.
    """

    images: np.ndarray
    masks: np.ndarray
    plane_object: np.ndarray
    plane_names: list[str]
    object_names: list[str]
    object_shapes: list[str]

    def __post_init__(self) -> None:
        p = self.images.shape[0]
        if self.images.ndim != 4 or self.images.shape[3] != 3 or self.images.shape[1] != self.images.shape[2]:
            raise ValueError(f"images must be (P, S, S, 3), got {self.images.shape}")
        if self.images.dtype != np.uint8:
            raise ValueError(f"images must be uint8, got {self.images.dtype}")
        if self.masks.shape != self.images.shape[:3] or self.masks.dtype != np.bool_:
            raise ValueError(f"masks must be bool {self.images.shape[:3]}, got {self.masks.dtype} {self.masks.shape}")
        if self.plane_object.shape != (p,) or self.plane_object.dtype != np.int64:
            raise ValueError(
                f"plane_object must be int64 ({p},), got {self.plane_object.dtype} {self.plane_object.shape}"
            )
        if len(self.plane_names) != p:
            raise ValueError(f"{len(self.plane_names)} plane names for {p} planes")
        o = len(self.object_names)
        if len(self.object_shapes) != o:
            raise ValueError(f"{len(self.object_shapes)} object shapes for {o} objects")
        if len(set(self.object_names)) != o:
            raise ValueError("object names must be unique")
        bad = sorted(set(self.object_shapes) - set(OBJECT_SHAPES))
        if bad:
            raise ValueError(f"unknown object shapes {bad}; valid: {OBJECT_SHAPES}")
        if p and (self.plane_object.min() < 0 or self.plane_object.max() >= o):
            raise ValueError("plane_object indexes outside object_names")

    @property
    def num_planes(self) -> int:
        """Number of planes ``P``."""
        return int(self.images.shape[0])

    @property
    def num_objects(self) -> int:
        """Number of objects ``O``."""
        return len(self.object_names)

    @property
    def image_size(self) -> int:
        """Side ``S`` of the square canonical images."""
        return int(self.images.shape[1])

    def plane_label(self, plane: int) -> str:
        """Human-readable ``"<object>/<plane>"`` of plane index ``plane``."""
        return f"{self.object_names[int(self.plane_object[plane])]}/{self.plane_names[plane]}"

    def subset_objects(self, object_indices: Sequence[int] | np.ndarray) -> CanonicalSet:
        """The planes of the given objects only, objects re-indexed ``0..len(object_indices)-1``
        in the order given; each object's planes keep their original relative order."""
        idx = [int(i) for i in np.asarray(object_indices, dtype=np.int64).reshape(-1)]
        if len(set(idx)) != len(idx):
            raise ValueError(f"object indices must be unique, got {idx}")
        if any(i < 0 or i >= self.num_objects for i in idx):
            raise IndexError(f"object indices must be in [0, {self.num_objects}), got {idx}")
        planes = planes_of_objects(self.plane_object, idx)
        remap = np.full(self.num_objects, -1, dtype=np.int64)
        remap[idx] = np.arange(len(idx))
        return CanonicalSet(
            images=self.images[planes],
            masks=self.masks[planes],
            plane_object=remap[self.plane_object[planes]],
            plane_names=[self.plane_names[i] for i in planes],
            object_names=[self.object_names[i] for i in idx],
            object_shapes=[self.object_shapes[i] for i in idx],
        )


@runtime_checkable
class CanonicalSource(Protocol):
    """Anything that can produce a :class:`CanonicalSet`.

    A source may also accept an optional ``progress: ProgressFn`` keyword in ``build``;
    :func:`load_canonical` forwards one when given and the source accepts it.
    """

    def cache_key(self) -> dict[str, Any]:
        """Everything that determines the images, JSON-serialisable."""
        ...

    def build(self, image_size: int) -> CanonicalSet:
        """Render or load all canonical images at ``image_size`` px."""
        ...


@runtime_checkable
class ModelSource(CanonicalSource, Protocol):
    """A :class:`CanonicalSource` that can also hand out its 3D models (mesh-based sources).

    ``models()`` yields one textured :class:`ProductModel` per object, in the object order of the
    canonical set; ``fill`` and ``supersample`` are the canonical renders' framing and
    antialiasing, which rendered views must share so their homographies refer to the same pixels.
    """

    fill: float
    supersample: int

    def models(self) -> Iterator[ProductModel]:
        """Every object's textured model, in object order."""
        ...


def require_models(source: Any, what: str) -> ModelSource:
    """``source`` if it can render views, else a one-line error naming ``what`` needed them."""
    if not callable(getattr(source, "models", None)) or not hasattr(source, "fill"):
        name = type(source).__name__
        raise MatlError(
            f"{what} needs 3D models, but the data source {name} has only images; use a mesh-based dataset "
            "(synthetic_*, ycb, apc, arc, meshes) or the warped default"
        )
    return source


def cache_path(source: CanonicalSource, image_size: int, cache_dir: str | Path) -> Path:
    """File the set of ``source`` at ``image_size`` is cached in (inside ``cache_dir``)."""
    return _path_for(_full_key(source, image_size), cache_dir)


def _full_key(source: CanonicalSource, image_size: int) -> str:
    key = {"source": source.cache_key(), "image_size": int(image_size), "format": CACHE_FORMAT_VERSION}
    return json.dumps(key, sort_keys=True, separators=(",", ":"))


def _path_for(key_json: str, cache_dir: str | Path) -> Path:
    return Path(cache_dir) / f"canonical_{hashlib.sha1(key_json.encode()).hexdigest()}.npz"


def _save(cs: CanonicalSet, key_json: str, path: Path) -> None:
    """Write ``cs`` to ``path`` atomically (:func:`matl.utils.io.atomic_savez`): readers never see
    a partial file."""
    atomic_savez(
        path,
        images=cs.images,
        masks=cs.masks,
        plane_object=cs.plane_object,
        plane_names=np.array(cs.plane_names, dtype=str),
        object_names=np.array(cs.object_names, dtype=str),
        object_shapes=np.array(cs.object_shapes, dtype=str),
        key=np.array(key_json),
    )


def _load(path: Path, key_json: str) -> CanonicalSet:
    """Read a cache file; raises ValueError (or the reader's error) if it is incomplete or stale."""
    with np.load(path, allow_pickle=False) as z:
        missing = [a for a in _ARRAYS if a not in z.files]
        if missing:
            raise ValueError(f"missing arrays {missing}")
        if str(z["key"]) != key_json:
            raise ValueError("cache key mismatch")
        return CanonicalSet(
            images=z["images"],
            masks=z["masks"],
            plane_object=z["plane_object"].astype(np.int64),
            plane_names=[str(s) for s in z["plane_names"]],
            object_names=[str(s) for s in z["object_names"]],
            object_shapes=[str(s) for s in z["object_shapes"]],
        )


def _accepts_progress(source: CanonicalSource) -> bool:
    try:
        return "progress" in inspect.signature(source.build).parameters
    except (TypeError, ValueError):
        return False


def load_canonical(
    source: CanonicalSource, image_size: int, cache_dir: str | Path, progress: ProgressFn | None = None
) -> CanonicalSet:
    """Return the cached set if present, else build and cache it.

    The key is the sha1 of the JSON of ``source.cache_key()``, ``image_size`` and
    :data:`CACHE_FORMAT_VERSION`. The write is atomic (temp file in the same directory, then
    ``os.replace``) so an interrupted build never leaves a corrupt cache; a corrupt or stale file
    (unreadable, missing arrays, inconsistent shapes, other key) is rebuilt with a warning.
    ``progress`` is passed to ``source.build`` if its signature accepts it.
    """
    key_json = _full_key(source, image_size)
    path = _path_for(key_json, cache_dir)
    if path.exists():
        try:
            cs = _load(path, key_json)
            log.info("loaded %d canonical planes from %s", cs.num_planes, path)
            return cs
        except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile, zlib.error) as e:
            warnings.warn(f"canonical cache {path} is unreadable ({e}); rebuilding it", RuntimeWarning, stacklevel=2)
    if progress is not None and _accepts_progress(source):
        cs = source.build(image_size, progress=progress)  # type: ignore[call-arg]
    else:
        cs = source.build(image_size)
    if cs.image_size != image_size:
        raise ValueError(f"source built {cs.image_size} px images, {image_size} px requested")
    _save(cs, key_json, path)
    log.info("cached %d canonical planes in %s", cs.num_planes, path)
    return cs
