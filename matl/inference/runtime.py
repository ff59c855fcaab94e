"""The query networks in onnxruntime (``runtime=onnxruntime``): ``c(s(query))`` for CPU queries.

What a query costs at a batch of one on the CPU is the convolutions and the per-op overhead around
them. onnxruntime's CPU kernels run ``s()``'s regressor and ``c()`` about twice as fast as torch's
oneDNN path at these sizes (docs/speed.md), so :class:`OnnxRuntimeQueryPath` runs each network as an
ONNX graph in onnxruntime and does the rest of ``s()`` outside any graph:

* the regressor (an ``(B, S, S, 3)`` channels-last graph: the warps below hand it images in that layout)
  and ``c()`` (``(B, 3, S, S)``, ``FeatureNet.forward_graph``) are exported from the model's own modules
  in memory (:func:`matl.inference.export.onnx_bytes`) when the path is first used, and again whenever a
  weight changes (version counters, as :class:`~matl.models.recognizer.CompiledQueryPath`);
* ``s()``'s loop (:func:`matl.models.stn.regress_homography`: regress, warp, re-regress, compose), its
  degeneracy guard and the final warp run per query in NumPy (float64 matrices) and OpenCV:
  ``cv2.warpPerspective`` (bilinear, zeros outside) of the channels-last query by
  ``pixel_H_norm @ query_H_anchor_norm @ norm_H_pixel`` samples where ``grid_sample(align_corners=True)``
  does, at a fraction of its cost; OpenCV quantises sample positions to 1/32 px, which moves the poses
  by about 1e-4 px (``tests/inference/test_runtime.py`` holds them to torch's within 1e-3 px);
* search, pose and refinement are the recognizer's own, unchanged.

Built at the first call; the regressor and ``c()`` are checked against the torch modules on random
images (:data:`TOLERANCE`). If onnxruntime or the export is missing or fails, the path records why
(``failure``) and the recognizer answers with torch.
"""

from __future__ import annotations

import logging
from typing import Any

import cv2
import numpy as np
import torch
from torch import nn

from matl.geometry import degenerate_matrix, normalisation_matrices, sample_by_pixels
from matl.models.feature import FeatureNet
from matl.models.recognizer import MODAL_LAYERS, weights_key
from matl.models.stn import HomographyRegressor, SpatialTransformer

__all__ = ["RUNTIMES", "OnnxRuntimeQueryPath", "apply_runtime", "apply_runtime_option", "runtime_option",
           "runtime_path"]

log = logging.getLogger(__name__)

#: values of the ``runtime`` option
RUNTIMES = ("torch", "onnxruntime")
#: largest difference accepted between a network in onnxruntime and the torch module when the path is built
TOLERANCE = 1e-4


class _ChannelsLast(nn.Module):
    """``module`` on ``(B, S, S, C)`` images (the export's wrapper: the graph transposes its input)."""

    def __init__(self, module: nn.Module) -> None:
        super().__init__()
        self.module = module

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        return self.module(images.permute(0, 3, 1, 2))


class _Embedding(nn.Module):
    """``c()`` as its inference graph (``FeatureNet.forward_graph``)."""

    def __init__(self, feature_net: FeatureNet) -> None:
        super().__init__()
        self.feature_net = feature_net

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        return self.feature_net.forward_graph(images)


def unsupported(feature_net: nn.Module, stn: nn.Module | None) -> str | None:
    """Why the path cannot serve these networks, or None: the default networks (``SpatialTransformer`` with a
    ``HomographyRegressor``, ``FeatureNet``) with CPU float32 weights, no mode-dependent layer in training mode."""
    if not isinstance(stn, SpatialTransformer) or not isinstance(stn.regressor, HomographyRegressor):
        return f"{type(stn).__name__} is not an STN with MATL's homography regressor"
    if not isinstance(feature_net, FeatureNet):
        return f"{type(feature_net).__name__} is not MATL's feature net"
    modules = (*stn.modules(), *feature_net.modules())
    if any(m.training for m in modules if isinstance(m, MODAL_LAYERS)):
        return "batch norm or dropout in training mode"
    tensors = (*stn.parameters(), *stn.buffers(), *feature_net.parameters(), *feature_net.buffers())
    if not all(t.device.type == "cpu" and t.dtype in (torch.float32, torch.int64) for t in tensors):
        return "the networks' weights are not CPU float32"
    return None


class OnnxRuntimeQueryPath:
    """``c(s(queries))`` with the networks in onnxruntime and ``s()``'s warps in OpenCV (module docstring).

    ``path(queries (B, 3, S, S) CPU float32) -> (embedding (B, D), query_H_anchor (B, 3, 3) float32 pixel,
    degenerate (B,) bool, warped (B, 3, S, S))``, the outputs of
    :meth:`~matl.models.recognizer.TensorRecognizer.embed_queries`; None when the networks no longer qualify or
    the graphs could not be built (``failure`` says why).

    Args:
        feature_net: ``c()``, a :class:`~matl.models.feature.FeatureNet`.
        stn: ``s()``, a :class:`~matl.models.stn.SpatialTransformer`.
        image_size: ``S``.
        threads: onnxruntime's intra-op threads; None: torch's thread count at each call (sessions are kept per
            count, so ``torch.set_num_threads`` applies to this path too).
    """

    def __init__(self, feature_net: nn.Module, stn: nn.Module, image_size: int, threads: int | None = None) -> None:
        self.feature_net, self.stn, self.image_size = feature_net, stn, int(image_size)
        self.threads = None if threads is None else int(threads)
        self._tensors = [*stn.parameters(), *stn.buffers(), *feature_net.parameters(), *feature_net.buffers()]
        self._key: list[tuple[int, int]] | None = None
        self._graphs: tuple[bytes, bytes] | None = None
        self._sessions: dict[int, tuple[Any, Any]] = {}
        self.failure: str | None = None
        pixel_H_norm, norm_H_pixel = normalisation_matrices((self.image_size, self.image_size), dtype=torch.float64)
        self._pixel_H_norm, self._norm_H_pixel = pixel_H_norm[0].numpy(), norm_H_pixel[0].numpy()

    # ------------------------------------------------------------------------------ graphs
    def _export(self) -> tuple[bytes, bytes]:
        """The regressor (channels-last input) and ``c()`` as ONNX bytes, each checked against its module."""
        from matl.inference.export import onnx_bytes, require_onnxruntime

        require_onnxruntime()
        S = self.image_size
        example = torch.rand(3, 3, S, S, generator=torch.Generator().manual_seed(0))
        regressor, embedding = _ChannelsLast(self.stn.regressor).eval(), _Embedding(self.feature_net).eval()
        with torch.inference_mode(False), torch.no_grad():
            graphs = (onnx_bytes(regressor, example[:1].permute(0, 2, 3, 1), ("query_H_anchor",)),
                      onnx_bytes(embedding, example[:1], ("embedding",)))
            expected = (regressor(example.permute(0, 2, 3, 1)), embedding(example))
        sessions = self._new_sessions(graphs, 1)
        inputs = (np.ascontiguousarray(example.permute(0, 2, 3, 1).numpy()), example.numpy())
        for name, session, x, want in zip(("regressor", "c()"), sessions, inputs, expected, strict=True):
            diff = float(np.abs(session.run(None, {"images": x})[0] - want.numpy()).max())
            if not diff <= TOLERANCE:
                raise RuntimeError(f"{name} in onnxruntime differs from torch by {diff:.3g}")
        return graphs

    @staticmethod
    def _new_sessions(graphs: tuple[bytes, bytes], threads: int) -> tuple[Any, Any]:
        import onnxruntime as ort

        options = ort.SessionOptions()
        options.intra_op_num_threads, options.inter_op_num_threads = int(threads), 1
        # pool threads spin while a call runs (a sleeping thread's wake-up costs more than a small convolution) and
        # stop when it returns: the refinement and OpenCV run between the calls, and a thread still spinning takes a
        # core from them (2 threads on 2 cores: a refined query 2x slower)
        options.add_session_config_entry("session.intra_op.allow_spinning", "1")
        options.add_session_config_entry("session.force_spinning_stop", "1")
        return tuple(ort.InferenceSession(g, options, providers=["CPUExecutionProvider"]) for g in graphs)

    def sessions(self) -> tuple[Any, Any] | None:
        """The two onnxruntime sessions at the current thread count, (re)built as needed; None on failure."""
        if self.failure is not None:
            return None
        key = weights_key(self._tensors)
        if self._graphs is None or key != self._key:
            self._graphs, self._sessions = None, {}
            reason = unsupported(self.feature_net, self.stn)
            if reason is not None:
                return None
            try:
                self._graphs = self._export()
            except Exception as error:  # onnx / onnxruntime missing, or an operator refused: torch answers
                self.failure = f"{type(error).__name__}: {' '.join(str(error).split())[:300]}"
                log.warning("onnxruntime query path unavailable, using torch: %s", self.failure)
                return None
            self._key = key
        threads = self.threads if self.threads is not None else torch.get_num_threads()
        if threads not in self._sessions:
            self._sessions[threads] = self._new_sessions(self._graphs, threads)
        return self._sessions[threads]

    # ------------------------------------------------------------------------------ queries
    def _warp(self, image: np.ndarray, query_H_anchor_norm: np.ndarray) -> np.ndarray:
        """``out(x) = image(query_H_anchor_norm @ x)`` of a ``(S, S, 3)`` image, bilinear, zeros outside."""
        M = self._pixel_H_norm @ query_H_anchor_norm @ self._norm_H_pixel
        return sample_by_pixels(image, M, (self.image_size, self.image_size))

    def _guard(self, H: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:func:`matl.geometry.guard_homographies` of ``(B, 3, 3)`` float64 matrices."""
        limit = float(self.stn.max_condition)
        bad = np.array([degenerate_matrix(h, limit) for h in H])
        if bad.any():  # a kept matrix is finite
            H = np.where(bad[:, None, None], np.eye(3), H)
        return H, bad

    @torch.no_grad()
    def __call__(self, queries: torch.Tensor
                 ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor] | None:
        sessions = self.sessions()
        if sessions is None:
            return None
        regressor, embedding = sessions
        x = np.ascontiguousarray(queries.detach().numpy())
        images = [cv2.merge((q[0], q[1], q[2])) for q in x]  # channels-last, for OpenCV and the regressor graph
        H = regressor.run(None, {"images": _batch(images)})[0]
        H = H.astype(np.float64)
        for _ in range(int(self.stn.iterations) - 1):
            warped = _batch([self._warp(image, h) for image, h in zip(images, H, strict=True)])
            H = H @ regressor.run(None, {"images": warped})[0].astype(np.float64)
        H, bad = self._guard(H)
        warped = _batch([self._warp(image, h) for image, h in zip(images, H, strict=True)])
        warped = np.ascontiguousarray(warped.transpose(0, 3, 1, 2))  # channels first, for c()
        features = embedding.run(None, {"images": warped})[0]
        pixel = self._pixel_H_norm @ H @ self._norm_H_pixel
        pixel = (pixel / pixel[:, 2:, 2:]).astype(np.float32)
        return (torch.from_numpy(features), torch.from_numpy(pixel), torch.from_numpy(bad),
                torch.from_numpy(warped))


def _batch(images: list[np.ndarray]) -> np.ndarray:
    """``(B, ...)`` of ``B`` same-shaped arrays (one query: a view, no copy)."""
    return images[0][None] if len(images) == 1 else np.stack(images)


# ------------------------------------------------------------------------------ the config option
def runtime_option(cfg: Any) -> str:
    """The ``runtime`` value of an eval / predict / unseen / bench config (missing: ``torch``), checked."""
    from matl.utils.errors import MatlError

    value = cfg.get("runtime", "torch") if hasattr(cfg, "get") else "torch"
    value = "torch" if value is None else str(value)
    if value not in RUNTIMES:
        raise MatlError(f"runtime={value} is invalid: use {' or '.join(RUNTIMES)}")
    return value


def runtime_path(recognizer: Any) -> tuple[OnnxRuntimeQueryPath | None, str | None]:
    """The onnxruntime query path for MATL's ``recognizer`` (its networks exported and checked), or None and why
    not: a recognizer without MATL's networks (the STN classifier, a keypoint baseline), one on a GPU, or an
    export or onnxruntime failure. The path depends on the networks only: a recognizer rebuilt over another
    gallery of the same model can take the same path (``recognizer.onnx = path``)."""
    if not hasattr(recognizer, "feature_net") or not hasattr(recognizer, "embed_queries"):
        return None, f"runtime=onnxruntime applies to MATL's recognizer, not to {type(recognizer).__name__}"
    device = recognizer.gallery.images.device
    if device.type != "cpu":
        return None, f"runtime=onnxruntime serves CPU queries; this recognizer is on {device}"
    reason = unsupported(recognizer.feature_net, getattr(recognizer, "stn", None))
    if reason is None:
        path = OnnxRuntimeQueryPath(recognizer.feature_net, recognizer.stn, recognizer.gallery.image_size)
        if path.sessions() is not None:
            return path, None
        reason = path.failure or "the networks do not qualify"
    log.warning("runtime=onnxruntime unavailable, using torch: %s", reason)
    return None, reason


def apply_runtime(recognizer: Any, runtime: str) -> str | None:
    """Give ``recognizer`` the query path of ``runtime`` in place (``torch``: none; ``onnxruntime``:
    :func:`runtime_path`'s). Returns None when it is in place, else why not (the recognizer answers with torch)."""
    path, reason = runtime_path(recognizer) if runtime == "onnxruntime" else (None, None)
    if hasattr(recognizer, "onnx"):
        recognizer.onnx = path
    return reason


def apply_runtime_option(recognizer: Any, cfg: Any) -> dict[str, Any]:
    """``runtime=`` of an entry point's config applied to ``recognizer``; ``{"runtime", "runtime_fallback"}`` for
    the run's record (``runtime`` is ``torch`` when the onnxruntime path could not be built)."""
    value = runtime_option(cfg)
    reason = apply_runtime(recognizer, value)
    return {"runtime": "torch" if reason else value, "runtime_fallback": reason}
