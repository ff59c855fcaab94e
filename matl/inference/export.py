"""Exporting the query and gallery networks of a checkpoint as TorchScript, torch.export or ONNX graphs.

The library side of ``python -m matl.export`` (the command and its options: :mod:`matl.export`).
"""

from __future__ import annotations

import json
import logging
import os
import warnings
from collections.abc import Callable
from pathlib import Path
from types import ModuleType
from typing import Any

import torch
from omegaconf import DictConfig
from torch import nn
from torch.overrides import TorchFunctionMode

from matl.utils.errors import MatlError
from matl.utils.io import write_json

log = logging.getLogger(__name__)

FORMATS = ("torchscript", "export", "onnx")
SUFFIXES = {"torchscript": ".pt", "export": ".pt2", "onnx": ".onnx"}
#: output names of the two networks, in order (the ONNX graphs' names too)
GALLERY_OUTPUTS = ("embedding",)
QUERY_OUTPUTS = ("embedding", "query_H_anchor", "degenerate", "warped")
#: the alignment stage's network (a checkpoint with ``model.align``): its inputs, in order, and its output
ALIGN_INPUTS = ("images", "anchors", "stn_query_H_anchor", "warped")
ALIGN_OUTPUTS = ("query_H_anchor",)
#: the visibility network's output (``foreground_net``: the foreground of RGB crops without a mask)
FOREGROUND_OUTPUTS = ("logits",)
#: what an export writes into ``out`` (glob patterns: an earlier export's files are replaced only when asked)
EXPORT_FILES = ("export.json", "gallery_net.*", "query_net.*", "align_net.*", "foreground_net.*")
#: 16 is the first opset with GridSample (the STN's warp); 17 is read by every onnxruntime >= 1.12
ONNX_OPSET = 17
ONNX_INSTALL = 'pip install "onnx>=1.15" "onnxruntime>=1.17" (dependencies of matl)'
#: squarings of the power iteration in :func:`svdvals_3x3`: the largest eigenvalue to < 1 / (e * 2**24) relative
_SQUARINGS = 24


def __getattr__(name: str) -> Any:
    """``QueryNet``: :class:`matl.models.recognizer.QueryGraph`, the ``s()`` + ``c()`` graph that
    ``TensorRecognizer`` itself compiles for single queries, so the exported network and the in-process
    fast path are one piece of code. Imported on first use (matl.models loads kornia; a bad option
    of the CLI is reported before that)."""
    if name == "QueryNet":
        from matl.models.recognizer import QueryGraph

        return QueryGraph
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


# ------------------------------------------------------------------------------------------- ONNX
def require_onnxruntime() -> ModuleType:
    """``onnxruntime`` (with ``onnx``, which the exporter needs), or a one-line error naming the fix."""
    try:
        import onnx  # noqa: F401  (torch.onnx serialises through it)
        import onnxruntime
    except ImportError as error:
        raise MatlError(f"format=onnx needs onnx and onnxruntime ({error.name} is not installed): "
                        f"{ONNX_INSTALL}") from None
    return onnxruntime


def _largest_eigenvalue(A: torch.Tensor) -> torch.Tensor:
    """Largest eigenvalue ``(...,)`` of symmetric positive semi-definite ``(..., 3, 3)`` matrices.

    Power iteration by repeated squaring, ``M <- M @ M / max|M @ M|`` from ``M = A``: after ``k``
    squarings ``M`` is ``A ** (2 ** k)`` up to scale, all but the dominant eigenspace gone, and the
    Rayleigh quotient ``trace(A @ M) / trace(M)`` is the eigenvalue to a relative ``1 / (e * 2 ** k)``
    (whatever the gap to the next eigenvalue; equal eigenvalues are exact). Fixed-size, branch-free
    tensor ops (an ONNX graph has no eigensolver).
    """
    def unit_max(M: torch.Tensor) -> torch.Tensor:
        top = M.abs().amax(dim=(-2, -1), keepdim=True)
        return M / torch.where(top > 0, top, 1.0)

    M = unit_max(A)
    for _ in range(_SQUARINGS):
        M = unit_max(M @ M)
    trace = (M * torch.eye(3, dtype=M.dtype, device=M.device)).sum((-2, -1))  # not diagonal(): an ONNX If node
    return torch.where(trace > 0, (A * M).sum((-2, -1)) / torch.where(trace > 0, trace, 1.0), 0.0)


def _cross(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Cross products of ``(..., 3)`` vectors by their components (``torch.linalg.cross`` has no ONNX export)."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return torch.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], -1)


def svdvals_3x3(H: torch.Tensor) -> torch.Tensor:
    """``torch.linalg.svdvals`` of ``(B, 3, 3)`` matrices, ``(B, 3)`` largest first, as plain tensor ops.

    ONNX has no singular value decomposition; the STN's degeneracy guard
    (:func:`matl.geometry.degenerate_homographies`) needs the largest and the smallest singular value.
    In float64, on ``H`` scaled to a largest entry of 1: ``s1 = sqrt(lmax(H^T H))``; the singular values
    of the adjugate are ``s1 s2, s1 s3, s2 s3``, so ``s1 s2 = sqrt(lmax(adj^T adj))`` and
    ``s3 = |det H| / (s1 s2)`` (relatively accurate however small, unlike an eigenvalue next to
    ``s1 ** 2``); ``lmax`` is :func:`_largest_eigenvalue`. Singular matrices give ``s3 = 0``
    (``s2 = 0`` too at rank 1). Agrees with ``svdvals`` to float rounding (checked in the tests).
    """
    X = H.double()
    scale = X.abs().amax(dim=(-2, -1), keepdim=True)
    X = X / torch.where(scale > 0, scale, 1.0)
    r0, r1, r2 = X[..., 0, :], X[..., 1, :], X[..., 2, :]
    cofactors = torch.stack([_cross(r1, r2), _cross(r2, r0), _cross(r0, r1)], -2)  # rows of the cofactor matrix
    det = (r0 * cofactors[..., 0, :]).sum(-1)
    gram = torch.stack([X.transpose(-2, -1) @ X, cofactors.transpose(-2, -1) @ cofactors], -3)  # (B, 2, 3, 3)
    top = _largest_eigenvalue(gram).clamp_min(0.0).sqrt()                                       # (B, 2)
    s1, s12 = top[..., 0], top[..., 1]
    s2 = torch.where(s1 > 0, s12 / torch.where(s1 > 0, s1, 1.0), 0.0)
    s3 = torch.minimum(torch.where(s12 > 0, det.abs() / torch.where(s12 > 0, s12, 1.0), 0.0), s2)
    return (torch.stack([s1, s2, s3], -1) * scale[..., 0]).to(H.dtype)


class _OnnxTraceable(TorchFunctionMode):
    """While tracing for ONNX: ``torch.linalg.svdvals`` (no ONNX operator) of 3x3 batches as :func:`svdvals_3x3`.

    A torch function mode changes what the trace records, not the module: the eager networks, their
    TorchScript and torch.export graphs keep the LAPACK SVD."""

    def __torch_function__(self, func: Callable[..., Any], types: Any, args: tuple[Any, ...] = (),
                           kwargs: dict[str, Any] | None = None) -> Any:
        kwargs = kwargs or {}
        if func is torch.linalg.svdvals and not kwargs and args[0].shape[-2:] == (3, 3):
            return svdvals_3x3(args[0])
        return func(*args, **kwargs)


class OnnxNetwork:
    """An exported ``.onnx`` network in onnxruntime (CPUExecutionProvider), called like the torch module.

    ``network(images (B, 3, S, S) float32 tensor)`` returns the outputs as CPU tensors: the tuple of
    ``output_names`` (the query network), or the one tensor of a single-output network (the gallery's,
    the alignment stage's). A network of several inputs (the alignment stage's, :data:`ALIGN_INPUTS`)
    takes them in order.

    Args:
        path: the ``.onnx`` file, or its bytes.
        threads: onnxruntime's intra-op threads (None: its default, all cores).
    """

    def __init__(self, path: str | Path | bytes, threads: int | None = None) -> None:
        ort = require_onnxruntime()
        options = ort.SessionOptions()
        if threads is not None:
            options.intra_op_num_threads, options.inter_op_num_threads = int(threads), 1
        model = path if isinstance(path, bytes) else str(path)
        self.session = ort.InferenceSession(model, options, providers=["CPUExecutionProvider"])
        self.input_names = tuple(i.name for i in self.session.get_inputs())
        self.input_name = self.input_names[0]
        self.output_names = tuple(o.name for o in self.session.get_outputs())

    def __call__(self, *inputs: torch.Tensor) -> tuple[torch.Tensor, ...] | torch.Tensor:
        feed = {name: x.detach().to("cpu", torch.float32).contiguous().numpy()
                for name, x in zip(self.input_names, inputs, strict=True)}
        outputs = tuple(torch.from_numpy(o) for o in self.session.run(None, feed))
        return outputs if len(outputs) > 1 else outputs[0]


def _export_onnx(module: nn.Module, example: torch.Tensor | tuple[torch.Tensor, ...], path: Path,
                 outputs: tuple[str, ...], inputs: tuple[str, ...] = ("images",)) -> OnnxNetwork:
    """Write ``module`` as ONNX with a dynamic batch axis; returns it loaded in onnxruntime.

    The TorchScript-based exporter (``dynamo=False``): with torch 2.13 it records the same graph as
    the torch.export-based one (``dynamo=True``, checked: identical outputs) in a few seconds instead
    of a minute, and needs only ``onnx``, where ``dynamo=True`` also needs ``onnxscript``. It is
    deprecated (hence the filtered warning); :class:`_OnnxTraceable` works for both, so switching is
    the one argument and ``dynamic_shapes`` for ``dynamic_axes``.
    """
    require_onnxruntime()
    path.write_bytes(onnx_bytes(module, example, outputs, inputs))
    return OnnxNetwork(path)


def onnx_bytes(module: nn.Module, example: torch.Tensor | tuple[torch.Tensor, ...], outputs: tuple[str, ...],
               inputs: tuple[str, ...] = ("images",)) -> bytes:
    """``module`` as a serialised ONNX model (``inputs`` and ``outputs`` named, a dynamic batch axis on each).

    The TorchScript-based exporter (see :func:`_export_onnx`), ``torch.linalg.svdvals`` recorded as
    :func:`svdvals_3x3`. Needs the ``onnx`` package."""
    import io

    examples = example if isinstance(example, tuple) else (example,)
    axes = {name: {0: "batch"} for name in (*inputs, *outputs)}
    buffer = io.BytesIO()
    with warnings.catch_warnings(), _OnnxTraceable():
        warnings.filterwarnings("ignore", message=".*legacy TorchScript-based ONNX export.*")
        warnings.filterwarnings("ignore", message=".*Converting a tensor to a Python.*")
        warnings.filterwarnings("ignore", category=torch.jit.TracerWarning)
        torch.onnx.export(module, examples, buffer, dynamo=False, input_names=list(inputs),
                          output_names=list(outputs), dynamic_axes=axes, opset_version=ONNX_OPSET)
    return buffer.getvalue()


class AlignGraph(nn.Module):
    """The alignment stage (:class:`matl.models.align.AlignmentStage`) as plain torch ops with no
    batch-size constant and no Python branch on the values, so that it traces into TorchScript,
    ``torch.export`` and ONNX graphs with a dynamic batch axis; equal to ``stage.infer`` up to float rounding
    (checked on every export).

    ``forward(images (B, 3, S, S), anchors (B, 3, S, S), stn_query_H_anchor (B, 3, 3) pixel, warped
    (B, 3, S, S)) -> query_H_anchor (B, 3, 3) pixel``: ``images`` the model-frame queries, ``anchors`` the
    gallery anchor the search found for each, ``stn_query_H_anchor`` and ``warped`` the query network's
    outputs. A query whose residuals are all the identity keeps ``stn_query_H_anchor`` bit for bit.
    """

    def __init__(self, stage: nn.Module, image_size: int | None = None) -> None:
        super().__init__()
        from matl.geometry import normalisation_matrices, normalised_grid

        self.regressor = stage.regressor
        self.iterations, self.max_condition = int(stage.iterations), float(stage.max_condition)
        self.size = int(image_size if image_size is not None else stage.image_size)
        self.register_buffer("grid", normalised_grid(self.size, self.size).clone(), persistent=False)
        pixel_H_norm, norm_H_pixel = normalisation_matrices((self.size, self.size))
        self.register_buffer("pixel_H_norm", pixel_H_norm.clone(), persistent=False)  # (1, 3, 3)
        self.register_buffer("norm_H_pixel", norm_H_pixel.clone(), persistent=False)  # (1, 3, 3)
        self.register_buffer("eye", torch.eye(3), persistent=False)

    def forward(self, images: torch.Tensor, anchors: torch.Tensor, stn_query_H_anchor: torch.Tensor,
                warped: torch.Tensor) -> torch.Tensor:
        from matl.geometry import guard_homographies, normalised_to_pixel, sample_by_normalised, scale_to_unit
        from matl.models.align import square_to_quad

        start = stn_query_H_anchor.to(images.dtype)
        H = scale_to_unit(self.norm_H_pixel @ start @ self.pixel_H_norm)  # pixel -> normalised
        residual = self.eye.expand_as(H)
        current = warped
        for step in range(self.iterations):
            R, _ = guard_homographies(square_to_quad(self.regressor(current, anchors)), self.max_condition, self.eye)
            H, residual = H @ R, residual @ R
            if step + 1 < self.iterations:
                current = sample_by_normalised(images, H, self.grid)
        pixel = normalised_to_pixel(H, (self.size, self.size), (self.pixel_H_norm, self.norm_H_pixel))
        unchanged = (residual == self.eye).flatten(1).all(dim=1)
        return torch.where(unchanged[:, None, None], start, pixel)


# ---------------------------------------------------------------------------------------- export
def _trace(module: nn.Module, example: torch.Tensor | tuple[torch.Tensor, ...], fmt: str, path: Path,
           outputs: tuple[str, ...], inputs: tuple[str, ...] = ("images",)) -> Any:
    """Export ``module`` in ``fmt`` to ``path``; returns the loaded exported module (callable)."""
    module.eval()
    examples = example if isinstance(example, tuple) else (example,)
    if fmt == "onnx":
        return _export_onnx(module, examples, path, outputs, inputs)
    if fmt == "torchscript":
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message=".*torch.jit.trace.*deprecated")
            warnings.filterwarnings("ignore", message=".*Converting a tensor to a Python.*")
            warnings.filterwarnings("ignore", category=torch.jit.TracerWarning)  # constants (corners, matrices)
            traced = torch.jit.trace(module, examples, check_trace=False)
        torch.jit.save(traced, str(path))
        return torch.jit.load(str(path))
    batch = torch.export.Dim("batch", min=1, max=4096)
    program = torch.export.export(module, examples, dynamic_shapes=tuple({0: batch} for _ in examples))
    with warnings.catch_warnings():  # torch's own archive code warns about CPU weights it handles fine
        warnings.filterwarnings("ignore", message=".*No complete tensor found")
        torch.export.save(program, str(path))
        return torch.export.load(str(path)).module()


def _max_diffs(eager: Any, exported: Any, names: tuple[str, ...]) -> dict[str, float]:
    """Largest difference per output between (tuples of) eager and exported outputs, absolute where the eager
    value is within [-1, 1] and relative to it beyond (a pixel homography's entries reach ~100, where float32
    rounds at ~1e-5); inf on a shape mismatch (booleans compare as 0 / 1)."""
    eager = eager if isinstance(eager, tuple) else (eager,)
    exported = exported if isinstance(exported, tuple) else (exported,)
    diffs = {}
    for name, a, b in zip(names, eager, exported, strict=True):
        if a.shape != b.shape:
            diffs[name] = float("inf")
        else:
            a, b = a.double(), b.double()
            diffs[name] = float(((a - b).abs() / a.abs().clamp(min=1.0)).max()) if a.numel() else 0.0
    return diffs


def _fixed_anchor_matrices(num_anchors: int, image_size: int) -> list[list[list[float]]]:
    """``anchor_k_H_canon`` of the fixed anchors, ``N`` pixel 3x3 matrices as nested lists."""
    from matl.geometry import anchor_H_canon

    matrices = anchor_H_canon(num_anchors, (image_size, image_size), torch.float64).tolist()
    return [[[round(v, 12) + 0.0 for v in row] for row in H] for H in matrices]  # cos(90 deg) as 0, not 6e-17


def deployment_notes(fmt: str, image_size: int, num_anchors: int | None, has_pose: bool,
                     max_condition: float | None = None, has_align: bool = False,
                     foreground_size: int | None = None) -> dict[str, Any]:
    """What ``export.json`` tells a user of the exported files alone (C++, ROS): how to load them, what
    goes in, what comes out, and how recognition, pose and original-image pixels follow (``has_align``:
    the checkpoint's alignment stage is ``align_net``, between the search and the pose; ``foreground_size``: the
    working size of ``foreground_net``, the visibility network, or None without one)."""
    S = int(image_size)
    notes: dict[str, Any] = {
        "inputs": f"float32 (B, 3, S, S) RGB in [0, 1] (row-major, channels first), S = image_size = {S}; "
                  "background 0 (foreground-segmented); any batch size B >= 1",
        "to_model_frame": "matl.data.image_files.fit_to_model: an h x w image is resized, keeping its aspect, "
                          "so its longer side spans fill * S pixels (fill: predict's gallery_fill / query_fill, "
                          "default 1; the synthetic catalogs frame planes at 0.6): new_w = min(S, max(1, "
                          "round(w * s))), new_h likewise, s = fill * S / max(h, w); antialiased bilinear "
                          "(half-pixel centres), clamped to [0, 1]; then pasted at left = (S - new_w) // 2, "
                          "top = (S - new_h) // 2 on zeros",
        "model_H_file": "file pixel -> model pixel: [[new_w / w, 0, 0.5 * new_w / w - 0.5 + left], "
                        "[0, new_h / h, 0.5 * new_h / h - 0.5 + top], [0, 0, 1]]",
        "gallery_net": "(B, 3, S, S) -> embedding (B, D): c(anchor image)",
        "gallery": "per plane: its canonical image fitted to the model frame (8-bit quantised: round(255 x) / 255), "
                   "then each anchor k = 0..N-1 warped from it by anchor_k_H_canon (bilinear, zeros outside: "
                   "anchor(x) = canon(inv(anchor_k_H_canon) x)); embed all P * N anchors once",
        "recognition": "the gallery anchor whose embedding is nearest (L2) to the query's embedding (paper Sec. "
                       "4.5); its plane and object are the answer",
        "pixel_convention": "pixel homographies on model-frame pixels, (0, 0) = centre of the top-left pixel, "
                            "x right, y down, H[2, 2] = 1 (docs/design.md)",
    }
    if num_anchors is not None:
        notes["anchors"] = (f"anchor k = canonical image rotated by k * 360 / N degrees (N = {num_anchors}) about "
                            f"the image centre ((S - 1) / 2, (S - 1) / 2), counter-clockwise on screen: "
                            "anchor_k_H_canon = [[c, s, tx], [-s, c, ty], [0, 0, 1]], c = cos, s = sin of the "
                            "angle, tx = cx - c cx - s cy, ty = cy + s cx - c cy")
        notes["anchor_k_H_canon"] = _fixed_anchor_matrices(num_anchors, S)
    if has_pose:
        notes["query_net"] = ("(B, 3, S, S) -> embedding (B, D), query_H_anchor (B, 3, 3) float32 pixel homography "
                              "(anchor frame -> query: warped(x) = query(query_H_anchor x)), degenerate (B,) bool, "
                              "warped (B, 3, S, S) (the query in its anchor's frame)")
        notes["pose"] = ("query_H_canon = query_H_anchor @ anchor_k_H_canon of the nearest anchor k (in float64, "
                         "then divided by its [2, 2]): maps canonical model pixels to query model pixels")
        if has_align:
            notes["align_net"] = ("(images (B, 3, S, S), anchors (B, 3, S, S), stn_query_H_anchor (B, 3, 3), warped "
                                  "(B, 3, S, S)) -> query_H_anchor (B, 3, 3): the checkpoint's alignment stage; after "
                                  "the search, feed the query, the image of the nearest gallery anchor, and the "
                                  "query_net's query_H_anchor and warped; its query_H_anchor replaces the query_net's "
                                  "in the pose (without it the pose is the STN's alone, several times less accurate)")
            notes["pose"] = ("query_H_canon = query_H_anchor @ anchor_k_H_canon of the nearest anchor k, "
                             "query_H_anchor being align_net's (in float64, then divided by its [2, 2]): maps "
                             "canonical model pixels to query model pixels")
        limit = f"{max_condition:g}" if max_condition is not None else "max_condition"
        notes["degenerate"] = (f"true: the STN's homography was unusable (non-finite, or a condition number >= {limit} "
                               "in normalised coordinates) and was replaced by the identity; the pose is then not an "
                               "estimate")
        notes["pose_in_files"] = ("query_file_H_gallery_file = inv(model_H_file of the query) @ query_H_canon @ "
                                  "model_H_file of the gallery image (matl.data.image_files.pose_in_files); "
                                  "warping the gallery file by it (cv2.warpPerspective) lands on the query file")
    else:
        notes["query_net"] = "(B, 3, S, S) -> embedding (B, D) (no STN: no pose)"
    if foreground_size is not None:
        F = int(foreground_size)
        notes["foreground_net"] = (f"(B, 3, {F}, {F}) -> logits (B, 1, {F}, {F}): an RGB crop without a mask (a "
                                   f"detector's box, float32 in [0, 1]) resized to {F} x {F} (area averaging, the "
                                   "aspect not kept); sigmoid(logits) is the probability that a pixel shows the "
                                   "visible print of the crop's target product (background, neighbours and occluders "
                                   "out). "
                                   "Resize the logits back to the crop (bilinear), keep the pixels above 0.5 in the "
                                   "component overlapping the crop's centre, and multiply the crop by that mask: the "
                                   "query the other networks take (background 0). matl's foreground=learned adds "
                                   "GrabCut started from this probability (docs/usage.md)")
    if fmt == "onnx":
        notes["runtime"] = (f"ONNX opset {ONNX_OPSET}, input 'images', outputs "
                            f"{list(QUERY_OUTPUTS if has_pose else GALLERY_OUTPUTS)} (gallery_net: ['embedding']"
                            + (f"; align_net: inputs {list(ALIGN_INPUTS)}, output {list(ALIGN_OUTPUTS)}" if has_align
                               else "")
                            + (f"; foreground_net: {list(FOREGROUND_OUTPUTS)}" if foreground_size is not None else "")
                            + "), batch axis dynamic; onnxruntime (C++: Ort::Session) with the CPUExecutionProvider "
                            "is what the export is checked with; scripts/onnx_predict_example.py is the whole query "
                            "path with numpy, OpenCV and onnxruntime alone")
    return notes


@torch.no_grad()
def export_inference(feature_net: nn.Module, stn: nn.Module | None, image_size: int, out_dir: str | Path,
                     fmt: str = "torchscript", tolerance: float = 5e-4, check_batches: tuple[int, ...] = (1, 3),
                     meta: dict[str, Any] | None = None, seed: int = 0,
                     num_anchors: int | None = None, align: nn.Module | None = None,
                     foreground: nn.Module | None = None) -> dict[str, Any]:
    """Export the gallery and query networks (and the alignment stage, the visibility network), check them against
    the eager ones, write ``export.json``.

    The files are written to a temporary folder inside ``out_dir`` and moved into it only once every check
    has passed: a failed export leaves ``out_dir`` as it was.

    Args:
        feature_net: ``c()`` (eval mode is set here).
        stn: ``s()``, or None for a model without pose (the query net is then ``c()`` alone and returns
            only the embedding).
        image_size: ``S``.
        out_dir: destination folder (created).
        fmt: ``torchscript``, ``export`` or ``onnx`` (run in onnxruntime for the check).
        tolerance: largest accepted difference between exported and eager outputs, absolute within [-1, 1]
            and relative beyond (5e-4: a trained 100 px model differs by ~3e-5 in float32 rounding alone; the
            pixel homography's entries, up to ~100, are compared relative to their size, and s()'s warp of the
            random check images moves by that rounding times the noise's gradient: up to ~1.4e-4).
        check_batches: batch sizes checked (random images, and the same images brightened), so a
            batch size baked into the export would be caught.
        meta: extra fields for ``export.json`` (N, checkpoint, ...).
        num_anchors: ``N`` of the fixed anchors, for their matrices in ``export.json`` (None: left out).
        align: the checkpoint's alignment stage (``model.align``) or None: exported as ``align_net``
            (:class:`AlignGraph`), run after the search on the query network's pose against the anchor found.
        foreground: a visibility network (:class:`matl.models.visibility.VisibilityNet`, ``foreground=learned``'s)
            or None: exported as ``foreground_net``, ``(B, 3, F, F)`` crops at its working size ``F`` -> logits.
    Returns:
        ``export.json``'s content; ``max_abs_diff`` per network, ``max_abs_diff_by_output`` per output.
    Raises:
        MatlError: unknown format, ``onnx`` without onnxruntime, or an output that differs by more than
            ``tolerance``.
    """
    import shutil
    import tempfile

    if fmt not in FORMATS:
        raise MatlError(f"format={fmt} is invalid: use {' or '.join(FORMATS)}")
    if fmt == "onnx":
        require_onnxruntime()  # before any work
    from matl.models.recognizer import QueryGraph

    out = Path(out_dir).expanduser()
    out.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=".matl_export.", dir=out))
    try:
        info = _export_checked(feature_net, stn, align if stn is not None else None, image_size, staging, fmt,
                               tolerance, check_batches, seed, QueryGraph)
        if foreground is not None:
            info = _with_foreground(info, foreground, staging, fmt, tolerance, check_batches, seed)
        info.update(deployment_notes(fmt, image_size, num_anchors, stn is not None,
                                     getattr(stn, "max_condition", None), "align_net" in info["files"],
                                     None if foreground is None else int(foreground.size)))
        info.update(meta or {})
        write_json(staging / "export.json", info)
        for name in [*info["files"].values(), "export.json"]:  # each a rename within out: complete files only
            os.replace(staging / name, out / name)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return info


def _export_checked(feature_net: nn.Module, stn: nn.Module | None, align: nn.Module | None, image_size: int,
                    folder: Path, fmt: str, tolerance: float, check_batches: tuple[int, ...], seed: int,
                    query_graph: type[nn.Module]) -> dict[str, Any]:
    """:func:`export_inference`'s networks, written into ``folder`` and checked; ``export.json``'s measured part."""
    feature_net = feature_net.eval().cpu()
    query_net: nn.Module = query_graph(stn.eval().cpu(), feature_net) if stn is not None else feature_net
    query_outputs = QUERY_OUTPUTS if stn is not None else GALLERY_OUTPUTS
    g = torch.Generator().manual_seed(seed)
    example = torch.rand(2, 3, image_size, image_size, generator=g)

    files = {"gallery_net": folder / f"gallery_net{SUFFIXES[fmt]}", "query_net": folder / f"query_net{SUFFIXES[fmt]}"}
    exported = {"gallery_net": _trace(feature_net, example, fmt, files["gallery_net"], GALLERY_OUTPUTS),
                "query_net": _trace(query_net, example, fmt, files["query_net"], query_outputs)}
    if align is not None:
        align = align.eval().cpu()
        files["align_net"] = folder / f"align_net{SUFFIXES[fmt]}"
        stn_out = stn(example)
        exported["align_net"] = _trace(AlignGraph(align, image_size), (example, example.flip(0), stn_out.query_H_anchor,
                                                                     stn_out.warped),
                                       fmt, files["align_net"], ALIGN_OUTPUTS, ALIGN_INPUTS)

    def eager_query(x: torch.Tensor) -> tuple[torch.Tensor, ...] | torch.Tensor:
        if stn is None:
            return feature_net(x)
        result = stn(x)
        return feature_net(result.warped), result.query_H_anchor, result.degenerate, result.warped

    by_output = {"gallery_net": dict.fromkeys(GALLERY_OUTPUTS, 0.0), "query_net": dict.fromkeys(query_outputs, 0.0)}
    if align is not None:
        by_output["align_net"] = dict.fromkeys(ALIGN_OUTPUTS, 0.0)
    for batch in check_batches:
        images = torch.rand(batch, 3, image_size, image_size, generator=g)
        for x in (images, (images * 1.5).clamp(0, 1)):
            checks = [("gallery_net", _max_diffs(feature_net(x), exported["gallery_net"](x), GALLERY_OUTPUTS)),
                      ("query_net", _max_diffs(eager_query(x), exported["query_net"](x), query_outputs))]
            if align is not None:  # against other images as anchors, from s()'s own pose
                anchors = torch.rand(batch, 3, image_size, image_size, generator=g)
                result = stn(x)
                args = (x, anchors, result.query_H_anchor, result.warped)
                checks.append(("align_net", _max_diffs(align.infer(*args).query_H_anchor,
                                                       exported["align_net"](*args), ALIGN_OUTPUTS)))
            for name, diffs in checks:
                for output, diff in diffs.items():
                    by_output[name][output] = max(by_output[name][output], diff)
    for name, diffs in by_output.items():
        for output, diff in diffs.items():
            if not diff <= tolerance:
                raise MatlError(f"exported {name} output {output} differs from the eager model by {diff:.3g} > "
                                f"tolerance {tolerance:g} ({', '.join(f'{k} {v:.3g}' for k, v in diffs.items())})")

    embedding_dim = int(feature_net(example[:1]).shape[1])
    info: dict[str, Any] = {
        "format": fmt, "files": {k: v.name for k, v in files.items()}, "image_size": int(image_size),
        "embedding_dim": embedding_dim, "torch": torch.__version__,
        "max_abs_diff": {name: max(diffs.values()) for name, diffs in by_output.items()},
        "max_abs_diff_by_output": by_output, "tolerance": tolerance, "checked_batch_sizes": list(check_batches),
    }
    if fmt == "onnx":
        info["onnxruntime"] = require_onnxruntime().__version__
        info["checked_with"] = "onnxruntime CPUExecutionProvider"
    return info


def _with_foreground(info: dict[str, Any], foreground: nn.Module, folder: Path, fmt: str, tolerance: float,
                     check_batches: tuple[int, ...], seed: int) -> dict[str, Any]:
    """``info`` with the visibility network ``foreground`` written into ``folder`` as ``foreground_net`` and checked
    against the eager one (logits, ``tolerance`` absolute, as every output in [-1, 1] is, else relative)."""
    foreground = foreground.eval().cpu()
    size = int(foreground.size)
    g = torch.Generator().manual_seed(seed + 1)
    path = folder / f"foreground_net{SUFFIXES[fmt]}"
    exported = _trace(foreground, torch.rand(2, 3, size, size, generator=g), fmt, path, FOREGROUND_OUTPUTS)
    worst = 0.0
    with torch.no_grad():
        for batch in check_batches:
            x = torch.rand(batch, 3, size, size, generator=g)
            worst = max(worst, _max_diffs(foreground(x), exported(x), FOREGROUND_OUTPUTS)["logits"])
    if not worst <= tolerance:
        raise MatlError(f"exported foreground_net output logits differs from the eager network by {worst:.3g} > "
                        f"tolerance {tolerance:g}")
    info = dict(info)
    info["files"] = {**info["files"], "foreground_net": path.name}
    info["max_abs_diff"] = {**info["max_abs_diff"], "foreground_net": worst}
    info["max_abs_diff_by_output"] = {**info["max_abs_diff_by_output"], "foreground_net": {"logits": worst}}
    return info


def export(cfg: DictConfig) -> dict[str, Any]:
    """``matl.export``'s work for a composed ``conf/export.yaml``: ``ckpt=`` (a path, ``pretrained`` or
    ``pretrained_fast``), ``format`` and ``out`` checked before anything is traced."""
    from matl.models.checkpoint import CKPT_FIX, load_embedding_model, resolve_ckpt_option
    from matl.utils.io import check_output_folder, overwrite_option

    if cfg.get("ckpt") in (None, ""):
        raise MatlError("ckpt=... is required: python -m matl.export ckpt=<path>|pretrained|pretrained_fast out=<dir>")
    resolve_ckpt_option(cfg)
    if not Path(str(cfg.ckpt)).expanduser().is_file():  # before any work: a typo costs a second
        raise MatlError(f"checkpoint {cfg.ckpt} not found: {CKPT_FIX}")
    if str(cfg.format) not in FORMATS:
        raise MatlError(f"format={cfg.format} is invalid: use {' or '.join(FORMATS)}")
    if str(cfg.format) == "onnx":
        require_onnxruntime()
    check_output_folder(cfg.out, EXPORT_FILES, "out", overwrite_option(cfg))
    model, size, num_anchors, sha = load_embedding_model(cfg.ckpt)
    stn = getattr(model, "stn", None)
    align = getattr(model, "align", None) if stn is not None else None
    meta = {"N": num_anchors, "checkpoint": str(cfg.ckpt), "checkpoint_sha256": sha,
            "fixed_anchors": "anchor k = canonical image rotated by k * 360 / N degrees about the centre"}
    if align is not None:
        meta["alignment_stage"] = ("exported as align_net: run it after the search on the query network's "
                                   "query_H_anchor against the anchor found; its query_H_anchor is the pose")
    foreground = None
    if cfg.get("foreground_net") not in (None, False, "none"):
        from matl.models.visibility import load_visibility_net

        shipped = cfg.foreground_net in (True, "shipped")
        foreground = load_visibility_net(None if shipped else str(cfg.foreground_net))
        meta["foreground_weights"] = "shipped" if shipped else str(cfg.foreground_net)
    info = export_inference(model.feature_net, stn, size, cfg.out, str(cfg.format), float(cfg.tolerance), meta=meta,
                            num_anchors=num_anchors, align=align, foreground=foreground)
    log.info("export: %s", json.dumps(info))
    return info
