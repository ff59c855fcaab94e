"""MATL's batched tensor-level recognizer (paper Sec. 4.5): nearest gallery anchor by
``||c(anchor) - c(s(query))||`` plus the STN pose.

It sits beside the models because their validation and test run it (:meth:`MATLModule.build_recognizer
<matl.models.module.MATLModule.build_recognizer>`); the serving side (:mod:`matl.inference`) wraps it with
image files, open-set answers, verification, refinement and other runtimes.

Speed (docs/speed.md): a query batch runs ``s()`` and ``c()`` through their ``infer`` methods (the
same function as ``forward`` up to float rounding, without kornia's per-call overhead). Small CPU
batches (``compiled_max_batch``, default 8: the one-query calls of ``query_ms``, bench and predict)
go through :class:`CompiledQueryPath` instead: both networks as one TorchScript graph, traced,
frozen and optimised for inference (weights pre-packed for oneDNN, convolution and ReLU fused),
built at the first call and rebuilt whenever a weight changes.

With an alignment stage (``model.align``, :mod:`matl.models.align`) the stage runs after the search, on
the networks' outputs of whichever path ran (eager, compiled, int8, or an exported query network put
in place of :meth:`TensorRecognizer.embed_queries`), against the anchor the search returned; the stage
itself is always eager float32 (it is not part of the compiled, int8 or exported graphs).
"""

from __future__ import annotations

import logging
import warnings
from typing import Any

import torch
from torch import nn

from matl.data.gallery import Gallery
from matl.geometry import (
    check_images,
    compose_query_H_canon,
    normalisation_matrices,
    normalised_grid,
    normalised_to_pixel,
    sample_by_normalised,
)
from matl.losses import anchor_distances
from matl.models.feature import FeatureNet
from matl.models.prediction import Prediction
from matl.models.search import ExactSearch, GallerySearch, SearchFactory, distances
from matl.models.stn import SpatialTransformer, regress_homography

__all__ = ["MODAL_LAYERS", "CompiledQueryPath", "QueryGraph", "TensorRecognizer", "embed", "weights_key"]

log = logging.getLogger(__name__)

#: layers whose output depends on training / eval mode
MODAL_LAYERS = (nn.modules.batchnorm._BatchNorm, nn.modules.dropout._DropoutNd)

#: largest difference accepted between the compiled query path and the eager networks when it is built
COMPILED_TOLERANCE = 1e-4


def weights_key(tensors: list[torch.Tensor]) -> list[tuple[int, int]]:
    """Storage and version counter of each tensor: changes when a weight is replaced, moved or modified in place
    (an optimiser step, ``load_state_dict``), so a path built from the weights knows when to rebuild."""
    return [(t.data_ptr(), t._version) for t in tensors]


@torch.no_grad()
def embed(feature_net: nn.Module, images: torch.Tensor, batch_size: int = 512) -> torch.Tensor:
    """``c(images)`` in chunks: ``(G, 3, H, W) -> (G, D)``."""
    return torch.cat([feature_net(images[i:i + batch_size]) for i in range(0, len(images), batch_size)])


class QueryGraph(nn.Module):
    """``s()`` then ``c()`` of queries as plain torch ops with no data-dependent Python control flow
    (traceable by ``torch.jit.trace`` and ``torch.export``), equal to the eager networks up to float rounding.

    ``s()`` is :func:`~matl.models.stn.regress_homography` (the STN's own loop and guard) with the warp
    :func:`~matl.geometry.sample_by_normalised` on a grid held as a buffer, then
    :func:`~matl.geometry.normalised_to_pixel` with matrices held as buffers, so that the traced graph
    keeps them as constants. Used by :class:`CompiledQueryPath`, by ``matl.export`` and, with int8
    layers, by :class:`matl.inference.quantize.QuantizedQueryPath`.

    ``forward(images (B, 3, S, S)) -> (embedding (B, D), query_H_anchor (B, 3, 3) pixel,
    degenerate (B,) bool, warped (B, 3, S, S))``.

    Args:
        stn: ``s()`` (its regressor, ``iterations``, ``max_condition`` and ``image_size``).
        feature_net: ``c()``.
        image_size: ``S``; None: the STN's.
        regressor: replaces ``stn.regressor`` (the int8 path's quantised one); a module, so that its
            weights are the graph's.
        feature: replaces ``feature_net``, likewise.
    """

    def __init__(self, stn: nn.Module, feature_net: nn.Module, image_size: int | None = None,
                 regressor: nn.Module | None = None, feature: nn.Module | None = None) -> None:
        super().__init__()
        self.regressor = stn.regressor if regressor is None else regressor
        self.feature_net = feature_net if feature is None else feature
        self.iterations, self.max_condition = int(stn.iterations), float(stn.max_condition)
        size = int(image_size if image_size is not None else stn.image_size)
        self.size = size
        self.register_buffer("grid", normalised_grid(size, size).clone(), persistent=False)  # (3, S*S)
        pixel_H_norm, norm_H_pixel = normalisation_matrices((size, size))
        self.register_buffer("pixel_H_norm", pixel_H_norm.clone(), persistent=False)  # (1, 3, 3)
        self.register_buffer("norm_H_pixel", norm_H_pixel.clone(), persistent=False)  # (1, 3, 3)
        self.register_buffer("eye", torch.eye(3), persistent=False)

    def _warp(self, images: torch.Tensor, H: torch.Tensor) -> torch.Tensor:
        return sample_by_normalised(images, H, self.grid)

    def forward(self, images: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        H, bad = regress_homography(self.regressor, images, self.iterations, self.max_condition, self._warp, self.eye)
        warped = self._warp(images, H)
        pixel = normalised_to_pixel(H, (self.size, self.size), (self.pixel_H_norm, self.norm_H_pixel))
        c = self.feature_net
        embedding = c.forward_graph(warped) if isinstance(c, FeatureNet) else c(warped)
        return embedding, pixel, bad, warped


class CompiledQueryPath:
    """``c(s(query))`` for small CPU batches: :class:`QueryGraph` traced, frozen and optimised by TorchScript.

    ``torch.jit.freeze`` + ``optimize_for_inference`` pre-pack the convolution weights for oneDNN,
    fuse each convolution with its ReLU and keep the feature maps in oneDNN's blocked layout, and the
    whole of ``s()`` and ``c()`` is one graph call: most of the per-op cost of a batch of one goes.
    The result equals the eager networks up to float rounding; this is checked on random images each
    time the graph is built, and the path is given up (``failure`` set, a warning logged, the eager
    path used) if the difference exceeds ``COMPILED_TOLERANCE`` or TorchScript fails.

    The graph holds a copy of the weights: a call rebuilds it when a parameter or buffer of the
    networks has changed since (in place, as an optimiser step or ``load_state_dict`` does, or moved).

    Args:
        feature_net: ``c()``, a :class:`~matl.models.feature.FeatureNet`.
        stn: ``s()``, a :class:`~matl.models.stn.SpatialTransformer`.
        image_size: ``S``.
    """

    def __init__(self, feature_net: nn.Module, stn: SpatialTransformer, image_size: int) -> None:
        self.feature_net, self.stn, self.image_size = feature_net, stn, int(image_size)
        self._tensors = [*stn.parameters(), *stn.buffers(), *feature_net.parameters(), *feature_net.buffers()]
        self._key: list[tuple[int, int]] | None = None
        self._graph: torch.jit.ScriptModule | None = None
        self.failure: str | None = None

    @staticmethod
    def supports(feature_net: nn.Module, stn: nn.Module | None) -> bool:
        """True for the default networks with CPU float32 weights (and int64 counters: batch norm's) when
        oneDNN is there, unless a layer
        whose output depends on the mode (batch norm, dropout) is in training mode."""
        if not isinstance(stn, SpatialTransformer) or not isinstance(feature_net, FeatureNet):
            return False
        modules = (*stn.modules(), *feature_net.modules())
        tensors = (*stn.parameters(), *stn.buffers(), *feature_net.parameters(), *feature_net.buffers())
        return (torch.backends.mkldnn.is_available()
                and not any(m.training for m in modules if isinstance(m, MODAL_LAYERS))
                and all(t.device.type == "cpu" and t.dtype in (torch.float32, torch.int64) for t in tensors))

    def _build(self) -> torch.jit.ScriptModule:
        graph = QueryGraph(self.stn, self.feature_net, self.image_size)
        modes = {m: m.training for m in graph.modules()}
        graph.eval()  # freeze needs eval mode; supports() made sure that changes no output
        try:
            return _optimised_trace(graph, self.image_size)
        finally:
            for module, training in modes.items():
                module.training = training

    def __call__(self, queries: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor] | None:
        """:class:`QueryGraph`'s outputs for ``(B, 3, S, S)`` CPU float32 queries, or None when the
        networks no longer qualify (:meth:`supports`) or building the graph failed (``failure``)."""
        if self.failure is not None:
            return None
        key = weights_key(self._tensors)
        if self._graph is None or key != self._key:
            self._graph = None
            if not self.supports(self.feature_net, self.stn):
                return None
            try:
                with torch.inference_mode(False), torch.no_grad():  # graph constants must be plain tensors
                    self._graph = self._build()
            except Exception as error:  # no TorchScript, or it refused the graph: the eager path still works
                self.failure = f"{type(error).__name__}: {' '.join(str(error).split())[:300]}"
                log.warning("compiled query path unavailable, using the eager networks: %s", self.failure)
                return None
            self._key = key
        return self._graph(queries)


def _optimised_trace(graph: QueryGraph, size: int) -> torch.jit.ScriptModule:
    """Trace, freeze and optimise ``graph`` for inference; check it against the eager module."""
    example = torch.rand(3, 3, size, size, generator=torch.Generator().manual_seed(0))
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*torch.jit.*")
        warnings.filterwarnings("ignore", message=".*TorchScript.*")
        warnings.filterwarnings("ignore", message=".*Converting a tensor to a Python.*")
        compiled = torch.jit.optimize_for_inference(torch.jit.freeze(
            torch.jit.trace(graph, example[:1], check_trace=False)))
    for x in (example[:1], example):  # the traced batch size and another one
        diff = max(float((a.double() - b.double()).abs().max()) for a, b in zip(graph(x), compiled(x), strict=True))
        if not diff <= COMPILED_TOLERANCE:
            raise RuntimeError(f"the compiled graph differs from the eager networks by {diff:.3g}")
    return compiled


class TensorRecognizer(nn.Module):
    """Holds ``c()``, ``s()`` and a gallery's embeddings; answers class and pose for query batches.

    Args:
        anchor_choice: ``feature`` (paper): the anchor is the nearest gallery entry by feature
            distance. ``appearance``: the plane comes from features, then the anchor of that plane
            with the smallest appearance loss to ``s(query)`` is taken (Eq. 3 at test time).
        gallery_features: ``(G, D)`` precomputed ``c(gallery.images)`` (``matl.predict``'s on-disk
            cache); computed here when None.
        search: factory of the gallery search backend, ``factory(features (G, D))`` (see
            :mod:`matl.models.search`); None is exact torch search. Assigning ``gallery_features``
            rebuilds the backend, so the search never sees stale features.
        fast: run queries through the networks' ``infer`` methods when they have one
            (:meth:`matl.models.stn.SpatialTransformer.infer`, :meth:`matl.models.feature.FeatureNet.infer`):
            the same outputs as their ``forward`` up to float rounding, several times faster for one
            query on the CPU (docs/speed.md). False calls ``forward`` (the training code path).
        compiled_max_batch: with ``fast``, CPU batches up to this size use :class:`CompiledQueryPath`
            (0: never). Larger batches, where per-op overhead is amortised, use the eager ``infer``
            methods, so evaluation in batches gives the same numbers as before up to float rounding.
        align: an alignment stage (:class:`matl.models.align.AlignmentStage`) or None. After the search
            (and ``anchor_choice``), ``align(queries, anchor, query_H_anchor, s(queries))`` against the
            selected gallery anchor replaces ``query_H_anchor`` and hence ``query_H_canon``; recognition,
            ``warped`` (``s(query)``, what ``c()`` saw), ``features`` and ``degenerate`` (the STN's) are
            unchanged. Queries without an STN pose are left alone.
    """

    def __init__(self, feature_net: nn.Module, stn: nn.Module | None, gallery: Gallery,
                 anchor_choice: str = "feature", batch_size: int = 512,
                 gallery_features: torch.Tensor | None = None, search: SearchFactory | None = None,
                 fast: bool = True, compiled_max_batch: int = 8, align: nn.Module | None = None) -> None:
        super().__init__()
        if anchor_choice not in ("feature", "appearance"):
            raise ValueError(f"anchor_choice must be 'feature' or 'appearance', got {anchor_choice!r}")
        self.feature_net, self.stn = feature_net, stn
        self.align = align if stn is not None else None
        self.gallery = gallery
        self.anchor_choice = anchor_choice
        self.batch_size = batch_size
        self.fast = fast
        self.compiled_max_batch = int(compiled_max_batch)
        self._compiled: CompiledQueryPath | None = None
        #: optional reduced-precision path (:func:`matl.inference.quantize.quantize_recognizer`), used for every
        #: CPU float32 batch while the weights it was built from are unchanged; None: float32 only
        self.quantized: Any = None
        #: optional onnxruntime path (:mod:`matl.inference.runtime`, ``runtime=onnxruntime``), used for CPU float32
        #: batches (after the int8 path, when both are set); None: torch
        self.onnx: Any = None
        if gallery_features is not None and len(gallery_features) != len(gallery):
            raise ValueError(f"{len(gallery_features)} gallery features for {len(gallery)} gallery images")
        self._search_factory: SearchFactory = search or ExactSearch
        self.gallery_features = (embed(feature_net, gallery.images, batch_size) if gallery_features is None
                                 else gallery_features.to(gallery.images.device))

    @property
    def gallery_features(self) -> torch.Tensor:
        """``(G, D)`` gallery embeddings; assigning them rebuilds the search backend."""
        return self._gallery_features

    @gallery_features.setter
    def gallery_features(self, features: torch.Tensor) -> None:
        self._gallery_features = features
        self.search: GallerySearch = self._search_factory(features)
        self._gallery64: tuple[torch.Tensor, torch.Tensor] | None = None  # float64 copy and squared norms

    def gallery_distances(self, features: torch.Tensor) -> torch.Tensor:
        """``(Q, G)`` float64 L2 distance of each of ``features`` ``(Q, D)`` to every gallery anchor (verification's
        candidates, the per-product distances of the open set); the float64 gallery and its squared norms are
        computed once per gallery."""
        if self._gallery64 is None:
            gallery = self._gallery_features.double()
            self._gallery64 = (gallery, gallery.pow(2).sum(-1))
        return distances(features.double().to(self._gallery64[0].device), *self._gallery64)

    def use_search(self, factory: SearchFactory) -> None:
        """Switch the search backend (e.g. to FAISS for a very large gallery)."""
        self._search_factory = factory
        self.search = factory(self._gallery_features)

    def _compiled_path(self, queries: torch.Tensor) -> CompiledQueryPath | None:
        """The compiled path when it applies to this batch (see ``compiled_max_batch``), else None."""
        if (not self.fast or len(queries) > self.compiled_max_batch or queries.device.type != "cpu"
                or queries.dtype != torch.float32):
            return None
        if self._compiled is None:
            if not CompiledQueryPath.supports(self.feature_net, self.stn):
                return None
            assert isinstance(self.stn, SpatialTransformer)
            self._compiled = CompiledQueryPath(self.feature_net, self.stn, self.gallery.image_size)
        return self._compiled

    @torch.no_grad()
    def embed_queries(self, queries: torch.Tensor
                      ) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor, torch.Tensor]:
        """The networks' part of a query, ``c(s(queries))``: ``(embedding (B, D), query_H_anchor (B, 3, 3)
        pixel or None without an STN, degenerate (B,), warped (B, 3, S, S))``, by the fastest path that applies."""
        quantized = self.quantized
        if (quantized is not None and queries.device.type == "cpu" and queries.dtype == torch.float32
                and quantized.matches()):
            return quantized(queries)
        onnx = self.onnx
        if onnx is not None and queries.device.type == "cpu" and queries.dtype == torch.float32:
            result = onnx(queries)
            if result is not None:
                return result
        compiled = self._compiled_path(queries)
        result = compiled(queries) if compiled is not None else None
        if result is not None:
            return result
        if self.stn is not None:
            out = self.stn.infer(queries) if self.fast and hasattr(self.stn, "infer") else self.stn(queries)
            warped, query_H_anchor, degenerate = out.warped, out.query_H_anchor, out.degenerate
        else:
            warped, query_H_anchor = queries, None
            degenerate = torch.zeros(len(queries), dtype=torch.bool, device=queries.device)
        c = self.feature_net
        features = c.infer(warped) if self.fast and hasattr(c, "infer") else c(warped)
        return features, query_H_anchor, degenerate, warped

    @torch.no_grad()
    def forward(self, queries: torch.Tensor, pose: bool = True) -> Prediction:
        """Class and pose of ``queries`` ``(B, 3, S, S)``; ``pose=False`` leaves ``query_H_canon`` None (a caller that
        replaces ``query_H_anchor``, as :class:`~matl.inference.refine.RefinedRecognizer` does, composes it once)."""
        check_images(queries, "queries", (self.gallery.image_size, self.gallery.image_size))
        g = self.gallery
        features, query_H_anchor, degenerate, warped = self.embed_queries(queries)
        index, distance = self.search.search(features)
        if self.anchor_choice == "appearance" and self.stn is not None:
            N = g.num_anchors
            first = index - g.anchor_index[index]          # anchors of a plane are contiguous
            candidates = first[:, None] + torch.arange(N, device=index.device)
            appearance = anchor_distances(g.images[candidates], warped)
            index = candidates.gather(1, appearance.argmin(1, keepdim=True))[:, 0]
        if self.align is not None and query_H_anchor is not None:
            aligned = self.align.infer(queries, g.images[index], query_H_anchor, warped)
            query_H_anchor = aligned.query_H_anchor
        query_H_canon = None
        if query_H_anchor is not None and pose:
            query_H_canon = compose_query_H_canon(query_H_anchor.double(), g.anchor_H_canon64()[index])
        return Prediction(index, g.object_index[index], g.plane_index[index], g.anchor_index[index], distance,
                          query_H_anchor, query_H_canon, warped, degenerate, features=features)
