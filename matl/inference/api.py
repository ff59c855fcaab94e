"""The Python API: enrol products, recognise camera crops (or answer "unknown"), pose in the caller's pixels.

>>> from matl import Recognizer
>>> rec = Recognizer.from_checkpoint("outputs/train/<time>/checkpoints/best.ckpt")
>>> rec.enrol("gallery/")                       # <gallery>/<object>/<plane>.png, no retraining
>>> rec.add("tea", "front", "tea_front.png")    # one more product at run time
>>> match = rec.predict(camera_crop)            # HxWx3 uint8 RGB, HxWx4 with alpha as the mask, a path
>>> match.object, match.known, match.H          # H: gallery image pixels -> crop pixels

A :class:`Recognizer` holds one model and one gallery. Every enrolled plane keeps its canonical
image at model size, its ``N`` anchors' features (computed once, when the plane is added) and the
matrix from its gallery image's pixels to the model frame, so poses come back in the pixels of the
images the caller gave: ``cv2.warpPerspective(gallery_img, match.H, (w, h))`` lands on the query.

Verification (``verify_top_k`` > 0, models with an STN): once a pose is known the query can be
compared with the anchor pixel by pixel (:mod:`matl.inference.verify`): warped into the anchor's
frame, its zero-mean normalised cross-correlation (ZNCC) with the anchor over the anchor's plane is
near 1 when the product and the pose are right. The nearest anchor is verified first; when ``1 -
ZNCC`` exceeds ``verify_max`` the next-nearest anchors (up to ``verify_top_k``, any product, plane
or rotation, each posed by the STN and the alignment stage) are tried in turn, and the first that
verifies becomes the answer (object, plane, anchor, ``H``); when none does, the nearest stays. The
query's empty pixels (all channels 0: the transparent part of an RGBA query) are not compared. With
``verify_statistic=patches`` (default) the comparison is over the part of the plane the query shows: its mask
(an RGBA alpha, the foreground step's) travels with it as its visibility, warped by the pose, and an
occluder the mask missed costs only the patches it covers; a pose that shows less than
``verify_min_visible`` of the plane does not verify. The refinement weighs the query's pixels by the same
visibility and knows how much each file was enlarged (:mod:`matl.inference.fast_refine`).

Open set: a query whose statistic exceeds :attr:`Recognizer.threshold` is answered ``known=False``
(``object`` None). The statistic (``open_set_statistic``) is ``verify`` (default): 0 when the
answer's pose verifies, else ``ratio``, so a verified answer is always known and the others are
judged by the ratio; ``verify_or_ratio``: the same values, calibrated as ``ratio`` (below);
``ratio``: the distance to the nearest anchor of the answer's product over the distance to the
nearest anchor of any *other* product (a query of an enrolled product is much closer to it than to
anything else; an unenrolled product is about as far from its two nearest products); or
``distance``: the answer's nearest-anchor distance itself. With ``threshold="auto"`` the threshold
is calibrated on the gallery alone (:func:`calibrate_open_set`): warped copies of every enrolled
plane (the training warps) are embedded (for ``verify`` also posed and verified as queries are, by
the model's poses without refinement); their statistic against the whole gallery is the *genuine*
sample, and against the gallery without their own product the *impostor* sample (what an
unenrolled product looks like). The threshold is the ``open_set_quantile`` quantile of the genuine
sample; ``score`` is the share of the impostor sample above the query's statistic. With ``verify``
the threshold is set by copies most of which verify, so it is strict on the ratio of the rest: a
query that fails verification (a camera's blur, noise or JPEG, a poor mask, a poor pose) must be
clearly nearer its product than any other; ``verify_or_ratio`` (with a lower quantile, e.g. 0.88)
keeps the ratio's own threshold for those, trading unknowns let through for known products kept.

Grey queries (``HxW`` arrays, grey files, or equal colour channels) are answered against the grey (luma)
twins of the enrolled planes, embedded and calibrated once at the first grey query: a grey crop can
only be recognised by what its product looks like in grey.

The calibration is kept: :meth:`Recognizer.save` stores its samples, and a gallery enrolled from a
folder with ``cache=True`` keeps them beside the features' cache
(:meth:`Recognizer.calibration_cache_file`), each keyed by the model, every plane's image and the
calibration options (:meth:`Recognizer.calibration_key`), so a new process answers its first query
without calibrating again.

One call at a time: the methods take a lock, so one recognizer can be shared by threads that take
turns; for parallel queries make one recognizer per thread (they share nothing global).
"""

from __future__ import annotations

import copy
import dataclasses
import functools
import logging
import threading
import zlib
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from matl.data.gallery import Gallery
from matl.data.image_files import fit_to_model, load_image_file, pose_in_files, read_rgba
from matl.geometry import HomographySampler, compose_query_H_canon, warp_image
from matl.inference.fast_refine import FastRefiner
from matl.inference.foreground import ForegroundStep, foreground_option, mask_query, pose_mask
from matl.inference.gallery import build_gallery, enrol_gallery, report_skipped
from matl.inference.quantize import calibration_images, quantize_recognizer
from matl.inference.refine import PhotometricRefiner, RefinedRecognizer
from matl.inference.runtime import RUNTIMES, runtime_path
from matl.inference.verify import VERIFY_STATISTICS, CandidatePose, Verification, verify_candidates
from matl.models.checkpoint import (
    PRETRAINED,
    PRETRAINED_FAST,
    SHIPPED,
    load_embedding_model,
    resolve_checkpoint_keyword,
    shipped_checkpoint,
)
from matl.models.prediction import Prediction
from matl.models.recognizer import TensorRecognizer, embed
from matl.models.search import ExactSearch, FaissSearch, SearchFactory
from matl.utils.errors import MatlError
from matl.utils.timing import StageTimer, stage

# the shipped models' names and paths are matl.models.checkpoint's (the one resolver of ckpt=), importable here too
__all__ = ["PRETRAINED", "PRETRAINED_FAST", "SHIPPED", "Match", "Recognizer", "calibrate_open_set",
           "load_embedding_model", "resolve_checkpoint_keyword", "shipped_checkpoint"]

_log = logging.getLogger(__name__)

OPEN_SET_STATISTICS = ("verify", "verify_or_ratio", "ratio", "distance")
VERIFY_CHUNK = 32  # queries verified together (each with up to verify_top_k candidates in one batch)
GALLERY_FORMAT = 2  # bump when save()'s content changes meaning (2: the calibration samples, no per-plane copies)
READABLE_GALLERY_FORMATS = (1, 2)
CALIBRATION_FORMAT = 1  # bump when the calibration's samples change meaning: cached ones then miss their key
CALIBRATION_PREFIX = ".matl_calibration_"
#: px: a gallery image whose shorter side is below this carries too little of the product to match
MIN_GALLERY_SIDE = 8
#: ITU-R BT.601 luma weights (OpenCV's and PIL's RGB -> grey): a grey query is matched against its gallery's grey
LUMA = (0.299, 0.587, 0.114)


@dataclass
class Match:
    """The answer for one query image.

    Attributes:
        object, plane: the recognised product and face; None when ``known`` is False.
        anchor: index ``k`` of the selected anchor (rotation ``k * 360 / N``) of the nearest plane.
        distance: L2 feature distance to that anchor.
        score: in [0, 1], the share of the calibration's impostor statistics above ``statistic`` (1:
            closer than any unenrolled product came in calibration); NaN without calibration.
        known: False when ``statistic`` exceeds the open-set threshold.
        H: ``(3, 3)`` float64 ``query_H_canon`` in pixels: gallery image of the plane -> the given query
            image (``H[2, 2] = 1``); None for models without an STN. Given for the nearest plane even
            when ``known`` is False.
        nearest_object, nearest_plane: the nearest plane's labels, also when ``known`` is False.
        statistic: the open-set statistic of the query (``open_set_statistic``: ``verify``, the distance
            ratio, or ``distance``), compared with the threshold.
        verification: ``1 - ZNCC`` of the query warped by ``H`` onto the answer's anchor (0: identical
            up to gain and bias per channel; 1: uncorrelated); NaN without verification.
        gallery_image: the gallery file of the plane (None for a plane added as an array).
        alternatives: the next-nearest *other* products (``top_k - 1`` of them), each as a Match of its
            nearest plane (``anchor`` -1, no ``H``, ``score`` NaN).
    """

    object: str | None
    plane: str | None
    anchor: int
    distance: float
    score: float
    known: bool
    H: np.ndarray | None
    nearest_object: str
    nearest_plane: str
    gallery_image: str | None = None
    alternatives: list[Match] = field(default_factory=list)
    statistic: float = float("nan")
    verification: float = float("nan")


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


def _search_factory(search: str | SearchFactory | None) -> SearchFactory:
    if search is None or search == "exact":
        return ExactSearch
    if search == "faiss":
        return FaissSearch
    if callable(search):
        return search
    raise MatlError(f"search={search!r} is invalid: use 'exact', 'faiss' or a search factory")


def _refiner(refine: bool | PhotometricRefiner | FastRefiner | None) -> PhotometricRefiner | FastRefiner | None:
    if refine is None or refine is False:
        return None
    if refine is True:
        return FastRefiner()  # conf/refiner/fast.yaml's defaults
    if isinstance(refine, (PhotometricRefiner, FastRefiner)):
        return refine
    raise MatlError(f"refine={refine!r} is invalid: use true, false, a PhotometricRefiner or a FastRefiner")


#: how far outside [0, 1] float pixels may stray (rounding of the caller's arithmetic) before it is a scale error
FLOAT_SLACK = 1.0 / 512.0  # half a step of 8 bits


def _as_rgb(image: Any, what: str, keep_alpha: bool = False) -> np.ndarray:
    """A query or gallery image as float32 ``(H, W, 3)`` RGB in [0, 1], transparent pixels set to 0; with
    ``keep_alpha`` an image with an alpha channel stays ``(H, W, 4)`` RGBA (alpha = mask).

    Arrays: ``HxWx3`` RGB, ``HxWx4`` RGBA, or grey ``HxW`` / ``HxWx1`` (replicated to 3 channels, as a grey
    file is); tensors: ``(3|4, H, W)``, or grey ``(H, W)`` / ``(1, H, W)``. ``uint8`` pixels are 0-255, float
    pixels 0-1: a float image with values above 1 (0-255 floats), below 0, NaN or infinite is refused in
    one line, never clipped into another picture.
    """
    if isinstance(image, (str, Path)):
        if keep_alpha:
            rgb, alpha = read_rgba(image)
            return rgb if alpha is None else np.ascontiguousarray(np.concatenate([rgb, alpha[..., None]], -1))
        return load_image_file(image)
    if image is None:
        raise MatlError(f"{what}: got None instead of an image (a path, an HxWx3 uint8 array or a tensor)")
    if isinstance(image, torch.Tensor):
        image = image.detach().cpu()
        if image.ndim == 3 and image.shape[0] == 1:
            image = image[0]
        if image.ndim == 3 and image.shape[0] in (3, 4):
            image = image.permute(1, 2, 0)
        elif image.ndim != 2:
            raise MatlError(f"{what}: a tensor image must be (3, H, W), (4, H, W) or grey (H, W), got "
                            f"{tuple(image.shape)}")
        image = image.numpy()
    array = np.asarray(image)
    if array.ndim == 3 and array.shape[-1] == 1:
        array = array[..., 0]
    if array.ndim == 2:
        array = np.repeat(array[..., None], 3, axis=-1)
    if array.ndim != 3 or array.shape[-1] not in (3, 4) or array.shape[0] == 0 or array.shape[1] == 0:
        raise MatlError(f"{what}: expected an HxWx3 RGB, HxWx4 RGBA or HxW grey image, got shape {array.shape}")
    if array.dtype == np.uint8:
        x = array.astype(np.float32) / 255.0
    elif array.dtype.kind == "f":
        x = array.astype(np.float32)
        if not np.isfinite(x).all():
            raise MatlError(f"{what}: {int((~np.isfinite(x)).sum())} pixel value(s) are NaN or infinite: "
                            "replace them (e.g. np.nan_to_num) before passing the image")
        low, high = float(x.min()), float(x.max())
        if high > 1.0 + FLOAT_SLACK or low < -FLOAT_SLACK:
            hint = "divide by 255 (or pass uint8)" if high > 1.0 + FLOAT_SLACK else "rescale them into [0, 1]"
            raise MatlError(f"{what}: float pixels must be in [0, 1], these span [{low:g}, {high:g}]: {hint}")
        x = np.clip(x, 0.0, 1.0)
    else:
        raise MatlError(f"{what}: expected uint8 (0-255) or float (0-1) pixels, got {array.dtype}")
    if x.shape[-1] == 4 and not keep_alpha:  # alpha is the segmentation mask: background becomes 0, as in training
        x = x[..., :3] * x[..., 3:4]
    return np.ascontiguousarray(x)


def _check_name(value: Any, kind: str, call: str) -> str:
    """``value`` if it is a usable object or plane name (it stands for a folder or file of a gallery folder)."""
    if (not isinstance(value, str) or not value.strip() or "/" in value or "\\" in value or ".." in value
            or any(ord(c) < 32 for c in value)):
        raise MatlError(f"{call}: {kind}={value!r} is not a name: use a non-empty string without '/', '\\', '..' or "
                        f"control characters, e.g. {'tea' if kind == 'object' else 'front'!r}")
    return value


def _gallery_image_problem(file_size: tuple[int, int], canon_u8: torch.Tensor) -> str | None:
    """Why a canonical image cannot be enrolled (too small, or nothing but background), or None."""
    if min(file_size) < MIN_GALLERY_SIDE:
        return (f"is {file_size[1]}x{file_size[0]} px: a gallery image needs at least {MIN_GALLERY_SIDE} px a side "
                "(a top-down photo or render of the face)")
    if not bool(canon_u8.any()):
        return "is empty (every pixel is 0, the background): nothing to recognise"
    return None


def _is_grey(image: np.ndarray) -> bool:
    """Whether an ``(H, W, 3|4)`` image's colour channels are equal everywhere (a grey image); a subsample first,
    so a colour image costs a few microseconds."""
    step = max(1, min(image.shape[:2]) // 16)
    few = image[::step, ::step]
    if not (np.array_equal(few[..., 0], few[..., 1]) and np.array_equal(few[..., 1], few[..., 2])):
        return False
    return bool(np.array_equal(image[..., 0], image[..., 1]) and np.array_equal(image[..., 1], image[..., 2]))


def _grey_u8(canon_u8: torch.Tensor) -> torch.Tensor:
    """``(3, S, S)`` uint8 canonical image -> its luma (:data:`LUMA`) in all three channels."""
    weights = torch.tensor(LUMA, dtype=torch.float32)[:, None, None]
    luma = (canon_u8.float() * weights).sum(0).round().clamp(0, 255).to(torch.uint8)
    return luma.expand(3, -1, -1).clone()


def _concat(a: Any, b: Any) -> Any:
    """Two tensors, or dataclasses of per-query tensors (:class:`Prediction`), one after the other (None stays)."""
    if isinstance(a, torch.Tensor):
        return torch.cat([a, b.to(a.device, a.dtype)])
    return dataclasses.replace(a, **{f.name: _concat(getattr(a, f.name), getattr(b, f.name))
                                     for f in dataclasses.fields(a) if getattr(a, f.name) is not None})


def _rows(value: Any, index: torch.Tensor) -> Any:
    """The rows ``index`` of a tensor or of each tensor of a dataclass of per-query tensors."""
    if isinstance(value, torch.Tensor):
        return value[index.to(value.device)]
    return dataclasses.replace(value, **{f.name: _rows(getattr(value, f.name), index)
                                         for f in dataclasses.fields(value) if getattr(value, f.name) is not None})


def _with_rows(value: Any, rows: list[int], source: Any, source_rows: list[int]) -> Any:
    """``value`` (a tensor, or a dataclass of per-query tensors such as :class:`Prediction`) with its rows ``rows``
    replaced by ``source``'s rows ``source_rows``; new tensors, fields that are None stay None."""
    if isinstance(value, torch.Tensor):
        out = value.clone()
        out[rows] = source[source_rows].to(out.device, out.dtype)
        return out
    return dataclasses.replace(value, **{
        f.name: _with_rows(getattr(value, f.name), rows, getattr(source, f.name), source_rows)
        for f in dataclasses.fields(value) if getattr(value, f.name) is not None})


def _query_visibility(prepared: list[tuple[np.ndarray, np.ndarray, np.ndarray | None]], size: int, fill: float,
                      device: torch.device) -> torch.Tensor | None:
    """``(B, 1, S, S)`` float in [0, 1]: the mask each query prepared by :func:`mask_query` was multiplied by (the
    foreground step's, or an RGBA query's alpha read back from its pixels), framed as the query is (0 where the
    frame holds no file pixel); None when no query has a mask."""
    masks: list[np.ndarray | None] = []
    for masked, rgb, found in prepared:
        if found is not None:
            masks.append(found)
        elif masked is rgb:  # used as given: no mask
            masks.append(None)
        else:  # masked = rgb * alpha; where a pixel is black its alpha is unknown (and it holds no data: 0)
            peak = rgb.max(-1)
            masks.append(np.where(peak > 0, masked.max(-1) / np.maximum(peak, 1e-12), 0.0).astype(np.float32))
    if all(m is None for m in masks):
        return None
    framed = [fit_to_model(torch.from_numpy(np.ones(rgb.shape[:2], np.float32) if m is None else
                                            np.clip(m, 0.0, 1.0).astype(np.float32))[None], size, fill)[0][:1]
              for m, (_, rgb, _) in zip(masks, prepared, strict=True)]
    return torch.stack(framed).to(device)


#: ``verify_statistic=patches``: the calibration's copies ``j`` (of each plane's ``calibration_warps``) with ``j % 4``
#: 1 get a grey bar drawn over them (a mask that kept the occluder), with ``j % 4`` 3 the bar's pixels set to 0 and
#: out of the visibility (a mask that left it out); hidden share of the plane uniform in this range
CALIBRATION_HIDDEN = (0.1, 0.5)


def _occluded_copies(images: torch.Tensor, names: list[str]) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The calibration's copies ``(P * W, 3, S, S)`` (plane-major, ``names`` one per plane) with a bar across half of
    them (:data:`CALIBRATION_HIDDEN`), the copies' visibility ``(P * W, 1, S, S)`` and the rows changed.

    A bar is a band across the whole frame at a random angle whose two edges are quantiles of the plane's pixels
    projected on its normal, so it hides the drawn share of the plane; its grey level is uniform in [0.15, 0.85]
    (drawn) or it is set to 0 (left out of the visibility). Seeded by each plane's name: the same copies each time.
    """
    per_plane = len(images) // max(len(names), 1)
    out, visibility = images.clone(), torch.ones_like(images[:, :1])
    S = images.shape[-1]
    ys, xs = torch.meshgrid(torch.arange(S, dtype=torch.float64), torch.arange(S, dtype=torch.float64), indexing="ij")
    rows = []
    for p, name in enumerate(names):
        g = torch.Generator().manual_seed(zlib.crc32(f"{name}/occluded".encode()))
        for j in range(per_plane):
            draws = torch.rand(4, generator=g, dtype=torch.float64)  # angle, hidden share, position, grey
            if j % 2 == 0:
                continue
            row = p * per_plane + j
            plane = images[row].amax(0) > 0
            if int(plane.sum()) < 16:
                continue
            angle = float(draws[0]) * torch.pi
            along = xs * np.cos(angle) + ys * np.sin(angle)
            low, high = CALIBRATION_HIDDEN
            share = low + (high - low) * float(draws[1])
            start = float(draws[2]) * (1.0 - share)
            edges = torch.quantile(along[plane], torch.tensor([start, start + share], dtype=torch.float64))
            bar = ((along >= edges[0]) & (along <= edges[1])).to(images.device)
            if j % 4 == 1:
                out[row][:, bar] = 0.15 + 0.7 * float(draws[3])
            else:
                out[row][:, bar] = 0.0
                visibility[row][:, bar] = 0.0
            rows.append(row)
    return out, visibility, torch.tensor(rows, dtype=torch.long)


def calibrate_open_set(genuine: torch.Tensor, impostor: torch.Tensor, quantile: float) -> float:
    """The open-set threshold: the ``quantile`` quantile of the genuine statistics.

    Args:
        genuine: ``(M,)`` statistics of warped gallery copies against the whole gallery.
        impostor: ``(M',)`` the same against the gallery without their own product (unused by the
            rule; kept so the trade-off can be reported beside it).
        quantile: in (0, 1].
    """
    if not 0.0 < quantile <= 1.0:
        raise MatlError(f"open_set_quantile={quantile} is invalid: use a fraction in (0, 1]")
    if len(genuine) == 0:
        return float("inf")
    return float(torch.quantile(genuine.double(), quantile))


class Recognizer:
    """Recognition and pose of camera crops against an enrolled gallery; see the module docstring.

    Args:
        model: an embedding model (``feature_net``, ``stn``, ``anchor_choice``), e.g. from
            :func:`load_embedding_model`.
        image_size, num_anchors: the model's ``S`` and ``N``.
        model_id: identifies the weights (the checkpoint's sha256); a saved gallery of another model
            is refused.
        device: ``cpu`` or ``cuda``.
        refine: photometric refinement of every pose (True: the default refiner,
            :class:`~matl.inference.fast_refine.FastRefiner` with ``conf/refiner/fast.yaml``'s settings, whose
            per-anchor data is computed once each time the gallery changes; or a configured
            ``FastRefiner`` or :class:`~matl.inference.refine.PhotometricRefiner`).
        quantize: ``none`` or ``int8`` (int8 convolutions for the query networks, float fallback).
        runtime: ``onnxruntime`` (default: ``s()``'s regressor and ``c()`` in onnxruntime, ``s()``'s warps in
            OpenCV, for CPU queries; :mod:`matl.inference.runtime`) or ``torch``. Falls back to torch, saying
            why in ``options()["runtime_fallback"]``, where it does not apply (a GPU, another model).
        search: ``exact`` (default), ``faiss`` or a search factory (:mod:`matl.models.search`).
        threshold: ``auto`` (calibrated on the gallery), a distance, or None (closed set: every
            query gets the nearest product).
        open_set_statistic: ``verify``, ``verify_or_ratio``, ``ratio`` or ``distance`` (see the module docstring).
        open_set_quantile: with ``auto``, the quantile of the genuine calibration sample used.
        calibration_warps: warped copies per plane for the calibration.
        verify_top_k: nearest anchors verified per query, until one verifies (0: no verification; then
            ``verify`` is ``ratio``). Models without an STN have no pose to verify: none.
        verify_max: the largest ``1 - ZNCC`` that verifies a pose.
        verify_blur: Gaussian smoothing of both images before the comparison, px.
        verify_refine: pose each further candidate by the fast refinement against it (``refiner.start``'s
            pose refined, :class:`~matl.inference.fast_refine.FastRefiner`: the recognizer's own with
            ``refine=`` a FastRefiner, else one with ``conf/refiner/fast.yaml``'s settings, whose per-anchor
            data is computed once per gallery when first needed) rather than by the STN and alignment stage
            alone; with ``refine=false`` the nearest anchor is posed and verified again that way when its
            own pose does not verify. A re-ranked answer then carries the refined pose.
        verify_statistic: ``patches`` (over the part of the anchor's plane the query shows, its mask warped
            by the pose: the lower of ``1 - ZNCC`` over it and a strict trimmed mean of per-patch ``1 - ZNCC``, so
            an occluder the mask missed costs only the patches it covers; half of the calibration's copies are
            partly occluded too) or ``global`` (one ZNCC over the plane, every copy whole);
            :mod:`matl.inference.verify`.
        verify_min_visible: ``patches``: an answer whose pose shows less than this share of the anchor's plane
            does not verify (judged by the ratio test).
        gallery_fill, query_fill: the fraction of the model frame an image's longer side takes
            (:func:`matl.data.image_files.fit_geometry`).
        batch_size: query images per forward pass.
        foreground: the foreground step of RGB queries without a mask (:mod:`matl.inference.foreground`):
            ``grabcut`` (default; a crop whose border is black is used as given), ``none`` (every RGB
            query used as given), ``learned`` (the visibility network; its soft probability
            ``foreground.probability(rgb)``) or a :class:`~matl.inference.foreground.GrabCutForeground` or
            :class:`~matl.inference.foreground.LearnedForeground`. An RGBA
            query always uses its alpha.
    """

    def __init__(self, model: nn.Module, image_size: int, num_anchors: int, model_id: str, *,
                 device: str = "cpu", refine: bool | PhotometricRefiner | FastRefiner | None = False,
                 quantize: str = "none", runtime: str = "onnxruntime",
                 search: str | SearchFactory | None = "exact", threshold: float | str | None = "auto",
                 open_set_statistic: str = "verify", open_set_quantile: float = 0.94, calibration_warps: int = 8,
                 verify_top_k: int = 8, verify_max: float = 0.1, verify_blur: float = 1.0,
                 verify_refine: bool = True, verify_statistic: str = "patches", verify_min_visible: float = 0.3,
                 gallery_fill: float = 1.0, query_fill: float = 1.0, batch_size: int = 64,
                 foreground: str | ForegroundStep | None = "grabcut") -> None:
        if quantize not in ("none", "int8"):
            raise MatlError(f"quantize={quantize!r} is invalid: use none or int8")
        if runtime not in RUNTIMES:
            raise MatlError(f"runtime={runtime!r} is invalid: use {' or '.join(RUNTIMES)}")
        if not (threshold is None or threshold == "auto" or isinstance(threshold, (int, float))):
            raise MatlError(f"threshold={threshold!r} is invalid: use auto, a distance or None (closed set)")
        if device == "auto":
            device = "cuda" if torch.cuda.is_available() else "cpu"
        self.model = model.to(device).eval()
        self.image_size, self.num_anchors, self.model_id = int(image_size), int(num_anchors), str(model_id)
        self.device = torch.device(device)
        self.refiner = _refiner(refine)
        self.quantize = quantize
        self.runtime = runtime
        self.search = _search_factory(search)
        self.threshold_option = threshold
        if open_set_statistic not in OPEN_SET_STATISTICS:
            raise MatlError(f"open_set_statistic={open_set_statistic!r} is invalid: use verify, verify_or_ratio, ratio "
                            "or distance")
        if isinstance(verify_top_k, bool) or not isinstance(verify_top_k, int) or verify_top_k < 0:
            raise MatlError(f"verify_top_k={verify_top_k!r} is invalid: use an integer >= 0 (0: no verification)")
        if isinstance(verify_max, bool) or not isinstance(verify_max, (int, float)) or not 0.0 <= verify_max <= 2.0:
            raise MatlError(f"verify_max={verify_max!r} is invalid: use a 1 - ZNCC level in [0, 2] (e.g. 0.1)")
        if isinstance(verify_blur, bool) or not isinstance(verify_blur, (int, float)) or not 0.0 <= verify_blur <= 10.0:
            raise MatlError(f"verify_blur={verify_blur!r} is invalid: use a Gaussian sigma in px in [0, 10]")
        if not isinstance(verify_refine, bool):
            raise MatlError(f"verify_refine={verify_refine!r} is invalid: use true or false")
        self.verify_refine = verify_refine
        if verify_statistic not in VERIFY_STATISTICS:
            raise MatlError(f"verify_statistic={verify_statistic!r} is invalid: use {' or '.join(VERIFY_STATISTICS)}")
        if (isinstance(verify_min_visible, bool) or not isinstance(verify_min_visible, (int, float))
                or not 0.0 <= verify_min_visible <= 1.0):
            raise MatlError(f"verify_min_visible={verify_min_visible!r} is invalid: use a share of the plane in [0, 1] "
                            "(e.g. 0.3)")
        self.verify_statistic, self.verify_min_visible = verify_statistic, float(verify_min_visible)
        self._verify_refiner: tuple[FastRefiner, Any] | None = None  # the candidates' refiner and its anchor data
        self.open_set_statistic = open_set_statistic
        self.verify_top_k, self.verify_max, self.verify_blur = int(verify_top_k), float(verify_max), float(verify_blur)
        self.open_set_quantile = float(open_set_quantile)
        self.calibration_warps = int(calibration_warps)
        self.gallery_fill, self.query_fill = float(gallery_fill), float(query_fill)
        self.batch_size = int(batch_size)
        self.foreground = foreground_option(foreground)
        self.quantize_fallback: str | None = None
        self.runtime_fallback: str | None = None
        self._runtime_path: Any = None  # runtime=onnxruntime's query path, built at the first query
        self._planes: list[_Plane] = []
        self._lock = threading.RLock()
        self._built: tuple[Any, Gallery] | None = None
        self._calibrated: tuple[float, torch.Tensor] | None = None  # (threshold, sorted impostor distances)
        #: samples of the open-set statistic with the key they were made under (calibration_key): from load(), the
        #: enrolment folder's cache or the last calibration
        self._stored_calibration: dict[str, Any] | None = None
        #: (folder, ids of the planes enrol() took from it): the calibration of exactly those planes is cached there
        self._calibration_folder: tuple[Path, list[int]] | None = None
        self._grey: Recognizer | None = None  # the same recognizer over its gallery's grey twins (grey queries)
        self._variant = "rgb"  # "grey" for that twin
        #: filled with each stage's milliseconds while set (:meth:`time_stages`); None: no timing, no cost
        self.stage_timer: StageTimer | None = None

    # -------------------------------------------------------------------------------- construction
    @classmethod
    def from_checkpoint(cls, path: str | Path, **options: Any) -> Recognizer:
        """A recognizer for a ``matl.train`` checkpoint (or ``pretrained`` / ``pretrained_fast``, the shipped
        models, as ``ckpt=`` names them); ``options`` as the constructor's."""
        model, size, num_anchors, sha = load_embedding_model(resolve_checkpoint_keyword(path), device="cpu")
        return cls(model, size, num_anchors, sha, **options).prepare()

    def prepare(self) -> Recognizer:
        """Make the query networks ready, whatever the gallery: the onnxruntime path exported and its sessions
        opened (``runtime=onnxruntime``), the compiled search and refinement kernels loaded (numba's cache).
        Part of loading a model (:meth:`from_checkpoint`, :meth:`pretrained`), so that the first query after
        :meth:`enrol` or :meth:`load` pays only for its gallery (docs/speed.md); otherwise done at that query."""
        with self._lock:
            want_runtime = (self.runtime == "onnxruntime" and self._runtime_path is None
                            and self.runtime_fallback is None and self.device.type == "cpu")
            if want_runtime or self.search is ExactSearch:  # a one-plane gallery of zeros: the networks' shapes
                blank = build_gallery(torch.zeros(1, 3, self.image_size, self.image_size, dtype=torch.uint8), [0],
                                      ["p"], ["o"], self.num_anchors).to(self.device)
                probe = TensorRecognizer(self.model.feature_net, self.model.stn, blank, self.model.anchor_choice,
                                         search=self.search, align=getattr(self.model, "align", None))
                if want_runtime:
                    self._runtime_path, self.runtime_fallback = runtime_path(probe)
            if isinstance(self.refiner, FastRefiner) or (self._verifying() and self.verify_refine):
                from matl.inference import fast_refine_kernels

                fast_refine_kernels.warm_up()
        return self

    @classmethod
    def pretrained(cls, name: str = "default", **options: Any) -> Recognizer:
        """A model shipped inside the package (loaded offline): ``default`` (with its alignment stage: the best
        pose without refinement) or ``fast`` (a cheaper s() whose pose the refinement sets: ``refine`` defaults
        to True for it; docs/speed.md)."""
        if name == "fast":
            options.setdefault("refine", True)
        return cls.from_checkpoint(shipped_checkpoint(name), **options)

    # ------------------------------------------------------------------------------------ gallery
    @property
    def objects(self) -> list[str]:
        """The enrolled products, in enrolment order."""
        return list(dict.fromkeys(p.object for p in self._planes))

    @property
    def planes(self) -> list[tuple[str, str]]:
        """``(object, plane)`` of every enrolled plane."""
        return [(p.object, p.name) for p in self._planes]

    def _embed_anchors(self, canon_u8: torch.Tensor) -> torch.Tensor:
        gallery = build_gallery(canon_u8, [0] * len(canon_u8), ["p"] * len(canon_u8), ["o"], self.num_anchors)
        return embed(self.model.feature_net, gallery.images.to(self.device)).cpu()

    def _changed(self) -> None:
        self._built = None
        self._calibrated = None
        self._verify_refiner = None
        self._grey = None

    def enrol(self, folder: str | Path, cache: bool = True) -> Recognizer:
        """Add every plane of a gallery folder ``<folder>/<object>/<plane>.{png,jpg}`` (features cached on disk,
        and with ``cache`` the open-set calibration too, beside them: :meth:`calibration_cache_file`). A file
        whose shorter side is below :data:`MIN_GALLERY_SIDE` px, or that is empty (every pixel 0), is reported
        and skipped."""
        with self._lock:
            enrolled = enrol_gallery(folder, self.model.feature_net, self.image_size, self.num_anchors,
                                     self.gallery_fill, self.model_id if cache else None)
            g, N = enrolled.gallery, self.num_anchors
            canon_u8 = enrolled.canon_u8
            added = []
            for p, path in enumerate(enrolled.paths):
                problem = _gallery_image_problem(tuple(int(v) for v in enrolled.file_sizes[p]), canon_u8[p])
                if problem is not None:
                    report_skipped(Path(path), problem)
                    continue
                obj = g.object_names[int(g.object_index[p * N])]
                self._remove_plane(obj, g.plane_names[p])
                added.append(_Plane(obj, g.plane_names[p], canon_u8[p].clone(), enrolled.canon_H_file[p].clone(),
                                    tuple(int(v) for v in enrolled.file_sizes[p]), str(path),
                                    enrolled.features[p * N:(p + 1) * N].clone()))
            if not added:
                raise MatlError(f"gallery={folder} holds no usable image (all were skipped): expected "
                                f"{folder}/<object>/<plane>.png of at least {MIN_GALLERY_SIDE} px a side")
            self._planes.extend(added)
            self._changed()
            folder_of_cache = enrolled.cache_file.parent if cache and enrolled.cache_file is not None else None
            self._calibration_folder = None if folder_of_cache is None else (folder_of_cache, [id(p) for p in added])
        return self

    def add(self, object: str, plane: str, image: Any) -> Recognizer:
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

    def remove(self, object: str) -> Recognizer:
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

    def load(self, path: str | Path) -> Recognizer:
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

    # ----------------------------------------------------------------------------------- queries
    def _build(self) -> tuple[Any, Gallery]:
        """The batch recognizer over the current planes (rebuilt after any gallery change)."""
        if self._built is not None:
            return self._built
        if not self._planes:
            raise MatlError("the gallery is empty: enrol(folder) or add(object, plane, image) first")
        objects = self.objects
        gallery = build_gallery(torch.stack([p.canon_u8 for p in self._planes]),
                                [objects.index(p.object) for p in self._planes], [p.name for p in self._planes],
                                objects, self.num_anchors).to(self.device)
        features = torch.cat([p.features for p in self._planes]).to(self.device)
        model = self.model
        recognizer = TensorRecognizer(model.feature_net, model.stn, gallery, model.anchor_choice,
                                      gallery_features=features, search=self.search,
                                      align=getattr(model, "align", None))
        if self.quantize == "int8":
            self.quantize_fallback = quantize_recognizer(recognizer, calibration_images(gallery.images))
        if self.runtime == "onnxruntime":  # the path depends on the networks only: built once, kept across galleries
            if self._runtime_path is None and self.runtime_fallback is None:
                self._runtime_path, self.runtime_fallback = runtime_path(recognizer)
            recognizer.onnx = self._runtime_path
        predictor = RefinedRecognizer(recognizer, self.refiner) if self.refiner is not None else recognizer
        self._built = (predictor, gallery)
        return self._built

    def _calibration_images(self, planes: list[_Plane]) -> torch.Tensor:
        """``(len(planes) * W, 3, S, S)`` the calibration's warped copies of ``planes`` (the training warps,
        seeded by each plane's name: the same copies every time), plane-major, on the recognizer's device."""
        options = getattr(self.model, "homography_config", None) or {}
        sampler = HomographySampler(**{k: v for k, v in dict(options).items() if k != "_target_"})
        size = (self.image_size, self.image_size)
        H = torch.cat([sampler.sample(self.calibration_warps, size, torch.Generator().manual_seed(
            zlib.crc32(f"{plane.object}/{plane.name}".encode()))) for plane in planes]).float()
        canon = torch.stack([p.canon_u8 for p in planes]).float().div(255.0)
        return warp_image(canon.repeat_interleave(self.calibration_warps, 0), H).to(self.device)

    def _calibration_features(self) -> None:
        """Features of warped copies of every plane that has none yet (the training warps; once per plane)."""
        missing = [p for p in self._planes if p.calibration is None]
        if not missing:
            return
        images = self._calibration_images(missing)
        inner = self._gallery_recognizer()
        features = torch.cat([inner.embed_queries(images[i:i + 256])[0] for i in range(0, len(images), 256)])
        for plane, chunk in zip(missing, features.float().cpu().split(self.calibration_warps), strict=True):
            plane.calibration = chunk

    def _gallery_recognizer(self) -> TensorRecognizer:
        """The batch recognizer without its refinement wrapper (its networks and gallery features)."""
        recognizer, _ = self._build()
        return getattr(recognizer, "recognizer", recognizer)

    def _plane_distances(self, features: torch.Tensor) -> torch.Tensor:
        """``(Q, P)`` distance of each feature to the nearest anchor of every enrolled plane (the gallery
        features the search uses: int8 ones with ``quantize=int8``)."""
        gallery = self._gallery_recognizer().gallery_features.double().cpu()
        d = torch.cdist(features.double().cpu(), gallery)  # (Q, G), anchors plane-major
        return d.view(len(features), len(self._planes), -1).min(2).values

    def _object_distances(self, features: torch.Tensor) -> tuple[torch.Tensor, list[str]]:
        """``(Q, O)`` distance of each feature to the nearest anchor of every product, and the products."""
        objects = self.objects
        by_plane = self._plane_distances(features)
        owner = torch.tensor([objects.index(p.object) for p in self._planes])
        out = torch.full((len(features), len(objects)), float("inf"), dtype=torch.float64)
        return out.scatter_reduce(1, owner.expand(len(features), -1), by_plane, reduce="amin"), objects

    def _verifying(self) -> bool:
        """Whether answers are verified (``verify_top_k`` > 0 and a model with an STN to give a pose)."""
        return self.verify_top_k > 0 and getattr(self.model, "stn", None) is not None

    def _verify(self, queries: torch.Tensor, first: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None = None,
                exclude_object: torch.Tensor | None = None, visibility: torch.Tensor | None = None,
                upscale: torch.Tensor | None = None) -> Verification:
        """:func:`~matl.inference.verify.verify_candidates` with this recognizer's settings, in chunks; the
        queries' empty (all-zero: transparent) pixels are left out of the comparison, and ``verify_statistic=patches``
        weighs the rest by the queries' ``visibility`` ``(Q, 1, S, S)`` (None: ones); ``upscale`` ``(Q,)``: each file's
        enlargement to the model's size, for the candidates' refinement."""
        inner, chunks, step = self._gallery_recognizer(), [], VERIFY_CHUNK
        pose = self._candidate_pose() if self.verify_refine else None
        first_refined = first is not None and self.refiner is not None
        for i in range(0, len(queries), step):
            part = None if first is None else tuple(t[i:i + step] for t in first)
            chunks.append(verify_candidates(inner, queries[i:i + step], self.verify_top_k, self.verify_max,
                                            self.verify_blur, part,
                                            None if exclude_object is None else exclude_object[i:i + step],
                                            skip_empty=True, candidate_pose=pose, first_refined=first_refined,
                                            visibility=None if visibility is None else visibility[i:i + step],
                                            upscale=None if upscale is None else upscale[i:i + step],
                                            statistic=self.verify_statistic, min_visible=self.verify_min_visible))
        return Verification(*(torch.cat([getattr(c, f.name) for c in chunks])
                              for f in dataclasses.fields(Verification)))

    def _candidate_refiner(self) -> tuple[FastRefiner, Any]:
        """The refiner of ``verify_refine``'s candidates and its per-anchor data, built when a candidate first needs
        it (once per gallery): a query whose nearest anchor verifies never waits for it."""
        if self._verify_refiner is None:
            recognizer, gallery = self._build()
            refiner = self.refiner if isinstance(self.refiner, FastRefiner) else FastRefiner()
            templates = getattr(recognizer, "templates", None) if refiner is self.refiner else None
            if templates is None:
                templates = refiner.anchor_templates(gallery.images)  # once per gallery
            self._verify_refiner = (refiner, templates)
        return self._verify_refiner

    def _candidate_pose(self) -> CandidatePose:
        """``verify_refine``'s poses of candidates: verified after the fast refinement against each (from
        ``refiner.start``'s pose); an answer carries that pose with ``refine=`` set, else the networks' own."""
        inner = self._gallery_recognizer()

        refined_answers = self.refiner is not None
        align = getattr(inner, "align", None)

        def pose(queries: torch.Tensor, index: torch.Tensor, stn_H: torch.Tensor, warped: torch.Tensor,
                 visibility: torch.Tensor | None = None, upscale: torch.Tensor | None = None
                 ) -> tuple[torch.Tensor, torch.Tensor]:
            refiner, templates = self._candidate_refiner()
            network = stn_H  # the pose the recognizer gives without refinement: s(), then the alignment stage
            compare = refiner.compare_align and refiner.start == "stn"  # the stage's pose kept where its loss is lower
            if align is not None and (refiner.start == "align" or not refined_answers or compare):
                network = align.infer(queries, inner.gallery.images[index], stn_H, warped).query_H_anchor
            start = network if refiner.start == "align" else stn_H
            others = network.double()[:, None] if compare and network is not stn_H else None
            refined = refiner(queries, index, start.double(), templates, visibility=visibility, upscale=upscale,
                              alternatives=others).query_H_anchor.to(stn_H.dtype)
            return refined, refined if refined_answers else network

        return pose

    def _statistic(self, nearest: torch.Tensor, second: torch.Tensor,
                   verified: torch.Tensor | None = None) -> torch.Tensor:
        if self.open_set_statistic == "distance":
            return nearest
        ratio = nearest / second.clamp_min(1e-12)
        if self.open_set_statistic in ("verify", "verify_or_ratio") and verified is not None:
            return torch.where(verified.cpu(), torch.zeros_like(ratio), ratio)
        return ratio

    def calibration(self) -> dict[str, torch.Tensor]:
        """Genuine and impostor samples of the open-set statistic (see the module docstring)."""
        with self._lock:
            self._calibration_features()
            features = torch.cat([p.calibration for p in self._planes])
            own = torch.tensor([self.objects.index(p.object) for p in self._planes
                                for _ in range(self.calibration_warps)])
            d, objects = self._object_distances(features)               # (M, O)
            # verify: the copies are posed and verified as queries are (against the whole gallery; the
            # impostors against the gallery without their product); verify_or_ratio: the ratio's samples
            images = (self._calibration_images(self._planes)
                      if self.open_set_statistic == "verify" and self._verifying() else None)
            visibility = None
            if images is not None and self.verify_statistic == "patches":  # a share of the copies partly hidden
                images, visibility, rows = _occluded_copies(images, [f"{p.object}/{p.name}" for p in self._planes])
                inner = self._gallery_recognizer()
                features = features.clone()
                features[rows] = torch.cat([inner.embed_queries(images[rows[i:i + 256]])[0].float().cpu()
                                            for i in range(0, len(rows), 256)])
                d, objects = self._object_distances(features)
            ranked = d.sort(1).values
            genuine_ok = None if images is None else self._verify(images, visibility=visibility).verified
            genuine = self._statistic(ranked[:, 0], ranked[:, 1] if len(objects) > 1 else ranked[:, 0], genuine_ok)
            impostor = torch.zeros(0, dtype=torch.float64)
            if len(objects) > 2:  # without its own product, a copy's nearest and second-nearest products
                impostor_ok = None if images is None else self._verify(images, None, own.to(self.device),
                                                                       visibility=visibility).verified
                others = d.scatter(1, own[:, None], float("inf")).sort(1).values
                impostor = self._statistic(others[:, 0], others[:, 1], impostor_ok)
            return {"genuine": genuine, "impostor": impostor}

    @property
    def threshold(self) -> float | None:
        """The open-set threshold on the statistic in force (None: closed set)."""
        with self._lock:
            if self.threshold_option is None:
                return None
            if self.threshold_option != "auto":
                return float(self.threshold_option)
            return self._calibrate()[0]

    def _calibrate(self) -> tuple[float, torch.Tensor]:
        if self._calibrated is None:
            samples = self._calibration_samples()
            threshold = calibrate_open_set(samples["genuine"], samples["impostor"], self.open_set_quantile)
            self._calibrated = (threshold, samples["impostor"].sort().values)
        return self._calibrated

    # ------------------------------------------------------------------------- the calibration, kept
    def calibration_key(self) -> str:
        """What the open-set samples (:meth:`calibration`) depend on: the model, every plane's name and canonical
        image, and the options that change the statistic (the statistic, the warps, verification and the
        refiner that poses candidates, the query path). ``open_set_quantile`` is not in it: the threshold is
        taken from the kept samples for any quantile."""
        import hashlib
        import json

        digest = hashlib.sha256()
        for plane in self._planes:
            digest.update(f"{plane.object}\0{plane.name}\0".encode())
            digest.update(plane.canon_u8.contiguous().numpy().tobytes())
        refiner = None if self.refiner is None else {k: v for k, v in vars(self.refiner).items()
                                                     if not k.startswith("_")}
        options = {"format": CALIBRATION_FORMAT, "model": self.model_id, "image_size": self.image_size,
                   "num_anchors": self.num_anchors, "statistic": self.open_set_statistic,
                   "warps": self.calibration_warps, "homography": getattr(self.model, "homography_config", None),
                   "verify": ([self.verify_top_k, self.verify_max, self.verify_blur, self.verify_refine,
                               self.verify_statistic, self.verify_min_visible] if self._verifying() else None),
                   "refiner": refiner, "quantize": self.quantize, "runtime": self.runtime,
                   "search": self.options()["search"], "device": self.device.type, "variant": self._variant}
        return json.dumps(options, sort_keys=True, default=str) + "|planes:" + digest.hexdigest()

    def calibration_cache_file(self) -> Path | None:
        """Where the calibration of a gallery enrolled from a folder (``enrol(folder, cache=True)``, nothing added
        or removed since) is kept: ``<folder>/.matl_calibration_<model>_<options>.pt``, beside the features'
        cache; None for any other gallery."""
        import hashlib

        if self._calibration_folder is None:
            return None
        folder, ids = self._calibration_folder
        if [id(p) for p in self._planes] != ids:
            return None
        options = hashlib.sha256(self.calibration_key().rsplit("|planes:", 1)[0].encode()).hexdigest()
        return folder / f"{CALIBRATION_PREFIX}{self.model_id[:16]}_{options[:16]}.pt"  # one per model and options

    def _calibration_samples(self) -> dict[str, Any]:
        """``{"key", "genuine", "impostor"}`` of the current gallery and options: the kept samples when their key
        is this one (from :meth:`load` or the enrolled folder's cache), else :meth:`calibration`'s, kept (and
        written beside an enrolled folder)."""
        key = self.calibration_key()
        stored = self._stored_calibration
        if stored is None or stored.get("key") != key:
            stored = self._read_calibration_cache(key)
        if stored is None:
            samples = self.calibration()
            stored = {"key": key, "genuine": samples["genuine"], "impostor": samples["impostor"]}
            self._write_calibration_cache(stored)
        self._stored_calibration = stored
        return stored

    def _read_calibration_cache(self, key: str) -> dict[str, Any] | None:
        path = self.calibration_cache_file()
        if path is None or not path.is_file():
            return None
        try:
            payload = torch.load(path, map_location="cpu", weights_only=True)
        except Exception as error:  # a corrupt cache is never fatal: it is rebuilt
            _log.warning("calibration cache %s is unreadable (%s); calibrating again", path,
                         " ".join(str(error).split()))
            return None
        if (not isinstance(payload, dict) or payload.get("key") != key
                or not all(isinstance(payload.get(k), torch.Tensor) for k in ("genuine", "impostor"))):
            return None
        _log.info("open-set calibration loaded from %s", path)
        return payload

    def _write_calibration_cache(self, samples: dict[str, Any]) -> None:
        from matl.utils.io import atomic_write

        path = self.calibration_cache_file()
        if path is None:
            return
        try:
            with atomic_write(path, "wb") as f:
                torch.save(samples, f)
        except OSError as error:  # a read-only gallery folder only costs a warning
            _log.warning("cannot write the calibration cache %s (%s); it will be recomputed next time", path, error)

    # ----------------------------------------------------------------------------- grey queries
    def _grey_twin(self) -> Recognizer:
        """This recognizer over the grey (luma) twins of its planes, for grey queries: a grey crop is compared
        with what its product looks like in grey, not with colours it cannot show. Built at the first grey
        query (its anchors' features, once) and calibrated as this one; self when every plane is grey."""
        if self._variant == "grey":
            return self
        if self._grey is None:
            if all(bool((p.canon_u8[0] == p.canon_u8[1]).all() and (p.canon_u8[1] == p.canon_u8[2]).all())
                   for p in self._planes):
                return self
            twin = copy.copy(self)
            grey = torch.stack([_grey_u8(p.canon_u8) for p in self._planes])
            features = self._embed_anchors(grey).split(self.num_anchors)
            twin._planes = [dataclasses.replace(p, canon_u8=g, features=f.clone(), calibration=None)
                            for p, g, f in zip(self._planes, grey, features, strict=True)]
            twin._variant, twin._grey = "grey", None
            twin._built = twin._calibrated = twin._verify_refiner = twin._stored_calibration = None
            same_folder = self.calibration_cache_file() is not None
            twin._calibration_folder = ((self._calibration_folder[0], [id(p) for p in twin._planes])
                                        if same_folder else None)
            self._grey = twin
        return self._grey

    def _predict_routed(self, arrays: list[np.ndarray], top_k: int = 1
                        ) -> tuple[list[Match], Prediction, torch.Tensor]:
        """:meth:`_predict_arrays`, grey queries (equal colour channels) answered by :meth:`_grey_twin`; the
        answers in the given order (the twin's planes, anchors and objects are this gallery's, in its order)."""
        grey = [i for i, a in enumerate(arrays) if _is_grey(a)]
        twin = self._grey_twin() if grey and self._planes else self
        if twin is self:
            return self._predict_arrays(arrays, top_k)
        if len(grey) == len(arrays):
            return twin._predict_arrays(arrays, top_k)
        colour = [i for i in range(len(arrays)) if i not in set(grey)]
        first = self._predict_arrays([arrays[i] for i in colour], top_k)
        second = twin._predict_arrays([arrays[i] for i in grey], top_k)
        order = torch.argsort(torch.tensor(colour + grey))  # row i of the result: row order[i] of the concatenation
        matches = [*first[0], *second[0]]
        return ([matches[int(i)] for i in order], _rows(_concat(first[1], second[1]), order),
                _rows(_concat(first[2], second[2]), order))

    def _score(self, statistic: float) -> float:
        if self.threshold_option is None or not self._planes:
            return float("nan")
        impostor = self._calibrate()[1]
        if len(impostor) == 0:
            return float("nan")
        farther = len(impostor) - int(torch.searchsorted(impostor, torch.tensor([statistic], dtype=impostor.dtype)))
        return farther / len(impostor)

    def predict_tensor(self, queries: torch.Tensor) -> Prediction:
        """The model-frame prediction for ``(B, 3, S, S)`` images already at model size (no pose in files)."""
        with self._lock:
            recognizer, _ = self._build()
            return recognizer(queries.to(self.device))

    @property
    def gallery(self) -> Gallery:
        """The model-frame gallery of every enrolled plane's ``N`` anchors (plane-major)."""
        with self._lock:
            return self._build()[1]

    def plane_at(self, index: int) -> _Plane:
        """The enrolled plane of a prediction's ``plane_index``."""
        return self._planes[index]

    def options(self) -> dict[str, Any]:
        """What the queries run with (for result files): search, refinement, quantisation, runtime."""
        refiner = None
        if self.refiner is not None:
            refiner = {k: v for k, v in vars(self.refiner).items() if not k.startswith("_")}
        name = getattr(self.search, "func", self.search)
        return {"search": "faiss" if name is FaissSearch else "exact" if name is ExactSearch else str(name),
                "refine": self.refiner is not None, "refiner": refiner, "quantize": self.quantize,
                "foreground": None if self.foreground is None else dataclasses.asdict(self.foreground),
                "quantize_fallback": self.quantize_fallback,
                "runtime": "torch" if self.runtime_fallback else self.runtime,
                "runtime_fallback": self.runtime_fallback}

    def time_stages(self, timer: StageTimer | None) -> None:
        """Fill ``timer`` (:class:`matl.utils.timing.StageTimer`) with the milliseconds of each stage of the calls
        that follow: ``foreground``, ``framing`` (to the model frame), ``networks``, ``search``, ``alignment``,
        ``refinement``, ``verification`` (the further candidates' networks and poses included) and ``retries``
        (``foreground.retry_insets``: everything a retried query runs again); None stops it and leaves no cost.
        Time the stages after enrolling: a gallery changed afterwards is answered untimed inside the networks."""
        with self._lock:
            if self.stage_timer is not None:
                self.stage_timer.unwrap()
            self.stage_timer = timer
            if timer is None:
                return
            predictor, _ = self._build()
            inner = self._gallery_recognizer()
            timer.wrap(inner, "embed_queries", "networks")
            timer.wrap(inner.search, "search", "search")
            if getattr(inner, "align", None) is not None:
                timer.wrap(inner.align, "infer", "alignment")
            if predictor is not inner:
                timer.wrap(predictor, "refiner", "refinement")

    def predict_details(self, arrays: list[np.ndarray]) -> tuple[list[Match], Prediction, torch.Tensor]:
        """:meth:`predict` for float RGB ``(H, W, 3)`` or RGBA ``(H, W, 4)`` arrays in [0, 1] (alpha = mask),
        plus the model-frame prediction and the model-size query images it came from (for pictures and
        diagnostics)."""
        with self._lock:
            return self._predict_routed(arrays)

    def predict(self, images: Any, top_k: int = 1) -> Match | list[Match]:
        """Recognise one image or a batch; see :class:`Match`.

        Args:
            images: a path, an ``HxWx3`` RGB / ``HxWx4`` RGBA / ``HxW`` grey array (any size; uint8 0-255 or
                float 0-1), a ``(3|4, H, W)`` or ``(H, W)`` tensor, a list of those, or a ``(B, 3, H, W)`` tensor.
                A grey image (equal colour channels) is matched against the grey twins of the enrolled
                planes. Float pixels outside [0, 1], NaN or infinite are a one-line error.
            top_k: also return the ``top_k - 1`` next-nearest other planes in ``Match.alternatives``.
        Returns:
            One :class:`Match` for a single image, else a list in the given order.
        """
        single = not (isinstance(images, (list, tuple)) or (isinstance(images, torch.Tensor) and images.ndim == 4))
        items: Sequence[Any] = [images] if single else list(images)
        if top_k < 1:
            raise MatlError(f"top_k={top_k} is invalid: use an integer >= 1")
        matches: list[Match] = []
        with self._lock:
            for start in range(0, len(items), self.batch_size):
                chunk = [_as_rgb(x, f"image {start + i}", keep_alpha=True)
                         for i, x in enumerate(items[start:start + self.batch_size])]
                matches.extend(self._predict_routed(chunk, top_k)[0])
        return matches[0] if single else matches

    def _predict_arrays(self, arrays: list[np.ndarray], top_k: int = 1
                        ) -> tuple[list[Match], Prediction, torch.Tensor]:
        """Matches of float RGB ``(H, W, 3)`` arrays, the model-frame prediction they came from and the
        model-size queries."""
        recognizer, _ = self._build()
        with stage(self.stage_timer, "foreground"):
            prepared = [mask_query(self.foreground, a) for a in arrays]  # (masked, rgb, alpha found or None)
        pred, queries, query_H_file, verification = self._answer(recognizer, prepared)
        if verification is not None and self.foreground is not None and self.foreground.retrying:
            with stage(self.stage_timer, "retries"):
                pred, queries, verification = self._foreground_retries(recognizer, prepared, pred, queries,
                                                                       verification)
        plane = pred.plane_index.cpu()
        canon_H_file = torch.stack([p.canon_H_file for p in self._planes])
        H = None
        if pred.query_H_canon is not None:
            H = pose_in_files(pred.query_H_canon.cpu(), canon_H_file[plane], query_H_file)
        threshold = self.threshold
        features = pred.features  # c(s(query)), as the search used it: per-product distances
        if features is None:
            features = embed(self.model.feature_net, pred.warped)
        by_object, objects = self._object_distances(features)
        own = torch.tensor([objects.index(self._planes[int(p)].object) for p in plane])
        nearest = by_object.gather(1, own[:, None])[:, 0]
        second = by_object.scatter(1, own[:, None], float("inf")).min(1).values
        statistic = self._statistic(nearest, second if len(objects) > 1 else nearest,
                                    None if verification is None else verification.verified)
        alternatives = self._alternatives(features, own, top_k)
        matches = []
        for i in range(len(arrays)):
            matches.append(self._match(int(plane[i]), int(pred.anchor_index[i]), float(pred.distance[i]),
                                       float(statistic[i]), None if H is None else H[i].numpy(), threshold,
                                       alternatives[i],
                                       float("nan") if verification is None else float(verification.distance[i])))
        return matches, pred, queries

    def _answer(self, recognizer: Any, prepared: list[tuple[np.ndarray, np.ndarray, np.ndarray | None]]
                ) -> tuple[Prediction, torch.Tensor, torch.Tensor, Verification | None]:
        """The verified model-frame answer of queries prepared by :func:`mask_query`: the prediction (re-ranked
        by verification), the model-size queries ``(B, 3, S, S)`` of the last foreground pass, ``model_H_file``
        ``(B, 3, 3)`` and the verification (None without one)."""
        with stage(self.stage_timer, "framing"):
            fitted = [fit_to_model(masked, self.image_size, self.query_fill) for masked, _, _ in prepared]
            queries = torch.stack([f[0] for f in fitted]).to(self.device)
        query_H_file = torch.stack([f[1].model_H_file for f in fitted])
        visibility = _query_visibility(prepared, self.image_size, self.query_fill, self.device)
        upscale = (query_H_file[:, 0, 0] * query_H_file[:, 1, 1]).sqrt()  # model px per file px
        pred, queries = self._foreground_passes(recognizer, queries, [p[1] for p in prepared],
                                                [p[2] for p in prepared], visibility, upscale)
        verification = None
        if self._verifying() and pred.query_H_anchor is not None:
            with stage(self.stage_timer, "verification"):
                verification = self._verify(queries, (pred.gallery_index, pred.query_H_anchor, pred.distance),
                                            visibility=visibility, upscale=upscale)
                pred = self._reranked(pred, verification)
        return pred, queries, query_H_file, verification

    def _foreground_retries(self, recognizer: Any, prepared: list[tuple[np.ndarray, np.ndarray, np.ndarray | None]],
                            pred: Prediction, queries: torch.Tensor, verification: Verification
                            ) -> tuple[Prediction, torch.Tensor, Verification]:
        """``foreground.retry_insets``: each GrabCut-masked query whose answer does not verify is masked again by
        GrabCut from wider insets (:meth:`GrabCutForeground.retries`; ``foreground=learned``: at other thresholds,
        ``retry_thresholds``) and answered again; it keeps the answer
        whose verification distance is lowest (its first one on a tie). The file frame does not change (a mask
        keeps the crop's size)."""
        retried: list[int] = []
        again: list[tuple[np.ndarray, np.ndarray, np.ndarray | None]] = []
        for i, (_, rgb, found) in enumerate(prepared):
            if found is None or bool(verification.verified[i]):
                continue
            with stage(self.stage_timer, "foreground"):
                masks = self.foreground.retries(rgb)
            for mask in masks:
                retried.append(i)
                again.append((np.ascontiguousarray(rgb * mask[..., None]), rgb, mask))
        if not again:
            return pred, queries, verification
        alt_pred, alt_queries, _, alt_verification = self._answer(recognizer, again)
        best = verification.distance.clone()
        take: dict[int, int] = {}
        for j, i in enumerate(retried):
            if float(alt_verification.distance[j]) < float(best[i]):
                best[i], take[i] = alt_verification.distance[j], j
        if not take:
            return pred, queries, verification
        rows, source = list(take), list(take.values())
        return (_with_rows(pred, rows, alt_pred, source), _with_rows(queries, rows, alt_queries, source),
                _with_rows(verification, rows, alt_verification, source))

    def _reranked(self, pred: Prediction, verification: Verification) -> Prediction:
        """``pred`` with the verified answer where it differs from the nearest anchor (other rows unchanged)."""
        device = pred.gallery_index.device
        index = verification.gallery_index.to(device)
        changed = index != pred.gallery_index
        if not bool(changed.any()):
            return pred
        g = self.gallery
        rows = changed[:, None, None]
        query_H_anchor = torch.where(rows, verification.query_H_anchor.to(device, pred.query_H_anchor.dtype),
                                     pred.query_H_anchor)
        query_H_canon = torch.where(rows, compose_query_H_canon(query_H_anchor.double(),
                                                                g.anchor_H_canon64()[index]), pred.query_H_canon)
        distance = torch.where(changed, verification.feature_distance.to(device, pred.distance.dtype), pred.distance)
        return dataclasses.replace(pred, gallery_index=index, object_index=g.object_index[index],
                                   plane_index=g.plane_index[index], anchor_index=g.anchor_index[index],
                                   distance=distance, query_H_anchor=query_H_anchor, query_H_canon=query_H_canon)

    def _foreground_passes(self, recognizer: Any, queries: torch.Tensor, rgbs: list[np.ndarray],
                           found: list[np.ndarray | None], visibility: torch.Tensor | None = None,
                           upscale: torch.Tensor | None = None) -> tuple[Prediction, torch.Tensor]:
        """The prediction of ``(B, 3, S, S)`` queries after the foreground step's pose passes, and the queries
        of the last pass: a query whose alpha came from the foreground step (``found[i]`` ``(H, W)``, None
        otherwise) is masked again by its answered plane warped by its pose, within that alpha
        (:mod:`matl.inference.foreground`). Earlier passes skip the refinement, which weighs the query's pixels by
        ``visibility`` ``(B, 1, S, S)`` and takes each file's enlargement ``upscale`` ``(B,)``."""
        if isinstance(recognizer, RefinedRecognizer):
            recognizer = functools.partial(recognizer, visibility=visibility, upscale=upscale)
        passes = 0 if self.foreground is None or all(f is None for f in found) else int(self.foreground.passes)
        if passes == 0:
            return recognizer(queries), queries
        redo = torch.tensor([f is not None for f in found], device=queries.device)[:, None, None, None]
        raw = torch.stack([fit_to_model(rgb, self.image_size, self.query_fill)[0] for rgb in rgbs])
        ones = [np.ones(rgb.shape[:2], np.float32) if f is None else f for rgb, f in zip(rgbs, found, strict=True)]
        alpha = torch.stack([fit_to_model(np.repeat(a[..., None], 3, -1), self.image_size, self.query_fill)[0][:1]
                             for a in ones])
        within = (raw * alpha).to(queries.device)  # (B, 3, S, S): the query inside the foreground step's alpha
        inner = self._gallery_recognizer()
        canon = torch.stack([p.canon_u8 for p in self._planes]).to(queries.device)
        for _ in range(passes):
            pred = inner(queries)
            if pred.query_H_canon is None:  # a model without a pose: the foreground step's alpha alone
                break
            outline = pose_mask(canon[pred.plane_index.to(queries.device)], pred.query_H_canon.to(queries.device),
                                self.image_size)
            queries = torch.where(redo, within * outline, queries)
        return recognizer(queries), queries

    def _match(self, plane: int, anchor: int, distance: float, statistic: float, H: np.ndarray | None,
               threshold: float | None, alternatives: list[Match], verification: float = float("nan")) -> Match:
        p = self._planes[plane]
        known = threshold is None or statistic <= threshold
        return Match(p.object if known else None, p.name if known else None, anchor, distance,
                     self._score(statistic), known, H, p.object, p.name, p.path, alternatives, statistic,
                     verification)

    def _alternatives(self, features: torch.Tensor, own: torch.Tensor, top_k: int) -> list[list[Match]]:
        """The ``top_k - 1`` next-nearest other products of each query, each by its nearest plane (no pose)."""
        if top_k <= 1:
            return [[] for _ in range(len(own))]
        by_plane = self._plane_distances(features)
        objects = self.objects
        out = []
        for i in range(len(own)):
            seen = {int(own[i])}
            matches = []
            for k in torch.argsort(by_plane[i]).tolist():
                plane = self._planes[k]
                if objects.index(plane.object) in seen:
                    continue
                seen.add(objects.index(plane.object))
                d = float(by_plane[i, k])
                matches.append(Match(plane.object, plane.name, -1, d, float("nan"), True, None, plane.object,
                                     plane.name, plane.path))
                if len(matches) == top_k - 1:
                    break
            out.append(matches)
        return out
