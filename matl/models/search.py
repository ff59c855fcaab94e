"""Gallery search: the nearest gallery embedding of each query (paper Sec. 4.5), exact or approximate.

Two backends with one interface (``search(queries (Q, D)) -> (index (Q,), distance (Q,))``, L2):

* :class:`ExactSearch` (default, ``search=exact``): a chunked matrix product in torch with the
  gallery's squared norms computed once, so a query costs one pass over the ``(G, D)`` gallery
  matrix. Exact (up to float32 rounding, like any L2 search), no extra dependency, GPU-ready. On the CPU
  a few queries against one chunk go through NumPy instead, and a single one through one numba-compiled
  pass at any gallery size (its latency is the calls' up to tens of thousands of anchors, the memory's
  beyond).
* :class:`FaissSearch` (``search=faiss``, optional ``pip install faiss-cpu``): a FAISS index, HNSW
  graph by default. Approximate: much faster than a full pass once the gallery holds hundreds of
  thousands of anchors, at a small recall cost that ``matl.bench`` measures.

Backends are built by factories ``factory(gallery_features (G, D)) -> backend`` (Hydra
``_partial_`` nodes in ``conf/search/``), so a recognizer can rebuild its backend whenever its
gallery features change (new products enrolled).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from typing import Any, Protocol

import numpy as np
import torch
from numba import njit

from matl.utils.errors import MatlError

__all__ = ["ExactSearch", "FaissSearch", "GallerySearch", "SearchFactory", "distances", "nearest", "require_faiss"]

FAISS_MISSING = "search=faiss needs the optional faiss package: pip install faiss-cpu (or: pip install -e '.[faiss]')"


def nearest(queries: torch.Tensor, gallery: torch.Tensor, chunk: int = 65536,
            gallery_sq_norms: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Exact L2 nearest neighbour: ``(Q, D) x (G, D) -> (index (Q,), distance (Q,))``, gallery in chunks.

    Args:
        queries: ``(Q, D)`` query embeddings.
        gallery: ``(G, D)`` gallery embeddings.
        chunk: gallery rows per matrix product (bounds the ``(Q, chunk)`` distance block).
        gallery_sq_norms: ``(G,)`` precomputed ``|g|^2`` (see :class:`ExactSearch`); computed here if None.

    Ties go to the lowest gallery index, as ``torch.cdist(...).min(1)``.
    """
    if gallery_sq_norms is None:
        gallery_sq_norms = gallery.pow(2).sum(-1)
    queries = queries.to(gallery.dtype)
    best_d = torch.full((len(queries),), float("inf"), dtype=gallery.dtype, device=queries.device)
    best_i = torch.zeros(len(queries), dtype=torch.long, device=queries.device)
    q_sq = queries.pow(2).sum(-1, keepdim=True)
    if 0 < len(gallery) <= chunk:  # one chunk (a single query's usual case): no running minimum to keep
        d, i = torch.addmm(gallery_sq_norms[None], queries, gallery.T, alpha=-2.0).add_(q_sq).min(dim=1)
        found = d < best_d  # as below: a NaN or infinite row keeps index 0 and distance inf
        return torch.where(found, i, best_i), torch.where(found, d, best_d).clamp_min_(0).sqrt_()
    for start in range(0, len(gallery), chunk):
        g = gallery[start:start + chunk]
        # |q - g|^2 = |q|^2 + |g|^2 - 2 q.g as one fused addmm (|g|^2 cached: one pass over the gallery)
        d2 = torch.addmm(gallery_sq_norms[start:start + chunk][None], queries, g.T, alpha=-2.0).add_(q_sq)
        d, i = d2.min(dim=1)
        better = d < best_d  # strict: an equal distance in a later chunk keeps the lower index
        best_d = torch.where(better, d, best_d)
        best_i = torch.where(better, i + start, best_i)
    return best_i, best_d.clamp_min(0).sqrt()


def distances(queries: torch.Tensor, gallery: torch.Tensor, gallery_sq_norms: torch.Tensor | None = None
              ) -> torch.Tensor:
    """Every L2 distance ``(Q, D) x (G, D) -> (Q, G)`` in the gallery's dtype: ``|q|^2 + |g|^2 - 2 q.g`` as one
    matrix product (``gallery_sq_norms`` ``(G,)``: ``|g|^2`` precomputed; computed here if None), the rounding of
    a float64 gallery far below any gap between distances. Several times faster than ``torch.cdist`` of one query
    against a catalogue's anchors on the CPU."""
    if gallery_sq_norms is None:
        gallery_sq_norms = gallery.pow(2).sum(-1)
    queries = queries.to(gallery.dtype)
    d2 = torch.addmm(gallery_sq_norms[None], queries, gallery.T, alpha=-2.0).add_(queries.pow(2).sum(-1, keepdim=True))
    return d2.clamp_min_(0).sqrt_()


class GallerySearch(Protocol):
    """What a recognizer calls: nearest gallery entry of each query embedding."""

    def search(self, queries: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(Q, D) -> (index (Q,) int64, L2 distance (Q,))`` on the queries' device."""
        ...


SearchFactory = Callable[[torch.Tensor], GallerySearch]


class ExactSearch:
    """Exact L2 search in torch; the gallery's squared norms are computed once here, not per query.

    Args:
        features: ``(G, D)`` gallery embeddings (kept by reference, on their device).
        chunk: gallery rows per matrix product.
    """

    name = "exact"

    def __init__(self, features: torch.Tensor, chunk: int = 65536) -> None:
        if features.ndim != 2:
            raise ValueError(f"gallery features must be (G, D), got {tuple(features.shape)}")
        if chunk < 1:
            raise ValueError(f"search.chunk must be >= 1, got {chunk}")
        self.features = features.contiguous()
        self.sq_norms = self.features.pow(2).sum(-1)
        self.chunk = int(chunk)
        # CPU float32 galleries answer a single query in one compiled pass over the rows (no distance block, so
        # at any gallery size: a handful of NumPy or torch calls cost more, and torch's chunked matrix-vector
        # products many times more beyond a chunk), and a few queries against one chunk in NumPy (the same sums
        # at a third of torch's per-op cost)
        self._numpy = None
        if self.features.device.type == "cpu" and self.features.dtype == torch.float32 and len(features):
            self._numpy = (self.features.detach().numpy(), self.sq_norms.detach().numpy())
            # compiled (or loaded from numba's cache) here, not at the first query
            _nearest_one(np.zeros(features.shape[1], np.float32), *(a[:1] for a in self._numpy))

    def search(self, queries: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        if (self._numpy is not None and len(queries) <= SMALL_BATCH
                and queries.device.type == "cpu" and queries.dtype == torch.float32):
            gallery, sq_norms = self._numpy
            if len(queries) == 1:  # a camera crop at a time
                i, best = _nearest_one(np.ascontiguousarray(queries.detach().numpy()[0]), gallery, sq_norms)
                found = best < math.inf
                return (torch.from_numpy(np.array([i if found else 0], dtype=np.int64)),
                        torch.from_numpy(np.array([math.sqrt(max(best, 0.0)) if found else math.inf], np.float32)))
            if len(gallery) <= self.chunk:
                return _nearest_numpy(queries.detach().numpy(), gallery.T, sq_norms)
        return nearest(queries, self.features, self.chunk, self.sq_norms)


#: query batches up to this size use :class:`ExactSearch`'s NumPy path (latency), larger ones torch (throughput)
SMALL_BATCH = 8


def _nearest_numpy(queries: np.ndarray, gallery_T: np.ndarray, sq_norms: np.ndarray
                   ) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`nearest` for ``(Q, D)`` float32 queries against one chunk, ``gallery_T`` ``(D, G)``: the same
    ``|q|^2 + |g|^2 - 2 q.g``, ties to the lowest index, a row with a NaN at index 0 and distance inf."""
    d2 = queries @ gallery_T
    d2 *= -2.0
    d2 += sq_norms
    d2 += np.einsum("qd,qd->q", queries, queries)[:, None]
    index = d2.argmin(1)
    best = d2[np.arange(len(d2)), index]
    found = best < np.inf  # False for NaN (argmin stops at the first NaN) and inf
    index = np.where(found, index, 0)
    distance = np.sqrt(np.maximum(np.where(found, best, np.inf), 0.0))
    return torch.from_numpy(index.astype(np.int64)), torch.from_numpy(distance.astype(np.float32))


@njit(cache=True, nogil=True, boundscheck=False, fastmath={"reassoc", "contract", "arcp", "nsz"})
def _nearest_one(query: np.ndarray, gallery: np.ndarray, sq_norms: np.ndarray) -> tuple[int, float]:
    """:func:`_nearest_numpy` for one ``(D,)`` float32 query against ``gallery`` ``(G, D)``: ``(index, squared
    distance)`` of the nearest entry (the lowest index among ties), ``(0, inf)`` if a distance is NaN. The same
    float32 sums in another order: distances agree to float32 rounding."""
    qq = np.float32(0.0)
    for d in range(query.shape[0]):
        qq += query[d] * query[d]
    best = np.inf
    index = 0
    for g in range(gallery.shape[0]):
        row = gallery[g]
        dot = np.float32(0.0)
        for d in range(query.shape[0]):
            dot += row[d] * query[d]
        d2 = (np.float32(-2.0) * dot + sq_norms[g]) + qq
        if d2 < best:
            best, index = d2, g
        elif not d2 >= best:  # NaN: as the batch path, no answer
            return 0, np.inf
    return index, best


def require_faiss() -> Any:
    """Import faiss, or raise a one-line :class:`MatlError` saying how to install it."""
    # faiss logs every SIMD variant it tries to load at INFO: noise in a run's log
    logging.getLogger("faiss.loader").setLevel(logging.WARNING)
    try:
        import faiss
    except ImportError as error:
        raise MatlError(FAISS_MISSING) from error
    return faiss


class FaissSearch:
    """Approximate (or exact ``flat``) L2 search with a FAISS index on the CPU.

    Args:
        features: ``(G, D)`` gallery embeddings.
        index: ``hnsw`` (graph; no training, best latency for one query), ``ivf`` (inverted lists;
            needs ``G >= nlist``, trained on the gallery) or ``flat`` (exact brute force, a reference).
        hnsw_m: HNSW neighbours per node.
        ef_construction / ef_search: HNSW candidate list sizes when building / searching (higher:
            better recall, slower).
        nlist / nprobe: IVF lists, and lists visited per query.
        threads: FAISS OpenMP threads; None keeps ``torch.get_num_threads()`` so both backends are
            timed with the same threads.
    """

    name = "faiss"

    def __init__(self, features: torch.Tensor, index: str = "hnsw", hnsw_m: int = 32, ef_construction: int = 80,
                 ef_search: int = 64, nlist: int = 1024, nprobe: int = 16, threads: int | None = None) -> None:
        # the config is checked first: a wrong option is reported whether or not faiss is installed
        if index not in ("hnsw", "ivf", "flat"):
            raise ValueError(f"search.index must be hnsw, ivf or flat, got {index!r}")
        for key, value in (("hnsw_m", hnsw_m), ("ef_construction", ef_construction), ("ef_search", ef_search),
                           ("nlist", nlist), ("nprobe", nprobe)):
            if int(value) < 1:
                raise ValueError(f"search.{key} must be >= 1, got {value}")
        if features.ndim != 2 or len(features) == 0:
            raise ValueError(f"gallery features must be a non-empty (G, D) tensor, got {tuple(features.shape)}")
        faiss = require_faiss()
        faiss.omp_set_num_threads(int(threads) if threads else torch.get_num_threads())
        data = features.detach().float().cpu().contiguous().numpy()
        G, D = data.shape
        self.kind = index
        if index == "hnsw":
            self.index = faiss.IndexHNSWFlat(D, int(hnsw_m))
            self.index.hnsw.efConstruction = int(ef_construction)
            self.index.hnsw.efSearch = int(ef_search)
        elif index == "ivf":
            lists = min(int(nlist), G)  # k-means cannot make more lists than points
            self.index = faiss.IndexIVFFlat(faiss.IndexFlatL2(D), D, lists)
            self.index.train(data)
            self.index.nprobe = min(int(nprobe), lists)
        else:
            self.index = faiss.IndexFlatL2(D)
        self.index.add(data)

    def search(self, queries: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        q = queries.detach().float().cpu().contiguous().numpy()
        d2, i = self.index.search(q, 1)
        index = torch.from_numpy(i[:, 0]).long()
        # an HNSW / IVF search can come back empty (-1) for a tiny gallery: fall back to entry 0
        index = index.clamp_min(0)
        distance = torch.from_numpy(d2[:, 0]).clamp_min(0).sqrt()
        return index.to(queries.device), distance.to(queries.device)
