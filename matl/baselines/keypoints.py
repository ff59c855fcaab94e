"""Shared machinery of the keypoint baselines (Table 1 rows (d), (e) and the learned matcher).

Every keypoint baseline recognises a query and estimates its pose the same way (Sec. 5.5): match the
query's local features against each gallery image, fit ``query_H_anchor`` with RANSAC
(``cv2.findHomography``) per gallery image, and vote for the image with the most RANSAC inliers.
The baselines differ only in the features and in how tentative correspondences are formed, so this
module holds the interface (:class:`MatchResult`, :class:`KeypointMatcher`), the vectorised matching
of one query against the whole gallery at once, and the RANSAC voting.

Conventions (DESIGN sec. 2): images are ``(B, 3, H, W)`` float RGB in [0, 1]; keypoints are pixel
coordinates ``(x, y)`` with ``(0, 0)`` the centre of the top-left pixel; ``query_H_anchor`` maps
gallery-image pixels to query pixels and has ``H[2, 2] == 1``.

Speed without changing the result: the exhaustive baseline matches the query against each gallery
image separately (a k-NN per image, then RANSAC per image). Here all gallery descriptors sit in
one zero-padded ``(G * K_max, D)`` matrix built once, one matrix product per query gives every
distance as a ``(n, G, K_max)`` block, and per-image neighbours are a ``topk`` over its last axis.
RANSAC then visits the candidates in decreasing order of tentative
matches and stops as soon as the next candidate has fewer tentative matches than the best inlier
count so far, which cannot change the winner since inliers never exceed tentative matches.
"""

from __future__ import annotations

import time
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

import cv2
import numpy as np
import torch

__all__ = [
    "RANSAC_METHODS",
    "GalleryDescriptors",
    "ImageFeatures",
    "KeypointMatcher",
    "MatchResult",
    "RansacVoting",
    "RansacVotingMatcher",
    "TentativeMatches",
    "check_image_batch",
    "extract_in_batches",
    "measure_query_ms",
    "mutual_nn_matches",
    "ratio_test_matches",
    "to_gray_float",
    "to_gray_uint8",
    "vote_by_ransac",
]

# Padded descriptor columns per gallery bucket: a query's (n, Gb, K) distance block is then at most
# n * 8192 floats (32 MB for 1024 query keypoints) while GEMMs stay large enough to be efficient.
_BUCKET_COLUMNS = 8192

# Robust estimators of cv2.findHomography by config name. "ransac" is the paper's (Sec. 5.5); the
# USAC variants give different (not approximate) estimates and are ~100x faster per call.
RANSAC_METHODS: dict[str, int] = {
    "ransac": cv2.RANSAC,
    "usac_default": cv2.USAC_DEFAULT,
    "usac_fast": cv2.USAC_FAST,
    "usac_accurate": cv2.USAC_ACCURATE,
    "usac_magsac": cv2.USAC_MAGSAC,
    "rho": cv2.RHO,
}


@dataclass
class MatchResult:
    """Recognition and pose of a batch of queries by a keypoint baseline.

    Attributes:
        gallery_index: ``(Q,)`` int64, index of the chosen gallery image (most RANSAC inliers), or -1
            when no gallery image reached ``min_inliers``.
        query_H_anchor: ``(Q, 3, 3)`` float64, maps the chosen gallery image's pixel coordinates to
            the query's, ``H[2, 2] == 1``; identity where ``gallery_index == -1``.
        inliers: ``(Q,)`` int64, RANSAC inlier count of the chosen image (0 where nothing matched).
    """

    gallery_index: torch.Tensor
    query_H_anchor: torch.Tensor
    inliers: torch.Tensor


@runtime_checkable
class KeypointMatcher(Protocol):
    """What the evaluation calls on every keypoint baseline."""

    def index_gallery(self, gallery: torch.Tensor) -> None:
        """Extract and keep the features of the gallery ``(G, 3, H, W)`` once."""
        ...

    def match(self, queries: torch.Tensor) -> MatchResult:
        """Recognise and register queries ``(Q, 3, H, W)`` against the indexed gallery."""
        ...


@dataclass
class ImageFeatures:
    """Local features of one image.

    Attributes:
        keypoints: ``(K, 2)`` float32 pixel coordinates ``(x, y)``.
        descriptors: ``(K, D)`` float32 descriptors (row ``i`` describes keypoint ``i``).
    """

    keypoints: np.ndarray
    descriptors: torch.Tensor

    def __post_init__(self) -> None:
        self.keypoints = np.ascontiguousarray(self.keypoints, dtype=np.float32).reshape(-1, 2)
        if self.descriptors.ndim != 2 or self.descriptors.shape[0] != self.keypoints.shape[0]:
            raise ValueError(
                f"descriptors {tuple(self.descriptors.shape)} do not match keypoints {self.keypoints.shape}"
            )

    def __len__(self) -> int:
        return int(self.keypoints.shape[0])


@dataclass
class TentativeMatches:
    """Tentative correspondences of one query with every gallery image.

    Rows are sorted by gallery image, then by query keypoint, the order in which a per-image matcher
    lists them (RANSAC's result depends on the order of its input points).

    Attributes:
        query_kp: ``(T,)`` int64 index of the query keypoint.
        gallery_img: ``(T,)`` int64 gallery image.
        gallery_kp: ``(T,)`` int64 index of the keypoint within that gallery image.
    """

    query_kp: np.ndarray
    gallery_img: np.ndarray
    gallery_kp: np.ndarray

    @classmethod
    def empty(cls) -> TentativeMatches:
        """No correspondence at all."""
        z = np.zeros(0, dtype=np.int64)
        return cls(z, z.copy(), z.copy())

    def counts(self, num_gallery: int) -> np.ndarray:
        """``(G,)`` int64 number of tentative matches per gallery image."""
        return np.bincount(self.gallery_img, minlength=num_gallery).astype(np.int64)

    def sorted(self) -> TentativeMatches:
        """The same rows in (gallery image, query keypoint) order."""
        order = np.lexsort((self.query_kp, self.gallery_img))
        return TentativeMatches(self.query_kp[order], self.gallery_img[order], self.gallery_kp[order])


@dataclass
class _Bucket:
    """Gallery images of similar keypoint counts, zero-padded to a common ``K`` keypoints.

    Attributes:
        images: ``(Gb,)`` int64 gallery indices of the images.
        k: padded keypoint count (the largest count of the bucket).
        padded_t: ``(D, Gb * K)`` float32 transposed descriptors; image ``images[b]``'s keypoint ``j``
            is column ``b * K + j``.
        sq_norms: ``(Gb * K,)`` float32 squared norms, +inf on padding so it never wins a search.
    """

    images: np.ndarray
    k: int
    padded_t: torch.Tensor
    sq_norms: torch.Tensor

    def neg_half_distances(self, query_x2: torch.Tensor) -> torch.Tensor:
        """``||g||^2 - 2 q.g`` ``(n, Gb, K)`` for query descriptors already multiplied by -2.

        One fused GEMM; adding ``||q||^2`` (constant per query row) is left to the caller, on the
        few distances it keeps. All terms of integer-valued descriptors (SIFT) below 2^24 are exact.
        """
        out = torch.addmm(self.sq_norms[None, :], query_x2, self.padded_t)
        return out.view(query_x2.shape[0], len(self.images), self.k)


class GalleryDescriptors:
    """All gallery descriptors, laid out for one-shot matching of a query against every image.

    Images are sorted by keypoint count and grouped into buckets of at most ``_BUCKET_COLUMNS``
    padded keypoints, each zero-padded to its own largest count: one GEMM per bucket gives a
    ``(n, Gb, K)`` block whose last axis is "keypoints of that image", with little padding waste.

    Attributes:
        features: the per-image features, kept for their keypoints.
        counts: ``(G,)`` int64 keypoints per image.
    """

    def __init__(self, features: list[ImageFeatures]) -> None:
        if not features:
            raise ValueError("the gallery is empty")
        dims = {f.descriptors.shape[1] for f in features}
        if len(dims) != 1:
            raise ValueError(f"gallery descriptors have mixed dimensions {sorted(dims)}")
        self.features = features
        self.counts = np.array([len(f) for f in features], dtype=np.int64)
        self.buckets: list[_Bucket] = []
        group: list[int] = []
        # images without keypoints can never match and get no bucket
        for g in (int(i) for i in np.argsort(self.counts, kind="stable") if self.counts[i] > 0):
            if group and (len(group) + 1) * self.counts[g] > _BUCKET_COLUMNS:
                self._add_bucket(group)
                group = []
            group.append(g)
        if group:
            self._add_bucket(group)

    def _add_bucket(self, images: list[int]) -> None:
        k = int(self.counts[images].max())
        dim = self.features[images[0]].descriptors.shape[1]
        padded = torch.zeros(len(images), k, dim)
        valid = torch.zeros(len(images), k, dtype=torch.bool)
        for b, g in enumerate(images):
            n = len(self.features[g])
            padded[b, :n] = self.features[g].descriptors.float()
            valid[b, :n] = True
        flat = padded.view(-1, dim)
        sq = torch.where(valid.view(-1), (flat * flat).sum(1), float("inf"))
        self.buckets.append(_Bucket(np.array(images, dtype=np.int64), k, flat.T.contiguous(), sq))

    def __len__(self) -> int:
        return len(self.features)


def _tentative(q_idx: list[torch.Tensor], g_idx: list[np.ndarray], k_idx: list[torch.Tensor]) -> TentativeMatches:
    if not q_idx:
        return TentativeMatches.empty()
    return TentativeMatches(
        torch.cat(q_idx).numpy().astype(np.int64),
        np.concatenate(g_idx).astype(np.int64),
        torch.cat(k_idx).numpy().astype(np.int64),
    ).sorted()


def ratio_test_matches(query: torch.Tensor, gallery: GalleryDescriptors, ratio: float) -> TentativeMatches:
    """Lowe's ratio test of one query against every gallery image at once.

    Equivalent to running ``cv2.BFMatcher(cv2.NORM_L2).knnMatch(query, image, k=2)`` per gallery
    image and keeping ``m.distance < ratio * n.distance``: the two nearest neighbours are taken
    *within each image*, not over the whole gallery. An image with fewer than two keypoints yields
    no match (the second neighbour is missing).

    For SIFT descriptors (integer-valued float32) the squared distances are exact in float32, so
    the result is bit-identical to the per-image matcher; for other descriptors it can differ only
    where two distances tie to within float rounding.

    Args:
        query: ``(N, D)`` float32 descriptors of the query.
        gallery: the indexed gallery.
        ratio: Lowe's ratio.

    Returns:
        The tentative matches, sorted by (gallery image, query keypoint).
    """
    if query.shape[0] == 0:
        return TentativeMatches.empty()
    q = query.float()
    q_sq = (q * q).sum(1)[:, None]
    q_x2 = q * -2.0  # exact: a power of two
    out_q, out_g, out_k = [], [], []
    for bucket in gallery.buckets:
        if bucket.k < 2:
            continue  # one keypoint per image: knnMatch gives no second neighbour
        d = bucket.neg_half_distances(q_x2)  # (n, Gb, K)
        # two nearest by min / mask / min, several times faster than topk(2) on a CPU
        first, arg = d.min(2)
        d.scatter_(2, arg[..., None], float("inf"))
        second = d.min(2).values
        d1 = (first + q_sq).clamp_min_(0.0)
        d2 = (second + q_sq).clamp_min_(0.0)
        # sqrt in float32 then compare in float64: the exact arithmetic of OpenCV's matcher followed
        # by Python's `m.distance < ratio * n.distance`; an infinite second distance (an image with
        # a single keypoint) has no second neighbour in knnMatch and is excluded explicitly
        keep = (d1.sqrt().double() < ratio * d2.sqrt().double()) & torch.isfinite(d2)
        qi, bi = torch.nonzero(keep, as_tuple=True)
        out_q.append(qi)
        out_g.append(bucket.images[bi.numpy()])
        out_k.append(arg[qi, bi])
    return _tentative(out_q, out_g, out_k)


def mutual_nn_matches(
    query: torch.Tensor, gallery: GalleryDescriptors, max_distance: float | None = None
) -> TentativeMatches:
    """Mutual nearest neighbours of one query with every gallery image at once.

    Equivalent to, per gallery image, keeping the pairs ``(i, j)`` with ``j`` the nearest image
    keypoint of query keypoint ``i`` and ``i`` the nearest query keypoint of ``j`` (L2 distance,
    which for the L2-normalised descriptors of learned features ranks like the dot product).

    Args:
        query: ``(N, D)`` float32 descriptors.
        gallery: the indexed gallery.
        max_distance: optional upper bound on the L2 distance of a kept pair.

    Returns:
        The tentative matches, sorted by (gallery image, query keypoint).
    """
    n = query.shape[0]
    if n == 0:
        return TentativeMatches.empty()
    q = query.float()
    q_sq = (q * q).sum(1)[:, None]
    q_x2 = q * -2.0
    rows = torch.arange(n)[:, None]
    out_q, out_g, out_k = [], [], []
    for bucket in gallery.buckets:
        d = bucket.neg_half_distances(q_x2)  # (n, Gb, K); + ||q||^2 does not change a row's argmin
        near, arg = d.min(2)  # nearest keypoint of each image, per query keypoint
        # the column argmin needs the true distances: ||q||^2 differs between rows
        col_best = (d + q_sq[:, :, None]).argmin(0)  # (Gb, K) nearest query keypoint
        mutual = rows == col_best.gather(1, arg.T).T  # (n, Gb)
        keep = mutual & torch.isfinite(near)
        if max_distance is not None:
            keep &= (near + q_sq).clamp_min(0.0) <= max_distance**2
        qi, bi = torch.nonzero(keep, as_tuple=True)
        out_q.append(qi)
        out_g.append(bucket.images[bi.numpy()])
        out_k.append(arg[qi, bi])
    return _tentative(out_q, out_g, out_k)


def vote_by_ransac(
    query_keypoints: np.ndarray,
    gallery_keypoints: list[np.ndarray],
    matches: TentativeMatches,
    *,
    reproj_threshold: float,
    min_inliers: int,
    top_k: int | None = None,
    max_iters: int = 2000,
    confidence: float = 0.995,
    method: int = cv2.RANSAC,
) -> tuple[int, np.ndarray, int]:
    """Pick the gallery image with the most RANSAC inliers and its homography.

    The result equals running ``cv2.findHomography(gallery_pts, query_pts, cv2.RANSAC, ...)`` on
    every gallery image with at least ``max(4, min_inliers)`` tentative matches and keeping the
    most inliers (ties: lowest gallery index). Candidates are visited by decreasing tentative count
    and the loop stops once no remaining candidate can reach the best inlier count.

    Args:
        query_keypoints: ``(N, 2)`` float32 query keypoints.
        gallery_keypoints: per gallery image ``(K_g, 2)`` float32 keypoints.
        matches: tentative matches sorted by (gallery image, query keypoint).
        reproj_threshold: RANSAC inlier threshold in query pixels.
        min_inliers: fewest inliers accepted as a recognition.
        top_k: if given, only the ``top_k`` images with most tentative matches are verified (an
            approximation: a lower-ranked image could have had more inliers).
        max_iters: RANSAC iterations (OpenCV's default 2000).
        confidence: RANSAC confidence (OpenCV's default 0.995).
        method: ``cv2.findHomography`` method flag (a value of :data:`RANSAC_METHODS`).

    Returns:
        ``(gallery_index, query_H_anchor (3, 3) float64, inliers)``; ``(-1, identity, 0)`` if no
        image reached ``min_inliers``.
    """
    num_gallery = len(gallery_keypoints)
    counts = matches.counts(num_gallery)
    need = max(4, int(min_inliers))  # a homography needs 4 correspondences
    order = np.lexsort((np.arange(num_gallery), -counts))  # most matches first, then lowest index
    order = order[counts[order] >= need]
    if top_k is not None:
        order = order[: int(top_k)]
    starts = np.searchsorted(matches.gallery_img, np.arange(num_gallery), side="left")
    best = (-1, np.eye(3), 0)
    for g in order:
        g = int(g)
        if counts[g] < best[2]:
            break  # inliers <= tentative matches: nobody further down can beat (or tie) the best
        sl = slice(int(starts[g]), int(starts[g] + counts[g]))
        src = gallery_keypoints[g][matches.gallery_kp[sl]].reshape(-1, 1, 2)
        dst = query_keypoints[matches.query_kp[sl]].reshape(-1, 1, 2)
        H, mask = cv2.findHomography(src, dst, method, reproj_threshold, maxIters=max_iters, confidence=confidence)
        if H is None or mask is None or not np.isfinite(H).all() or abs(H[2, 2]) < 1e-12:
            continue
        n_in = int(mask.sum())
        # strictly more inliers, or as many with a lower index (order is not by index)
        if n_in >= need and (n_in > best[2] or (n_in == best[2] and g < best[0])):
            best = (g, H / H[2, 2], n_in)
    return best[0], np.asarray(best[1], dtype=np.float64), best[2]


def check_image_batch(images: torch.Tensor, name: str) -> torch.Tensor:
    """Validate ``(B, 3, H, W)`` float RGB images and return them on the CPU, detached.

    Raises:
        ValueError: with a one-line message on any other shape or dtype.
    """
    if not isinstance(images, torch.Tensor) or images.ndim != 4 or images.shape[1] != 3:
        shape = tuple(images.shape) if isinstance(images, torch.Tensor) else type(images).__name__
        raise ValueError(f"{name} must be a (B, 3, H, W) RGB float tensor in [0, 1], got {shape}")
    if not images.is_floating_point():
        raise ValueError(f"{name} must be a float tensor in [0, 1], got {images.dtype}")
    return images.detach().cpu()


def to_gray_uint8(images: torch.Tensor) -> np.ndarray:
    """RGB ``(B, 3, H, W)`` in [0, 1] to ``(B, H, W)`` uint8 grey, OpenCV's weights and rounding."""
    rgb = (images.clamp(0, 1) * 255.0).round().to(torch.uint8).permute(0, 2, 3, 1).numpy()
    return np.stack([cv2.cvtColor(np.ascontiguousarray(im), cv2.COLOR_RGB2GRAY) for im in rgb])


def to_gray_float(images: torch.Tensor) -> torch.Tensor:
    """RGB ``(B, 3, H, W)`` in [0, 1] to ``(B, 1, H, W)`` float grey (ITU-R BT.601 luma)."""
    w = images.new_tensor([0.299, 0.587, 0.114]).view(1, 3, 1, 1)
    return (images * w).sum(1, keepdim=True)


def extract_in_batches(extract_batch: Callable[[torch.Tensor], list[ImageFeatures]], images: torch.Tensor,
                       batch_size: int) -> list[ImageFeatures]:
    """``extract_batch`` over ``images`` ``(B, 3, H, W)`` in chunks of ``batch_size``, the features in order."""
    out: list[ImageFeatures] = []
    for start in range(0, images.shape[0], batch_size):
        out.extend(extract_batch(images[start : start + batch_size]))
    return out


@dataclass
class RansacVoting:
    """The RANSAC vote of every keypoint baseline, by its config keys (``baseline.<key>``).

    Each matcher takes these keywords beside its own (``SiftRansacMatcher(ratio=0.8, top_k=10)``) and
    votes with :meth:`vote`, so the settings, their checks and the call are written once.

    Attributes:
        ransac_reproj_threshold: RANSAC inlier threshold in query pixels.
        min_inliers: fewest inliers for a recognition; below it the query is unmatched (-1). At least 4
            are always needed (a homography).
        top_k: RANSAC only on the ``top_k`` gallery images with most tentative matches (an approximation);
            None verifies every image that could win (exact). A matcher that shortlists the gallery before
            matching (LightGlue, XFeat's LighterGlue) uses it for its shortlist instead.
        ransac_max_iters: RANSAC iterations (OpenCV's default 2000).
        ransac_confidence: RANSAC confidence (OpenCV's default 0.995).
        ransac_method: the robust estimator, a key of :data:`RANSAC_METHODS`: ``"ransac"`` (the paper's
            ``cv2.RANSAC``) or a faster USAC one.
    """

    ransac_reproj_threshold: float = 3.0
    min_inliers: int = 4
    top_k: int | None = None
    ransac_max_iters: int = 2000
    ransac_confidence: float = 0.995
    ransac_method: str = "ransac"

    def __post_init__(self) -> None:
        if self.ransac_method not in RANSAC_METHODS:
            raise ValueError(f"ransac_method must be one of {sorted(RANSAC_METHODS)}, got {self.ransac_method!r}")
        if self.top_k is not None and int(self.top_k) < 1:
            raise ValueError(f"top_k must be a positive integer or null, got {self.top_k}")
        if self.ransac_reproj_threshold <= 0:
            raise ValueError(f"ransac_reproj_threshold must be > 0, got {self.ransac_reproj_threshold}")
        self.ransac_reproj_threshold = float(self.ransac_reproj_threshold)
        self.min_inliers = int(self.min_inliers)
        self.top_k = None if self.top_k is None else int(self.top_k)
        self.ransac_max_iters = int(self.ransac_max_iters)
        self.ransac_confidence = float(self.ransac_confidence)

    def vote(self, query_keypoints: np.ndarray, gallery_keypoints: list[np.ndarray], matches: TentativeMatches,
             top_k: int | None) -> tuple[int, np.ndarray, int]:
        """:func:`vote_by_ransac` with these settings; ``top_k`` as the matcher hands it on (see the attribute)."""
        return vote_by_ransac(query_keypoints, gallery_keypoints, matches,
                              reproj_threshold=self.ransac_reproj_threshold, min_inliers=self.min_inliers,
                              top_k=top_k, max_iters=self.ransac_max_iters, confidence=self.ransac_confidence,
                              method=RANSAC_METHODS[self.ransac_method])


class RansacVotingMatcher(ABC):
    """Gallery indexing, per-query matching and RANSAC voting shared by the keypoint baselines.

    Subclasses provide :meth:`extract` (features of a batch of images) and :meth:`tentative`
    (correspondences of one query with the indexed gallery).

    Args:
        **ransac: the vote's settings, :class:`RansacVoting`'s keys (kept as ``ransac``).
    """

    def __init__(self, **ransac: Any) -> None:
        self.ransac = RansacVoting(**ransac)
        self.gallery: GalleryDescriptors | None = None
        self.gallery_size: tuple[int, int] | None = None

    @abstractmethod
    def extract(self, images: torch.Tensor) -> list[ImageFeatures]:
        """Local features of images ``(B, 3, H, W)``, one :class:`ImageFeatures` per image."""

    @abstractmethod
    def tentative(self, query: ImageFeatures) -> TentativeMatches:
        """Tentative correspondences of one query with the indexed gallery."""

    def index_gallery(self, gallery: torch.Tensor) -> None:
        """Extract and keep the features of every gallery image ``(G, 3, H, W)``."""
        gallery = check_image_batch(gallery, "gallery")
        self.gallery = GalleryDescriptors(self.extract(gallery))
        self.gallery_size = (int(gallery.shape[2]), int(gallery.shape[3]))

    def _require_gallery(self) -> GalleryDescriptors:
        if self.gallery is None:
            raise RuntimeError(f"{type(self).__name__}.match called before index_gallery(gallery)")
        return self.gallery

    def match(self, queries: torch.Tensor) -> MatchResult:
        """Recognise and register queries ``(Q, 3, H, W)`` against the indexed gallery."""
        gallery = self._require_gallery()
        queries = check_image_batch(queries, "queries")
        feats = self.extract(queries)
        index = torch.full((len(feats),), -1, dtype=torch.int64)
        homs = torch.eye(3, dtype=torch.float64).repeat(len(feats), 1, 1)
        inliers = torch.zeros(len(feats), dtype=torch.int64)
        gallery_kpts = [f.keypoints for f in gallery.features]
        for i, qf in enumerate(feats):
            g, H, n_in = self.ransac.vote(qf.keypoints, gallery_kpts, self.tentative(qf), self._vote_top_k())
            if g >= 0:
                index[i], homs[i], inliers[i] = g, torch.from_numpy(H), n_in
        return MatchResult(gallery_index=index, query_H_anchor=homs, inliers=inliers)

    def _vote_top_k(self) -> int | None:
        """``top_k`` handed to the RANSAC vote (a subclass that shortlists earlier returns None)."""
        return self.ransac.top_k


def measure_query_ms(matcher: KeypointMatcher, queries: torch.Tensor, warmup: int = 1) -> float:
    """Mean wall-clock milliseconds of ``matcher.match`` per query, one query per call.

    The gallery must already be indexed (DESIGN sec. 3, ``query_ms``: batch of 1, gallery in
    memory). The first ``warmup`` queries are run once untimed to exclude lazy initialisation.

    Args:
        matcher: an indexed matcher.
        queries: ``(Q, 3, H, W)`` query images.
        warmup: number of untimed calls before timing.
    """
    for i in range(min(warmup, queries.shape[0])):
        matcher.match(queries[i : i + 1])
    start = time.perf_counter()
    for i in range(queries.shape[0]):
        matcher.match(queries[i : i + 1])
    return (time.perf_counter() - start) * 1e3 / max(queries.shape[0], 1)
