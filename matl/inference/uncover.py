"""The product a crop was cut for, under another product lying across it (``uncover``).

In a picking bin the product the robot is after often has another product lying across it. That product is on top,
so its print is whole: it verifies, and the recognizer can answer it instead of the product the crop was cut for.
Two facts tell them apart. The crop is cut around its subject, so the subject's plane (its hidden part included)
covers most of what the crop shows and lies about its centre, where a product lying across it covers less or lies
off centre; and where their planes overlap the pixels show the one on top. So an answer whose pose verifies but
whose plane covers less than ``uncover`` of the crop's shown pixels is explained away: its plane is erased from the
crop's foreground and the rest is answered again (the whole query path: networks, verification, keypoint pose).
The rest's answer is taken where it is another product, its pose verifies over what is left, its plane covers more
of the crop than the first answer's or lies nearer the crop's centre (:func:`centre_offset`), and the first answer
lies on top of it where their planes overlap (:func:`lies_on_top`); a neighbour behind the subject (clutter) covers
less of the crop and lies off centre, one beside it does not overlap it, and a subject lying on another product is
not under it, so each keeps its answer. Conversely an answer whose pose verifies but that is held unverified
(another product's keypoint pose: it might be such a product lying across) and whose plane covers at least ``uncover``
of the crop is the crop's subject, and counts as verified where its distance is within :data:`SUBJECT_MARGIN` of
``verify_max``.

This module holds the geometry (pure functions); :meth:`~matl.inference.query_passes.QueryPasses._uncovered` runs
the step.
"""

from __future__ import annotations

import cv2
import numpy as np
import torch

from matl.inference.verify import zncc

#: the explained plane is erased from the crop's foreground grown by this many pixels of the file (its edge, a pose
#: a pixel off)
ERASE_PX = 2
#: fewest overlap pixels :func:`lies_on_top` judges; with fewer there is no evidence of which one is on top
MIN_OVERLAP = 20
#: an answer held unverified (another product's keypoint pose) whose plane covers the crop is its subject when its
#: verification distance is within this share of ``verify_max``: the keypoints chose a product the embedding did not
#: put first, so its print must match with a margin (docs/decisions.md)
SUBJECT_MARGIN = 0.5


def plane_in_query(plane: np.ndarray, query_H_canon: np.ndarray, size: int) -> np.ndarray:
    """``(S, S)`` bool: a plane's foreground ``plane`` ``(S, S)`` bool in its canonical frame, warped into the query's
    model frame by ``query_H_canon`` ``(3, 3)`` (bilinear, above one half)."""
    warped = cv2.warpPerspective(plane.astype(np.float32), np.asarray(query_H_canon, dtype=np.float64), (size, size),
                                 flags=cv2.INTER_LINEAR)
    return warped > 0.5


def centre_offset(plane: np.ndarray, query_H_canon: np.ndarray, size: int) -> float:
    """How far from the query frame's centre a plane lies: the centroid of its foreground ``plane`` ``(S, S)`` bool
    in its canonical frame, mapped by ``query_H_canon`` ``(3, 3)``, in units of the frame's side ``S`` (inf for an
    empty plane or a centroid mapped to infinity)."""
    ys, xs = np.nonzero(plane)
    if len(xs) == 0:
        return float("inf")
    x, y, w = np.asarray(query_H_canon, dtype=np.float64) @ np.array([xs.mean(), ys.mean(), 1.0])
    if abs(w) < 1e-12:
        return float("inf")
    return float(np.hypot(x / w - (size - 1) / 2, y / w - (size - 1) / 2) / size)


def erased_alpha(alpha: np.ndarray, plane: np.ndarray, model_H_file: np.ndarray, grow: int = ERASE_PX) -> np.ndarray:
    """A crop's foreground alpha ``(H, W)`` float32 with a plane erased: ``plane`` ``(S, S)`` bool in the model
    frame, brought to the file's pixels by the inverse of the framing ``model_H_file`` ``(3, 3)`` and grown by
    ``grow`` px there."""
    h, w = alpha.shape
    file_H_model = np.linalg.inv(np.asarray(model_H_file, dtype=np.float64))
    erased = cv2.warpPerspective(plane.astype(np.uint8), file_H_model, (w, h), flags=cv2.INTER_NEAREST)
    if grow > 0:
        erased = cv2.dilate(erased, np.ones((2 * grow + 1, 2 * grow + 1), np.uint8))
    return np.ascontiguousarray(alpha * (1.0 - erased.astype(np.float32)), dtype=np.float32)


def lies_on_top(query: torch.Tensor, top: torch.Tensor, under: torch.Tensor, overlap: torch.Tensor) -> bool | None:
    """Whether, over ``overlap`` ``(S, S)`` bool, the query ``(3, S, S)`` shows the print of ``top`` rather than that
    of ``under`` (each ``(3, S, S)``: an anchor warped into the query's frame by its pose): the one that shows is
    the one on top (:func:`~matl.inference.verify.zncc`, the verification's correlation). Returns None with fewer
    than :data:`MIN_OVERLAP` overlap pixels (no evidence)."""
    if int(overlap.sum()) < MIN_OVERLAP:
        return None
    both = zncc(query[None].expand(2, -1, -1, -1), torch.stack([top, under]), overlap[None, None].expand(2, -1, -1, -1))
    return bool(both[0] > both[1])
