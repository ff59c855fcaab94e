"""Enrolling a gallery folder ``<root>/<object>/<plane>.png`` without retraining (paper Sec. 2.1).

Every canonical image file is loaded, resized with its aspect kept and centre-padded to the model
size (:mod:`matl.data.image_files`), rotated into the checkpoint's ``N`` fixed anchors and embedded
once by ``c()``. The features are cached next to the gallery in ``.matl_gallery_<ckpt>_<files>.pt``
(plain tensors, loaded with ``weights_only=True``), keyed by the checkpoint's sha256 and every file's
path, mtime and size, so adding, removing or editing a file refreshes it.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from torch import nn

from matl.data.gallery import Gallery
from matl.data.image_files import GalleryFiles, ImageFileError, fit_to_model, load_image_file, scan_gallery
from matl.geometry import anchor_H_canon, warp_image
from matl.models.recognizer import embed
from matl.utils.errors import MatlError
from matl.utils.io import atomic_write

log = logging.getLogger(__name__)

CACHE_FORMAT = 1  # bump when the cache's content or meaning changes: old files then miss the key
CACHE_PREFIX = ".matl_gallery_"
BUILD_PLANES = 256  # planes warped into anchors at a time (build_gallery)


# ---------------------------------------------------------------------------------------- gallery
@dataclass
class EnrolledGallery:
    """A gallery built from canonical image files.

    Attributes:
        gallery: the ``G = P * N`` anchors at model size with labels and ``anchor_H_canon``.
        features: ``(G, D)`` ``c(anchor)``, or None if no feature net was given.
        canon_H_file: ``(P, 3, 3)`` float64, gallery-file pixel -> canonical model-frame pixel.
        file_sizes: ``(P, 2)`` int64 ``(height, width)`` of each canonical image file.
        paths: ``(P,)`` the canonical image file of each plane.
        cache_file: the feature cache used or written, if any.
        canon_u8: ``(P, 3, S, S)`` uint8 canonical images at model size (the anchors are their rotations).
    """

    gallery: Gallery
    features: torch.Tensor | None
    canon_H_file: torch.Tensor
    file_sizes: torch.Tensor
    paths: list[Path]
    cache_file: Path | None = None
    canon_u8: torch.Tensor | None = None


def report_skipped(path: Path, reason: str) -> None:
    """One line per unusable file; the run goes on."""
    log.warning("skipped %s: %s", path, reason)


def _load_planes(files: GalleryFiles, size: int,
                 fill: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, list[int]]:
    """Load and fit every plane file; unusable files are reported and dropped.

    Returns:
        uint8 ``(P', 3, S, S)`` canonical images (quantised like the catalogs' canonical sets, so the
        cached and uncached paths see identical pixels), ``(P', 3, 3)`` ``canon_H_file``, ``(P', 2)``
        file ``(height, width)`` and the indices of the kept planes into ``files.paths``.
    """
    images, matrices, sizes, kept = [], [], [], []
    for i, path in enumerate(files.paths):
        try:
            original = load_image_file(path)
            image, fit = fit_to_model(original, size, fill)
        except ImageFileError as error:
            report_skipped(path, str(error).removeprefix(f"{path}: "))
            continue
        images.append((image * 255.0).round().to(torch.uint8))
        matrices.append(fit.model_H_file)
        sizes.append(original.shape[:2])
        kept.append(i)
    if not images:
        return (torch.zeros(0, 3, size, size, dtype=torch.uint8), torch.zeros(0, 3, 3, dtype=torch.float64),
                torch.zeros(0, 2, dtype=torch.long), [])
    return torch.stack(images), torch.stack(matrices), torch.tensor(sizes, dtype=torch.long), kept


def _cache_file(root: Path, key: dict[str, Any]) -> Path:
    key_json = json.dumps(key, sort_keys=True)
    files_digest = hashlib.sha256(key_json.encode()).hexdigest()[:16]
    return root / f"{CACHE_PREFIX}{key['checkpoint'][:16]}_{files_digest}.pt"


def _read_cache(path: Path, key: dict[str, Any]) -> dict[str, Any] | None:
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


def _write_cache(path: Path, payload: dict[str, Any]) -> None:
    """Atomic write (:func:`matl.utils.io.atomic_write`); stale caches of the same checkpoint are
    removed. A read-only gallery folder only costs a warning."""
    try:
        with atomic_write(path, "wb") as f:
            torch.save(payload, f)
    except OSError as error:
        log.warning("cannot write the gallery cache %s (%s); features will be recomputed next time", path, error)
        return
    same_checkpoint = path.name[:len(CACHE_PREFIX) + 16]
    for old in path.parent.glob(f"{same_checkpoint}_*.pt"):
        if old != path:
            with contextlib.suppress(OSError):
                old.unlink()


def build_gallery(canon_u8: torch.Tensor, plane_object: list[int], plane_names: list[str],
                  object_names: list[str], num_anchors: int) -> Gallery:
    """The ``P * N`` fixed anchors of the canonical images (docs/design.md), flattened plane-major."""
    P, N = len(canon_u8), num_anchors
    size = int(canon_u8.shape[-1])
    H = anchor_H_canon(N, (size, size), torch.float64)                    # (N, 3, 3)
    flat_H = H.repeat(P, 1, 1)                                             # (P*N, 3, 3)
    if P:  # warped BUILD_PLANES planes at a time: the peak stays near the anchors' own (P*N, 3, S, S) floats
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
                  fill: float = 1.0, cache_tag: str | None = None, batch_size: int = 256) -> EnrolledGallery:
    """Enrol ``<root>/<object>/<plane>.png`` files into a gallery, features cached when ``cache_tag`` is set.

    Args:
        root: the gallery folder.
        feature_net: ``c()`` (in eval mode), or None to skip the features.
        image_size: model side ``S`` (from the checkpoint).
        num_anchors: ``N`` (from the checkpoint).
        fill: see :func:`matl.data.image_files.fit_geometry`.
        cache_tag: the checkpoint's sha256; None disables the on-disk cache.
        batch_size: images per ``c()`` call.
    Raises:
        MatlError: no folder, or no usable image in it.
    """
    files = scan_gallery(root)
    for path, reason in files.skipped:
        report_skipped(path, reason)
    layout = f"{files.root}/<object>/<plane>.png"
    if not files.paths:
        raise MatlError(f"gallery={files.root} holds no canonical images: expected {layout}")
    key = None if cache_tag is None else {
        "format": CACHE_FORMAT, "checkpoint": cache_tag, "image_size": int(image_size),
        "num_anchors": int(num_anchors), "fill": float(fill), "anchors": "fixed", "files": files.fingerprint()}
    cache_path = None if key is None else _cache_file(files.root, key)
    payload = None if cache_path is None else _read_cache(cache_path, key)
    if payload is not None:
        log.info("gallery features loaded from %s", cache_path)
        canon_u8, canon_H_file, file_sizes = payload["images"], payload["canon_H_file"], payload["file_sizes"]
        kept = [int(i) for i in payload["kept"]]
    else:
        canon_u8, canon_H_file, file_sizes, kept = _load_planes(files, image_size, fill)
    if not kept:
        raise MatlError(f"gallery={files.root} holds no usable image (all were skipped): expected {layout}")
    # objects whose every plane was skipped disappear; the others are re-indexed densely
    used_objects = sorted({files.plane_object[i] for i in kept})
    remap = {o: j for j, o in enumerate(used_objects)}
    gallery = build_gallery(canon_u8, [remap[files.plane_object[i]] for i in kept],
                             [files.plane_names[i] for i in kept], [files.object_names[o] for o in used_objects],
                             num_anchors)
    features = None
    if payload is not None:
        features = payload["features"]
    elif feature_net is not None:
        first = next(iter(feature_net.parameters()), None)
        device = first.device if first is not None else torch.device("cpu")
        features = embed(feature_net, gallery.images.to(device), batch_size).cpu()
        if cache_path is not None:
            _write_cache(cache_path, {"key": json.dumps(key, sort_keys=True), "images": canon_u8,
                                      "canon_H_file": canon_H_file, "file_sizes": file_sizes,
                                      "kept": torch.tensor(kept, dtype=torch.long), "features": features})
    log.info("gallery: %d objects, %d planes, %d anchors", len(gallery.object_names), len(kept), len(gallery))
    return EnrolledGallery(gallery, features, canon_H_file, file_sizes, [files.paths[i] for i in kept], cache_path,
                           canon_u8)


