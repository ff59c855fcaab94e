"""Enrolment of a :class:`~matl.inference.api.Recognizer`'s gallery and its file: enrol / add / remove / save / load.

Every enrolled plane (:class:`_Plane`) keeps its canonical image at model size, its ``N`` anchors' features
(computed once, when the plane is added) and the matrix from its gallery image's pixels to the model frame.
:meth:`Enrolment.save` writes them (and the open-set calibration's samples) as plain tensors; :meth:`Enrolment.load`
reads them back for the same model.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Self

import torch

from matl.data.image_files import fit_to_model
from matl.inference.gallery import build_gallery, cache_gallery_shard, enrol_gallery, report_skipped
from matl.inference.images import MIN_GALLERY_SIDE, _as_rgb, _check_name, _gallery_image_problem
from matl.models.recognizer import embed
from matl.utils.errors import MatlError

GALLERY_FORMAT = 2  # bump when save()'s content changes meaning (2: the calibration samples, no per-plane copies)
READABLE_GALLERY_FORMATS = (1, 2)


@dataclass
class _Plane:
    """One enrolled plane: canonical image (uint8 ``(3, S, S)``), file geometry and anchor features."""

    object: str
    name: str
    canon_u8: torch.Tensor
    canon_H_file: torch.Tensor      # (3, 3) float64, gallery image pixel -> model pixel
    file_size: tuple[int, int]      # (height, width)
    path: str | None
    features: torch.Tensor          # (N, D) float32
    calibration: torch.Tensor | None = None  # (W, D) features of warped copies (open-set calibration)
    keypoints: Any = None  # its keypoints for keypoint_pose (ImageFeatures), computed at their first need


class Enrolment:
    """The gallery side of :class:`~matl.inference.api.Recognizer` (its planes, their file, the caches they
    invalidate); a mixin of it, using its model, options and lock."""

    @property
    def objects(self) -> list[str]:
        """The enrolled products, in enrolment order."""
        return list(self._products()[0])

    def _plane_objects(self) -> list[int]:
        """The product of each enrolled plane as its position in :attr:`objects`."""
        return self._products()[1]

    def _products(self) -> tuple[list[str], list[int], torch.Tensor]:
        """:attr:`objects`, :meth:`_plane_objects` and the latter as a ``(P,)`` int64 tensor, computed once per
        gallery (every query of a warehouse catalogue needs them; a dict of the names: ``objects.index`` per plane
        is quadratic in the gallery)."""
        held = self._product_index
        if held is None or held[0] is not self._planes or held[1] != len(self._planes):
            position: dict[str, int] = {}
            owners = [position.setdefault(p.object, len(position)) for p in self._planes]
            held = (self._planes, len(self._planes), list(position), owners, torch.tensor(owners, dtype=torch.long))
            self._product_index = held
        return held[2], held[3], held[4]

    @property
    def planes(self) -> list[tuple[str, str]]:
        """``(object, plane)`` of every enrolled plane."""
        return [(p.object, p.name) for p in self._planes]

    def _embed_anchors(self, canon_u8: torch.Tensor) -> torch.Tensor:
        gallery = build_gallery(canon_u8, [0] * len(canon_u8), ["p"] * len(canon_u8), ["o"], self.num_anchors)
        return embed(self.model.feature_net, gallery.images.to(self.device)).cpu()

    def _changed(self) -> None:
        if self._built is not None:  # its anchor images serve the next build's planes that it held
            self._previous_gallery = (self._built_planes, self._built[1])
        self._built = None
        self._calibrated = None
        self._verify_refiner = None
        self._grey = None

    def enrol(self, folder: str | Path, cache: bool = True) -> Self:
        """Add every plane of a gallery folder ``<folder>/<object>/<plane>.{png,jpg}`` (features cached on disk,
        and with ``cache`` the open-set calibration too, beside them: :meth:`calibration_cache_file`). A file
        whose shorter side is below :data:`MIN_GALLERY_SIDE` px, or that is empty (every pixel 0), is reported
        and skipped."""
        with self._lock:
            enrolled = enrol_gallery(folder, self.model.feature_net, self.image_size, self.num_anchors,
                                     self.gallery_fill, self.model_id if cache else None, anchors=False)
            N = self.num_anchors
            canon_u8 = enrolled.canon_u8
            added = []
            for p, path in enumerate(enrolled.paths):
                problem = _gallery_image_problem(tuple(int(v) for v in enrolled.file_sizes[p]), canon_u8[p])
                if problem is not None:
                    report_skipped(Path(path), problem)
                    continue
                added.append(_Plane(enrolled.plane_objects[p], enrolled.plane_names[p], canon_u8[p].clone(),
                                    enrolled.canon_H_file[p].clone(), tuple(int(v) for v in enrolled.file_sizes[p]),
                                    str(path), enrolled.features[p * N:(p + 1) * N].clone()))
            if not added:
                raise MatlError(f"gallery={folder} holds no usable image (all were skipped): expected "
                                f"{folder}/<object>/<plane>.png of at least {MIN_GALLERY_SIDE} px a side")
            replaced = {(p.object, p.name) for p in added}  # planes of the same name are replaced (in one pass)
            self._planes = [p for p in self._planes if (p.object, p.name) not in replaced] + added
            self._changed()
            folder_of_cache = enrolled.cache_file.parent if cache and enrolled.cache_file is not None else None
            self._calibration_folder = None if folder_of_cache is None else (folder_of_cache, [id(p) for p in added])
        return self

    def enrol_shard(self, folder: str | Path, shard: int, shards: int) -> tuple[int, int]:
        """Fill one shard of a gallery folder's per-product feature cache, without enrolling it here: the products
        ``shard``, ``shard + shards``, ... of its sorted product folders (shards run in separate processes or hosts
        sharing the folder; :meth:`enrol` afterwards reads every product from the cache). Returns ``(products of the
        shard, of those embedded now)``."""
        with self._lock:
            return cache_gallery_shard(folder, self.model.feature_net, self.image_size, self.num_anchors,
                                       self.gallery_fill, self.model_id, shard, shards)

    def add(self, object: str, plane: str, image: Any) -> Self:
        """Enrol one canonical image (a path, an HxWx3/HxWx4 array or a (3|4, H, W) tensor) as ``object/plane``.

        ``object`` and ``plane`` are names (non-empty strings without ``/``, ``\\`` or ``..``: they stand for
        the folder and file of a gallery folder); the image needs :data:`MIN_GALLERY_SIDE` px a side and a
        non-zero pixel. A plane of the same name replaces the old one.
        """
        _check_name(object, "object", f"add({object!r}, {plane!r}, ...)")
        _check_name(plane, "plane", f"add({object!r}, {plane!r}, ...)")
        rgb = _as_rgb(image, f"add({object!r}, {plane!r}, ...)")
        fitted, fit = fit_to_model(rgb, self.image_size, self.gallery_fill)
        canon_u8 = (fitted * 255.0).round().to(torch.uint8)
        problem = _gallery_image_problem(rgb.shape[:2], canon_u8)
        if problem is not None:
            raise MatlError(f"add({object!r}, {plane!r}, ...): the gallery image {problem}")
        with self._lock:
            features = self._embed_anchors(canon_u8[None])
            self._remove_plane(object, plane)
            self._planes.append(_Plane(str(object), str(plane), canon_u8, fit.model_H_file, rgb.shape[:2],
                                       str(image) if isinstance(image, (str, Path)) else None, features))
            self._changed()
        return self

    def _remove_plane(self, object: str, plane: str) -> None:
        self._planes = [p for p in self._planes if (p.object, p.name) != (object, plane)]

    def remove(self, object: str) -> Self:
        """Forget every plane of ``object``."""
        with self._lock:
            if object not in self.objects:
                raise MatlError(f"remove({object!r}): no such product; enrolled: {', '.join(self.objects) or 'none'}")
            self._planes = [p for p in self._planes if p.object != object]
            self._changed()
        return self

    def save(self, path: str | Path) -> None:
        """Write the enrolled gallery to ``path`` (plain tensors, written atomically): each plane's canonical
        image (uint8), its anchors' features and file geometry, and the open-set calibration (computed now if
        ``threshold="auto"`` and not yet done, so that a process that :meth:`load` s the file answers its first
        query without calibrating). Its size is linear in the planes: each tensor is saved on its own."""
        from matl.utils.io import atomic_write, check_output_file

        target = check_output_file(path, "save", overwrite=True, example="gallery.pt")
        with self._lock:
            samples = self._calibration_samples() if self.threshold_option == "auto" and self._planes else None
            planes = [{"object": p.object, "name": p.name, "canon_u8": p.canon_u8.clone(),
                       "canon_H_file": p.canon_H_file.clone(), "file_size": list(p.file_size), "path": p.path,
                       "features": p.features.clone()} for p in self._planes]  # clones: a view saves its whole base
            payload = {"format": GALLERY_FORMAT, "model_id": self.model_id, "image_size": self.image_size,
                       "num_anchors": self.num_anchors, "gallery_fill": self.gallery_fill, "planes": planes,
                       "calibration": None if samples is None else {k: (v.clone() if isinstance(v, torch.Tensor) else v)
                                                                    for k, v in samples.items()}}
            with atomic_write(target, "wb") as f:
                torch.save(payload, f)

    def load(self, path: str | Path) -> Self:
        """Replace the gallery by one written by :meth:`save` with the same model; refused otherwise. Its
        calibration is used while the gallery and the calibration options are the ones it was made with."""
        try:
            payload = torch.load(Path(path), map_location="cpu", weights_only=True)
        except FileNotFoundError:
            raise MatlError(f"{path}: no such gallery file") from None
        except Exception:  # torch's own message would advise weights_only=False: never
            raise MatlError(f"{path}: not a matl gallery file (torch cannot read it as plain tensors); pass a file "
                            "written by Recognizer.save") from None
        if not isinstance(payload, dict) or payload.get("format") not in READABLE_GALLERY_FORMATS:
            raise MatlError(f"{path}: not a matl gallery file of format {GALLERY_FORMAT}; pass a file written by "
                            "Recognizer.save")
        if payload.get("model_id") != self.model_id:
            raise MatlError(f"{path} was enrolled with another model ({str(payload.get('model_id'))[:12]}..., this one "
                            f"is {self.model_id[:12]}...): enrol the gallery again with this model")
        if payload.get("gallery_fill") != self.gallery_fill:
            raise MatlError(f"{path} was enrolled with gallery_fill={payload.get('gallery_fill')}, this recognizer "
                            f"uses {self.gallery_fill}")
        fields = {f.name for f in dataclasses.fields(_Plane)}  # format 1 also kept each plane's calibration copies
        with self._lock:
            self._planes = [_Plane(**{**{k: v for k, v in p.items() if k in fields},
                                      "file_size": tuple(p["file_size"])}) for p in payload["planes"]]
            self._changed()
            self._stored_calibration = payload.get("calibration") if isinstance(payload.get("calibration"), dict) \
                else None
        return self

