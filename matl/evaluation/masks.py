"""The quality of a foreground step's masks: intersection over union with the true visible mask, and its cost.

A foreground step (:mod:`matl.inference.foreground`: ``grabcut``, ``learned``) gives an RGB crop the
mask of its target product's visible print. Two sources of truth:

* :func:`score_condition`: a condition folder of ``python -m matl.unseen`` (``<out>/<condition>/``), whose
  ``truth.jsonl`` names each query's true mask (``mask_file``: ``masks/<stem>.png``, 255 where the target's
  visible coverage is above 0.5). The held-out benchmark: measured on, never tuned on.
* :func:`score_scenes`: scenes of :class:`matl.data.scenes.SceneMaker` made from a validation catalog
  (e.g. ``synthetic_ycb``), whose truth is the scene's visible coverage above 0.5; what settings are
  chosen on.

Each query is masked as the recognizer masks it (:func:`matl.inference.foreground.mask_query`): an RGB
crop by the step, an RGBA crop's alpha refined by the step (``use_alpha=False`` masks the RGB of every
crop by the step, the alpha ignored). A crop the step leaves whole (an all-ones mask) scores as that
mask. ``ms_per_crop`` is the median wall time of the step on one crop, one thread (torch's and OpenCV's).
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from matl.utils.errors import MatlError

__all__ = ["compare_steps", "mask_iou", "score_condition", "score_masks", "score_scenes"]

Crop = tuple[np.ndarray, np.ndarray]  # (image (H, W, 3) RGB or (H, W, 4) RGBA float32 in [0, 1], truth (H, W) bool)


def mask_iou(found: np.ndarray, truth: np.ndarray) -> float:
    """Intersection over union of a mask ``(H, W)`` (above 0.5) with a true mask ``(H, W)`` bool (1 when both are
    empty)."""
    a, b = found > 0.5, truth.astype(bool)
    union = int((a | b).sum())
    return 1.0 if union == 0 else float((a & b).sum() / union)


def mask_precision_recall(found: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    """The share of a mask's pixels ``(H, W)`` (above 0.5) that the true mask ``(H, W)`` bool holds (precision: 1
    when the mask is empty) and of the true pixels it holds (recall: 1 when the truth is empty): which of a mask's
    two errors it makes (an occluder or the floor taken for the product, print left out)."""
    a, b = found > 0.5, truth.astype(bool)
    both = float((a & b).sum())
    return (both / float(a.sum()) if a.any() else 1.0), (both / float(b.sum()) if b.any() else 1.0)


def _masked(step: Any, image: np.ndarray, use_alpha: bool) -> np.ndarray:
    """The mask ``(H, W)`` the recognizer uses for ``image`` with the foreground step ``step`` (None: no step), as
    :func:`matl.inference.foreground.mask_query` makes it: an RGBA crop's alpha refined by the step, an RGB crop's
    mask found by the step."""
    rgb = np.ascontiguousarray(image[..., :3], dtype=np.float32)
    if use_alpha and image.shape[-1] == 4:
        alpha = np.ascontiguousarray(image[..., 3], dtype=np.float32)
        return alpha if step is None else step.refine_alpha(rgb, alpha)
    return np.ones(rgb.shape[:2], np.float32) if step is None else step(rgb)


def score_masks(step: Any, crops: Iterable[Crop], use_alpha: bool = True, warmup: int = 3) -> dict[str, Any]:
    """IoU of ``step``'s masks of ``crops`` with their truths, and the step's milliseconds per crop.

    Returns:
        ``{"iou": mean, "iou_median", "iou_p10": 10 % quantile, "precision", "recall": means
        (:func:`mask_precision_recall`), "queries", "ms_per_crop": median, "per_query": [IoU, ...]}``.
    """
    from matl.utils.timing import compute_threads

    ious, times, shares = [], [], []
    with compute_threads(1):
        for i, (image, truth) in enumerate(crops):
            if i < warmup:  # untimed calls first: sessions and kernels are built at the first call
                _masked(step, image, use_alpha)
            start = time.perf_counter()
            found = _masked(step, image, use_alpha)
            times.append(time.perf_counter() - start)
            ious.append(mask_iou(found, truth))
            shares.append(mask_precision_recall(found, truth))
    if not ious:
        raise MatlError("no crop to score: the folder's truth.jsonl names no mask_file")
    values = np.asarray(ious)
    return {"iou": round(float(values.mean()), 4), "iou_median": round(float(np.median(values)), 4),
            "iou_p10": round(float(np.quantile(values, 0.1)), 4),
            "precision": round(float(np.mean([p for p, _ in shares])), 4),
            "recall": round(float(np.mean([r for _, r in shares])), 4), "queries": len(values),
            "ms_per_crop": round(1000.0 * float(np.median(times)), 3), "per_query": [round(v, 4) for v in ious]}


def condition_crops(folder: str | Path, limit: int | None = None, truth: str = "truth.jsonl") -> list[Crop]:
    """The query crops of a ``matl.unseen`` condition folder and their true masks (``mask_file`` of the truth file
    ``truth``: ``truth.jsonl``, or e.g. ``truth_rgb.jsonl``, the RGB files of ``occluded``).

    Raises:
        MatlError: no such truth file, or one without ``mask_file`` entries.
    """
    from matl.data.image_files import read_rgba

    folder = Path(folder)
    truth_file = folder / truth
    if not truth_file.is_file():
        raise MatlError(f"{folder}: no {truth}: give a condition folder written by python -m matl.unseen")
    crops: list[Crop] = []
    for line in truth_file.read_text().splitlines():
        if not line.strip():
            continue
        record = json.loads(line)
        if not record.get("mask_file"):
            continue
        rgb, alpha = read_rgba(folder / record["image"])
        image = rgb if alpha is None else np.concatenate([rgb, alpha[..., None]], -1)
        truth = cv2.imread(str(folder / record["mask_file"]), cv2.IMREAD_GRAYSCALE)
        if truth is None:
            raise MatlError(f"{folder / record['mask_file']}: the true mask cannot be read")
        crops.append((np.ascontiguousarray(image, dtype=np.float32), truth > 127))
        if limit is not None and len(crops) >= limit:
            break
    if not crops:
        raise MatlError(f"{truth_file} names no mask_file: re-run python -m matl.unseen, which writes the true masks")
    return crops


def score_condition(folder: str | Path, step: Any, use_alpha: bool = True, limit: int | None = None,
                    truth: str = "truth.jsonl") -> dict[str, Any]:
    """:func:`score_masks` of ``step`` on a ``matl.unseen`` condition folder's queries (:func:`condition_crops`)."""
    return score_masks(step, condition_crops(folder, limit, truth), use_alpha)


def scene_crops(maker: Any, n: int, start: int = 0) -> list[Crop]:
    """``n`` scenes of a set-up :class:`~matl.data.scenes.SceneMaker` (indices ``start`` ...) as RGB crops and their
    true masks (visible coverage above 0.5)."""
    out = []
    for i in range(start, start + int(n)):
        scene = maker(i)
        out.append((scene.image, scene.visible > 0.5))
    return out


def score_scenes(maker: Any, n: int, step: Any, start: int = 0) -> dict[str, Any]:
    """:func:`score_masks` of ``step`` on ``n`` scenes of ``maker`` (:func:`scene_crops`)."""
    return score_masks(step, scene_crops(maker, n, start))


def compare_steps(crops: list[Crop], steps: Mapping[str, Any], use_alpha: bool = True,
                  keep: Callable[[str], bool] = lambda key: key != "per_query") -> dict[str, dict[str, Any]]:
    """:func:`score_masks` of every named step on the same crops (``keep``: which result keys to return)."""
    return {name: {k: v for k, v in score_masks(step, crops, use_alpha).items() if keep(k)}
            for name, step in steps.items()}
