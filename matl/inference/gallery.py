"""Enrolling a gallery folder ``<root>/<object>/<plane>.png`` without retraining (paper Sec. 2.1).

Every canonical image file is loaded, resized with its aspect kept and centre-padded to the model
size (:mod:`matl.data.image_files`), rotated into the checkpoint's ``N`` fixed anchors and embedded
once by ``c()``. The features are cached next to the gallery, one file per product in
``.matl_gallery_<ckpt>_<settings>/<object>.pt`` (plain tensors, loaded with ``weights_only=True``), each keyed by
the checkpoint's sha256, the enrolment settings and the path, mtime and size of every file of its product: adding,
removing or editing a product embeds that product alone, and an interrupted enrolment keeps the products it wrote.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
import sys
import time
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn
from torch import nn

from matl.data.gallery import Gallery
from matl.data.image_files import GalleryFiles, ImageFileError, fit_to_model, load_image_file, scan_gallery
from matl.geometry import anchor_H_canon, warp_image
from matl.models.recognizer import embed
from matl.utils.errors import MatlError
from matl.utils.io import atomic_write

log = logging.getLogger(__name__)

CACHE_FORMAT = 2  # bump when the cache's content or meaning changes: old files then miss the key (2: per product)
CACHE_PREFIX = ".matl_gallery_"
BUILD_PLANES = 256  # planes warped into anchors at a time (build_gallery)
ENROL_PLANES = 256  # planes loaded, embedded and written to the cache at a time (enrol_gallery)


# ---------------------------------------------------------------------------------------- gallery
@dataclass
class EnrolledGallery:
    """A gallery built from canonical image files.

    Attributes:
        gallery: the ``G = P * N`` anchors at model size with labels and ``anchor_H_canon`` (None: not built,
            ``anchors=False``).
        features: ``(G, D)`` ``c(anchor)``, or None if no feature net was given.
        canon_H_file: ``(P, 3, 3)`` float64, gallery-file pixel -> canonical model-frame pixel.
        file_sizes: ``(P, 2)`` int64 ``(height, width)`` of each canonical image file.
        paths: ``(P,)`` the canonical image file of each plane.
        cache_file: the folder of the features' cache (one file per product), if it was used and is writable.
        canon_u8: ``(P, 3, S, S)`` uint8 canonical images at model size (the anchors are their rotations).
    """

    gallery: Gallery | None
    features: torch.Tensor | None
    canon_H_file: torch.Tensor
    file_sizes: torch.Tensor
    paths: list[Path]
    cache_file: Path | None = None
    canon_u8: torch.Tensor | None = None
    #: ``(P,)`` each plane's object and plane name
    plane_objects: list[str] | None = None
    plane_names: list[str] | None = None


def report_skipped(path: Path, reason: str) -> None:
    """One line per unusable file; the run goes on."""
    log.warning("skipped %s: %s", path, reason)


def _load_plane(path: Path, size: int, fill: float) -> tuple[torch.Tensor, torch.Tensor, tuple[int, int]] | str:
    """One plane file loaded and fitted: ``(uint8 (3, S, S) canonical image, (3, 3) canon_H_file, (height, width))``
    (quantised like the catalogs' canonical sets, so the cached and uncached paths see identical pixels), or why it
    is unusable."""
    try:
        original = load_image_file(path)
        image, fit = fit_to_model(original, size, fill)
    except ImageFileError as error:
        return str(error).removeprefix(f"{path}: ")
    return (image * 255.0).round().to(torch.uint8), fit.model_H_file, tuple(original.shape[:2])


def _load_planes(paths: list[Path], size: int, fill: float, pool: ThreadPoolExecutor | None = None
                 ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, list[int]]:
    """Load and fit plane files (decoded on ``pool``'s threads when given); unusable files are reported and dropped.

    Returns:
        uint8 ``(P', 3, S, S)`` canonical images, ``(P', 3, 3)`` ``canon_H_file``, ``(P', 2)`` file
        ``(height, width)`` and the positions of the kept files in ``paths``.
    """
    loaded = (pool.map(_load_plane, paths, [size] * len(paths), [fill] * len(paths)) if pool is not None
              else (_load_plane(path, size, fill) for path in paths))
    images, matrices, sizes, kept = [], [], [], []
    for i, (path, plane) in enumerate(zip(paths, loaded, strict=True)):
        if isinstance(plane, str):
            report_skipped(path, plane)
            continue
        images.append(plane[0])
        matrices.append(plane[1])
        sizes.append(plane[2])
        kept.append(i)
    if not images:
        return (torch.zeros(0, 3, size, size, dtype=torch.uint8), torch.zeros(0, 3, 3, dtype=torch.float64),
                torch.zeros(0, 2, dtype=torch.long), [])
    return torch.stack(images), torch.stack(matrices), torch.tensor(sizes, dtype=torch.long), kept


def _cache_folder(root: Path, settings: dict[str, Any]) -> Path:
    """``<root>/.matl_gallery_<checkpoint>_<settings>``: one file per product inside."""
    digest = hashlib.sha256(json.dumps(settings, sort_keys=True).encode()).hexdigest()[:16]
    return root / f"{CACHE_PREFIX}{settings['checkpoint'][:16]}_{digest}"


def _read_cache(path: Path, key: dict[str, Any]) -> dict[str, Any] | None:
    """A product's cache file, or None where it is missing, unreadable (reported) or made from other files or
    settings (its key)."""
    if not path.is_file():
        return None
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as error:  # a corrupt cache is never fatal: it is rebuilt
        log.warning("gallery cache %s is unreadable (%s); rebuilding it", path, " ".join(str(error).split()))
        return None
    if not isinstance(payload, dict) or payload.get("key") != json.dumps(key, sort_keys=True):
        return None
    return payload


def _write_cache(path: Path, payload: dict[str, Any]) -> bool:
    """Atomic write (:func:`matl.utils.io.atomic_write`); False (with a warning) where the folder is read-only."""
    try:
        path.parent.mkdir(exist_ok=True)
        with atomic_write(path, "wb") as f:
            torch.save(payload, f)
    except OSError as error:
        log.warning("cannot write the gallery cache %s (%s); features will be recomputed next time", path, error)
        return False
    return True


def _drop_stale(folder: Path, products: set[str], checkpoint: str) -> None:
    """Remove the cache files of products no longer in the gallery, and the single-file caches of this checkpoint
    that an earlier cache format wrote."""
    with contextlib.suppress(OSError):
        for old in folder.glob("*.pt"):
            if old.stem not in products:
                old.unlink()
        for old in folder.parent.glob(f"{CACHE_PREFIX}{checkpoint[:16]}_*.pt"):
            old.unlink()


def build_gallery(canon_u8: torch.Tensor, plane_object: list[int], plane_names: list[str],
                  object_names: list[str], num_anchors: int, images: torch.Tensor | None = None) -> Gallery:
    """The ``P * N`` fixed anchors of the canonical images (docs/design.md), flattened plane-major; ``images``:
    the anchors' ``(P * N, 3, S, S)`` images when already made (then only the labels are built)."""
    P, N = len(canon_u8), num_anchors
    size = int(canon_u8.shape[-1])
    H = anchor_H_canon(N, (size, size), torch.float64)                    # (N, 3, 3)
    flat_H = H.repeat(P, 1, 1)                                             # (P*N, 3, 3)
    if images is not None:
        if images.shape != (P * N, *canon_u8.shape[1:]):
            raise ValueError(f"images {tuple(images.shape)} are not the {P * N} anchors of {P} planes")
    elif P:  # warped BUILD_PLANES planes at a time: the peak stays near the anchors' own (P*N, 3, S, S) floats
        images = torch.empty((P * N, *canon_u8.shape[1:]), dtype=torch.float32)
        for start in range(0, P, BUILD_PLANES):
            canon = canon_u8[start:start + BUILD_PLANES].float().div(255.0).repeat_interleave(N, dim=0)
            images[start * N:start * N + len(canon)] = warp_image(canon, flat_H[start * N:start * N + len(canon)])
    else:
        images = canon_u8.float().div(255.0).repeat_interleave(N, dim=0)
    obj = torch.tensor(plane_object, dtype=torch.long)
    return Gallery(images=images, object_index=obj.repeat_interleave(N),
                   plane_index=torch.arange(P).repeat_interleave(N), anchor_index=torch.arange(N).repeat(P),
                   anchor_H_canon=flat_H, object_names=list(object_names), plane_names=list(plane_names))


def enrol_gallery(root: str | Path, feature_net: nn.Module | None, image_size: int, num_anchors: int,
                  fill: float = 1.0, cache_tag: str | None = None, batch_size: int = 256,
                  progress: bool | None = None, anchors: bool = True) -> EnrolledGallery:
    """Enrol ``<root>/<object>/<plane>.png`` files into a gallery, features cached per product when ``cache_tag``
    is set.

    Products whose files and settings match their cache file are read from it; the others are loaded (files
    decoded on every core), embedded and written :data:`ENROL_PLANES` planes at a time, so an interrupted
    enrolment keeps what it finished and a grown gallery embeds only its new or edited products.

    Args:
        root: the gallery folder.
        feature_net: ``c()`` (in eval mode), or None to skip the features.
        image_size: model side ``S`` (from the checkpoint).
        num_anchors: ``N`` (from the checkpoint).
        fill: see :func:`matl.data.image_files.fit_geometry`.
        cache_tag: the checkpoint's sha256; None disables the on-disk cache.
        batch_size: images per ``c()`` call.
        progress: a progress bar over the products to embed (None: on a terminal, for more than
            :data:`ENROL_PLANES` planes).
        anchors: build the gallery's anchor images (False: the planes, their features and names alone; a
            :class:`~matl.inference.api.Recognizer` builds its own gallery from them).
    Raises:
        MatlError: no folder, or no usable image in it.
    """
    started = time.perf_counter()
    files = scan_gallery(root)
    for path, reason in files.skipped:
        report_skipped(path, reason)
    layout = f"{files.root}/<object>/<plane>.png"
    if not files.paths:
        raise MatlError(f"gallery={files.root} holds no canonical images: expected {layout}")
    planes_of = _planes_of(files)
    products, missing, folder, writable = _product_payloads(files, planes_of, range(len(files.object_names)),
                                                            feature_net, image_size, num_anchors, fill, cache_tag,
                                                            batch_size, progress)
    if folder is not None and writable:
        _drop_stale(folder, set(files.object_names), str(cache_tag))
    kept = [planes_of[o][int(j)] for o, payload in enumerate(products) for j in payload["kept"]]
    if not kept:
        raise MatlError(f"gallery={files.root} holds no usable image (all were skipped): expected {layout}")
    used = [p for p in products if len(p["kept"])]  # a product whose every file was skipped adds nothing
    canon_u8 = torch.cat([p["images"] for p in used])
    canon_H_file = torch.cat([p["canon_H_file"] for p in used])
    file_sizes = torch.cat([p["file_sizes"] for p in used])
    features = None if feature_net is None else torch.cat([p["features"] for p in used])
    # objects whose every plane was skipped disappear; the others are re-indexed densely
    used_objects = sorted({files.plane_object[i] for i in kept})
    remap = {o: j for j, o in enumerate(used_objects)}
    plane_names = [files.plane_names[i] for i in kept]
    gallery = build_gallery(canon_u8, [remap[files.plane_object[i]] for i in kept], plane_names,
                            [files.object_names[o] for o in used_objects], num_anchors) if anchors else None
    log.info("gallery: %d objects, %d planes, %d anchors (%d products read from the cache, %d enrolled; %.1f s)",
             len(used_objects), len(kept), len(kept) * num_anchors, len(products) - missing, missing,
             time.perf_counter() - started)
    return EnrolledGallery(gallery, features, canon_H_file, file_sizes, [files.paths[i] for i in kept],
                           folder if writable else None, canon_u8,
                           [files.object_names[files.plane_object[i]] for i in kept], plane_names)


def _planes_of(files: GalleryFiles) -> list[list[int]]:
    """Each product's planes (indices into ``files.paths``)."""
    planes_of: list[list[int]] = [[] for _ in files.object_names]
    for i, o in enumerate(files.plane_object):
        planes_of[o].append(i)
    return planes_of


def _product_payloads(files: GalleryFiles, planes_of: list[list[int]], wanted: Sequence[int],
                      feature_net: nn.Module | None, image_size: int, num_anchors: int, fill: float,
                      cache_tag: str | None, batch_size: int, progress: bool | None
                      ) -> tuple[list[dict[str, Any] | None], int, Path | None, bool]:
    """The ``wanted`` products' images, geometry and features: read from their cache files where those match,
    else loaded, embedded and written :data:`ENROL_PLANES` planes at a time. Returns the payload of each product
    (None where not wanted), how many were embedded, the cache folder and whether it was writable."""
    settings = {"format": CACHE_FORMAT, "checkpoint": cache_tag, "image_size": int(image_size),
                "num_anchors": int(num_anchors), "fill": float(fill), "anchors": "fixed"}
    caching = cache_tag is not None and feature_net is not None
    folder = _cache_folder(files.root, settings) if caching else None
    prints = _product_fingerprints(files) if caching else {}
    products: list[dict[str, Any] | None] = [None] * len(files.object_names)
    if folder is not None:
        for o in wanted:
            name = files.object_names[o]
            products[o] = _read_cache(folder / f"{name}.pt", {**settings, "files": prints[name]})
    missing = [o for o in wanted if products[o] is None]
    writable = folder is not None
    show = progress if progress is not None else (sys.stderr.isatty() and sum(len(planes_of[o]) for o in missing)
                                                  > ENROL_PLANES)
    columns = (TextColumn("[bold]enrol"), BarColumn(), MofNCompleteColumn(), TextColumn("products"),
               TimeElapsedColumn(), TimeRemainingColumn())
    with ThreadPoolExecutor(max_workers=os.cpu_count() or 1) as pool, Progress(*columns, disable=not show,
                                                                             transient=True) as bar:
        task = bar.add_task("enrol", total=len(missing))
        for part in _parts(missing, planes_of, ENROL_PLANES):
            paths = [files.paths[i] for o in part for i in planes_of[o]]
            canon_u8, canon_H_file, file_sizes, kept = _load_planes(paths, image_size, fill, pool)
            features = None
            if feature_net is not None and kept:
                anchors = build_gallery(canon_u8, [0] * len(kept), ["p"] * len(kept), ["o"], num_anchors)
                features = _embed(feature_net, anchors.images, batch_size)
            owner = [o for o in part for _ in planes_of[o]]  # the product of each loaded file
            first = 0
            for o in part:
                rows = [j for j, k in enumerate(kept) if owner[k] == o]  # this product's kept planes
                local = [kept[j] - first for j in rows]
                first += len(planes_of[o])
                anchors_of = torch.tensor([j * num_anchors + a for j in rows for a in range(num_anchors)],
                                          dtype=torch.long)
                payload = {"images": canon_u8[rows].clone(), "canon_H_file": canon_H_file[rows].clone(),
                           "file_sizes": file_sizes[rows].clone(), "kept": torch.tensor(local, dtype=torch.long),
                           "features": None if features is None else features[anchors_of].clone()}
                products[o] = payload
                if writable:
                    name = files.object_names[o]
                    writable = _write_cache(folder / f"{name}.pt", {
                        "key": json.dumps({**settings, "files": prints[name]}, sort_keys=True), **payload})
            bar.advance(task, len(part))
    return products, len(missing), folder, writable


def cache_gallery_shard(root: str | Path, feature_net: nn.Module, image_size: int, num_anchors: int, fill: float,
                        cache_tag: str, shard: int, shards: int, batch_size: int = 256,
                        progress: bool | None = None) -> tuple[int, int]:
    """Enrol one shard of a gallery folder's products into its feature cache (:func:`enrol_gallery`'s): the
    products at positions ``shard``, ``shard + shards``, ... of the folder's sorted product folders. The shards of
    one folder run in separate processes or hosts that share the folder; an :func:`enrol_gallery` afterwards reads
    every product from the cache. Returns ``(products of the shard, of those embedded now)``."""
    if not (isinstance(shards, int) and shards >= 1 and isinstance(shard, int) and 0 <= shard < shards):
        raise MatlError(f"shard={shard} of shards={shards} is invalid: use integers with 0 <= shard < shards")
    files = scan_gallery(root)
    if not files.paths:
        raise MatlError(f"gallery={files.root} holds no canonical images: expected {files.root}/<object>/<plane>.png")
    wanted = range(shard, len(files.object_names), shards)
    _, embedded, _, writable = _product_payloads(files, _planes_of(files), wanted, feature_net, image_size,
                                                 num_anchors, fill, cache_tag, batch_size, progress)
    if not writable:
        raise MatlError(f"gallery={files.root}: its feature cache cannot be written there; a shard's work is its "
                        "cache files: give a folder this process can write")
    log.info("gallery shard %d of %d: %d products, %d embedded", shard, shards, len(wanted), embedded)
    return len(wanted), embedded


def _product_fingerprints(files: GalleryFiles) -> dict[str, list[tuple[str, int, int]]]:
    """Each product folder's part of :meth:`GalleryFiles.fingerprint` (its files, used or skipped)."""
    out: dict[str, list[tuple[str, int, int]]] = {name: [] for name in files.object_names}
    for row in files.fingerprint():
        parts = Path(row[0]).parts
        if len(parts) > 1 and parts[0] in out:
            out[parts[0]].append(row)
    return out


def _parts(products: list[int], planes_of: list[list[int]], most: int) -> list[list[int]]:
    """``products`` in consecutive groups of at most ``most`` planes (a product with more is a group alone)."""
    groups: list[list[int]] = []
    count = 0
    for o in products:
        n = len(planes_of[o])
        if not groups or count + n > most:
            groups.append([])
            count = 0
        groups[-1].append(o)
        count += n
    return groups


def _embed(feature_net: nn.Module, images: torch.Tensor, batch_size: int) -> torch.Tensor:
    first = next(iter(feature_net.parameters()), None)
    device = first.device if first is not None else torch.device("cpu")
    return embed(feature_net, images.to(device), batch_size).cpu()


