"""A keypoint baseline on image files: ``python -m matl.predict baseline=sift|sift_ecc ...``.

:class:`KeypointFileRecognizer` answers the calls :func:`matl.inference.files.predict` makes on
:class:`matl.Recognizer` (``enrol``, ``predict_details``, ``gallery``, ``plane_at``, ``planes``,
``threshold``, ``options``), so a baseline reads, frames and re-expresses its poses with exactly the
code MATL's files go through:

* *Enrol*: :func:`matl.inference.gallery.enrol_gallery` (no features): every gallery file resized with
  its aspect kept and centre-padded to the checkpoint's model size ``S`` (``gallery_fill``), rotated
  into the checkpoint's ``N`` fixed anchors (:class:`matl.data.gallery.Gallery`, as in training), and
  indexed once by the matcher.
* *Queries*: :func:`matl.data.image_files.fit_to_model` (``query_fill``), the matcher behind
  :class:`matl.baselines.recognizer.BaselineRecognizer`, and
  :func:`matl.data.image_files.pose_in_files` for ``H`` in the files' pixels.

A matcher has no open-set statistic: every matched query gets its product (a closed set); a query
no gallery image matched with ``min_inliers`` is answered ``object`` null, ``H`` null.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig

from matl.baselines.recognizer import BaselinePrediction, BaselineRecognizer, build_baseline
from matl.data.gallery import Gallery
from matl.data.image_files import fit_to_model, pose_in_files
from matl.inference.api import Match
from matl.inference.foreground import split_alpha
from matl.inference.gallery import EnrolledGallery, enrol_gallery
from matl.models.checkpoint import checkpoint_info, load_checkpoint
from matl.utils.errors import MatlError

__all__ = ["FilePlane", "KeypointFileRecognizer", "baseline_recognizer_from_config"]


class FilePlane:
    """An enrolled plane as :func:`matl.inference.files.plane_outline` reads it.

    Attributes:
        canon_u8: ``(3, S, S)`` uint8 canonical image at model size.
        canon_H_file: ``(3, 3)`` float64, gallery-file pixel -> model pixel.
    """

    def __init__(self, object: str, name: str, canon_u8: torch.Tensor, canon_H_file: torch.Tensor,
                 path: Path) -> None:
        self.object, self.name, self.canon_u8, self.canon_H_file, self.path = object, name, canon_u8, canon_H_file, path


class KeypointFileRecognizer:
    """A keypoint matcher over a gallery folder, answering like :class:`matl.Recognizer` (module docstring).

    Args:
        matcher: a :class:`matl.baselines.keypoints.KeypointMatcher` (``conf/baseline/<name>.yaml``).
        name: the baseline's name (``sift``, ``sift_ecc``, ...), reported by :meth:`options`.
        image_size, num_anchors: the model frame ``S`` and ``N`` the files are framed in (a checkpoint's).
        gallery_fill, query_fill: as predict's (:func:`matl.data.image_files.fit_geometry`).
        batch_size: query images per call of the matcher.
    """

    def __init__(self, matcher: Any, name: str, image_size: int, num_anchors: int, *, gallery_fill: float = 1.0,
                 query_fill: float = 1.0, batch_size: int = 64) -> None:
        self.matcher, self.name = matcher, str(name)
        self.image_size, self.num_anchors = int(image_size), int(num_anchors)
        self.gallery_fill, self.query_fill, self.batch_size = float(gallery_fill), float(query_fill), int(batch_size)
        self._enrolled: EnrolledGallery | None = None
        self._inner: BaselineRecognizer | None = None

    threshold = None  # no open-set statistic: a closed set

    def enrol(self, folder: str | Path, cache: bool = True) -> KeypointFileRecognizer:
        """Enrol ``<folder>/<object>/<plane>.{png,jpg}`` and index its anchors (``cache`` unused: no features)."""
        self._enrolled = enrol_gallery(folder, None, self.image_size, self.num_anchors, self.gallery_fill, None)
        self._inner = BaselineRecognizer(self.matcher, self._enrolled.gallery)
        return self

    def _require(self) -> tuple[EnrolledGallery, BaselineRecognizer]:
        if self._enrolled is None or self._inner is None:
            raise MatlError("the gallery is empty: enrol(folder) first")
        return self._enrolled, self._inner

    @property
    def gallery(self) -> Gallery:
        """The ``P * N`` anchors at model size (plane-major)."""
        return self._require()[0].gallery

    @property
    def planes(self) -> list[tuple[str, str]]:
        """``(object, plane)`` of every enrolled plane."""
        g = self.gallery
        return [(g.object_names[int(g.object_index[p * self.num_anchors])], g.plane_names[p])
                for p in range(len(g.plane_names))]

    def plane_at(self, index: int) -> FilePlane:
        """The enrolled plane of a prediction's ``plane_index``."""
        enrolled, _ = self._require()
        obj, name = self.planes[index]
        return FilePlane(obj, name, enrolled.canon_u8[index], enrolled.canon_H_file[index], enrolled.paths[index])

    def options(self) -> dict[str, Any]:
        """What the queries run with (for result files)."""
        return {"baseline": self.name, "search": None, "refine": False, "refiner": None, "quantize": "none",
                "quantize_fallback": None}

    def predict_details(self, arrays: list[np.ndarray]) -> tuple[list[Match], BaselinePrediction, torch.Tensor]:
        """Matches of float RGB ``(H, W, 3)`` or RGBA ``(H, W, 4)`` arrays (any size; alpha = mask), the
        model-frame prediction and the ``(B, 3, S, S)`` model-size queries, as
        :meth:`matl.Recognizer.predict_details`."""
        enrolled, inner = self._require()
        fitted = [fit_to_model(split_alpha(a)[0], self.image_size, self.query_fill) for a in arrays]
        queries = torch.stack([f[0] for f in fitted])
        query_H_file = torch.stack([f[1].model_H_file for f in fitted])
        pred = inner(queries)
        found = pred.plane_index >= 0
        plane = pred.plane_index.clamp_min(0)
        H = pose_in_files(pred.query_H_canon, enrolled.canon_H_file[plane], query_H_file)
        planes = self.planes
        matches = []
        for i in range(len(arrays)):
            if not bool(found[i]):
                matches.append(Match(None, None, -1, math.nan, math.nan, False, None, None, None))  # type: ignore[arg-type]
                continue
            p = int(plane[i])
            obj, name = planes[p]
            matches.append(Match(obj, name, int(pred.anchor_index[i]), math.nan, math.nan, True, H[i].numpy(), obj,
                                 name, str(enrolled.paths[p])))
        return matches, pred, queries


def baseline_recognizer_from_config(cfg: DictConfig, name: str) -> KeypointFileRecognizer:
    """The keypoint recognizer a predict config with ``baseline=<name>`` asks for (``S`` and ``N`` from ``ckpt``).

    Raises:
        MatlError: an option a keypoint baseline cannot honour (refinement, int8, a numeric open-set
            threshold), or a matcher that cannot be built.
    """
    if cfg.get("refine", False) is not False:
        raise MatlError(f"refine={cfg.get('refine')} does not apply to baseline={name}: refine is MATL's photometric "
                        "refinement (baseline=sift_ecc refines SIFT's poses by ECC)")
    if cfg.get("quantize", "none") != "none":
        raise MatlError(f"quantize={cfg.get('quantize')} does not apply to baseline={name}: use quantize=none")
    threshold = cfg.get("threshold", "auto")
    if threshold not in (None, "auto"):
        raise MatlError(f"threshold={threshold} does not apply to baseline={name}: a keypoint baseline has no "
                        "open-set statistic (use threshold=null)")
    ckpt = load_checkpoint(cfg.ckpt)
    size, num_anchors = checkpoint_info(ckpt, cfg.ckpt)
    del ckpt
    if cfg.get("image_size") is not None and int(cfg.image_size) != size:
        raise MatlError(f"checkpoint {cfg.ckpt} was trained at {size} px, not image_size={cfg.image_size}: the "
                        "model size always comes from the checkpoint (drop image_size=)")
    return KeypointFileRecognizer(build_baseline(cfg.baseline, name), name, size, num_anchors,
                                  gallery_fill=float(cfg.gallery_fill), query_fill=float(cfg.query_fill),
                                  batch_size=int(cfg.batch_size))
