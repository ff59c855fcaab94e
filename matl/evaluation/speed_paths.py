"""The query paths ``matl.bench`` times beside ``query_ms.matl`` on the same queries: torch's compiled graph under
``runtime=onnxruntime``, the int8 path (``quantize=int8``), the exported ONNX networks, and the extra keypoint
baselines of ``bench.baselines``; each at every thread count, kept at its fastest (what each number means:
:mod:`matl.bench`, docs/speed.md).
"""

from __future__ import annotations

import logging
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig, ListConfig, OmegaConf

from matl.utils.errors import MatlError
from matl.utils.timing import median_query_ms, synced

log = logging.getLogger(__name__)


def measure_torch_runtime(recognizer: Any, refined: Any, queries: torch.Tensor, warmup: int, counts: list[int],
                          device: torch.device) -> dict[str, Any]:
    """With ``runtime=onnxruntime`` in place: ``query_ms.matl_torch`` (and ``matl_torch_refine``), the same
    recognizer and queries with the query networks in torch (the compiled graph), each at every thread count and
    kept at its fastest; empty otherwise."""
    path = getattr(recognizer, "onnx", None)
    if path is None:
        return {"query_ms": {}}
    recognizer.onnx = None  # restored below
    try:
        by_threads = {str(n): median_query_ms(synced(recognizer, device), queries, warmup, n) for n in counts}
        threads = int(min(by_threads, key=lambda n: by_threads[n]))
        query_ms = {"matl_torch": by_threads[str(threads)]}
        if refined is not None:  # at every thread count, kept at its fastest (as matl_refine)
            query_ms["matl_torch_refine"] = min(median_query_ms(synced(refined, device), queries, warmup, n)
                                                for n in counts)
    finally:
        recognizer.onnx = path
    return {"query_ms": query_ms, "matl_torch_ms_by_threads": by_threads, "matl_torch_threads": threads}


def measure_int8(cfg: DictConfig, datamodule: Any, model: Any, queries: torch.Tensor, warmup: int,
                 counts: list[int], device: torch.device) -> dict[str, Any]:
    """``quantize=int8``: ``query_ms.matl_int8`` (the int8 query path of :mod:`matl.inference.quantize`,
    calibrated on training positives, its own int8 gallery embeddings) on the same queries, at each thread
    count like ``matl``, kept at its fastest; empty for ``quantize=none``. The float numbers are unchanged."""
    from matl.inference.quantize import apply_quantize_option, datamodule_calibration, quantize_option

    if quantize_option(cfg) == "none":
        return {"query_ms": {}}
    recognizer = model.build_recognizer(datamodule.gallery)
    start = time.perf_counter()
    applied = apply_quantize_option(recognizer, cfg, lambda: datamodule_calibration(datamodule))
    build_s = time.perf_counter() - start
    if applied["quantize"] == "none":
        return {"query_ms": {"matl_int8": None}, "matl_int8_fallback": applied["quantize_fallback"]}
    by_threads = {str(n): median_query_ms(synced(recognizer, device), queries, warmup, n) for n in counts}
    threads = int(min(by_threads, key=lambda n: by_threads[n]))
    return {"query_ms": {"matl_int8": by_threads[str(threads)]}, "recognizer": recognizer,
            "matl_int8_ms_by_threads": by_threads,
            "matl_int8_threads": threads, "matl_int8_build_s": build_s,
            "matl_int8_path": "int8 (FX static quantisation, oneDNN; TorchScript, frozen) + float warps, search, pose"}


def measure_onnx(model: Any, gallery: Any, queries: torch.Tensor, warmup: int, counts: list[int],
                 device: torch.device) -> dict[str, Any]:
    """``query_ms.matl_onnx``: the query network of ``matl.export format=onnx`` in onnxruntime (CPU), batch of 1.

    The model is exported to a temporary folder (checked against the eager model as every export), the
    gallery embedded by the exported gallery network, and the query timed as ``query_ms.matl``: the same
    queries and warm-up, at each thread count (onnxruntime's intra-op threads, and torch's for the rest),
    kept at its fastest. The timed call is a :class:`~matl.models.recognizer.TensorRecognizer` call whose
    networks step (``embed_queries``) is the onnxruntime session: the exact gallery search (torch) on
    the ONNX embeddings and the pose are the eager query's own code. Without onnxruntime, on a GPU run
    or for a model without an embedding network, ``query_ms`` has no ``matl_onnx`` and
    ``matl_onnx_skipped`` says why.
    """
    from matl.inference.export import OnnxNetwork, export_inference, require_onnxruntime

    try:
        ort = require_onnxruntime()
    except MatlError as error:
        return {"query_ms": {}, "matl_onnx_skipped": str(error)}
    if device.type != "cpu":
        return {"query_ms": {}, "matl_onnx_skipped": f"device={device}: onnxruntime is timed on CPU runs only"}
    feature_net, stn = getattr(model, "feature_net", None), getattr(model, "stn", None)
    if feature_net is None or not hasattr(model, "build_recognizer"):
        return {"query_ms": {}, "matl_onnx_skipped": f"{type(model).__name__} has no embedding network to export"}
    with tempfile.TemporaryDirectory(prefix="matl_bench_onnx_") as folder:
        start = time.perf_counter()
        try:
            info = export_inference(feature_net, stn, int(gallery.image_size), folder, "onnx")
        except Exception as error:  # an operator onnxruntime refuses, or a check above tolerance: reported
            return {"query_ms": {}, "matl_onnx_skipped": f"ONNX export failed: {' '.join(str(error).split())[:300]}"}
        export_s = time.perf_counter() - start
        gallery_net = OnnxNetwork(Path(folder) / "gallery_net.onnx")
        networks = {n: OnnxNetwork(Path(folder) / "query_net.onnx", threads=n) for n in counts}
    model.eval()
    recognizer = model.build_recognizer(gallery)
    images = gallery.images.cpu()
    recognizer.gallery_features = torch.cat([gallery_net(images[i:i + 256]) for i in range(0, len(images), 256)])

    def onnx_query_path(net: OnnxNetwork) -> Callable[[torch.Tensor], tuple[Any, ...]]:
        """``TensorRecognizer.embed_queries`` by ``net``:
        ``(embedding, query_H_anchor or None, degenerate, warped)``."""
        if stn is not None:
            return net
        return lambda q: (net(q), None, torch.zeros(len(q), dtype=torch.bool), q)

    by_threads = {}
    for n, net in networks.items():
        recognizer.embed_queries = onnx_query_path(net)  # the networks step of TensorRecognizer.forward
        by_threads[str(n)] = median_query_ms(recognizer, queries.cpu(), warmup, n)
    threads = int(min(by_threads, key=lambda n: by_threads[n]))
    with torch.no_grad():
        eager = model.build_recognizer(gallery)(queries)
        same = float((recognizer(queries.cpu()).gallery_index == eager.gallery_index.cpu()).float().mean())
    return {"query_ms": {"matl_onnx": by_threads[str(threads)]}, "matl_onnx_ms_by_threads": by_threads,
            "matl_onnx_threads": threads, "matl_onnx_export_s": export_s,
            "matl_onnx_max_abs_diff": info["max_abs_diff_by_output"], "matl_onnx_same_answers": same,
            "matl_onnx_path": f"onnxruntime {ort.__version__} CPUExecutionProvider (query_net.onnx and "
                              "gallery_net.onnx of matl.export format=onnx) + the recognizer's exact search and pose "
                              "(torch); matl_onnx_same_answers: share of the queries whose nearest anchor is eager's"}


def extra_baseline_names(cfg: DictConfig, options: DictConfig) -> list[str]:
    """``bench.baselines``: names of ``baselines.<name>`` nodes (``conf/bench.yaml`` composes them from
    ``conf/baseline/``), each timed as ``query_ms.<name>``; checked (a one-line error names the choices)."""
    value = options.get("baselines") or []
    names = list(value) if isinstance(value, (list, tuple, ListConfig)) else [value]
    known = sorted((cfg.get("baselines") or {}).keys())
    bad = [n for n in names if not isinstance(n, str) or n not in known]
    if bad or len(set(names)) != len(names):
        raise MatlError(f"bench.baselines={names} is invalid: use a list of distinct names among {known} (extra "
                        "baselines timed on the same queries; add another as baseline@baselines.<name> in bench.yaml)")
    return [str(n) for n in names]


def _missing_package(error: BaseException) -> ModuleNotFoundError | None:
    """The ``ModuleNotFoundError`` behind a failed build (an optional package not installed), else None."""
    seen: BaseException | None = error
    while seen is not None:
        if isinstance(seen, ModuleNotFoundError):
            return seen
        seen = seen.__cause__ or seen.__context__
    return None


def measure_extra_baselines(cfg: DictConfig, options: DictConfig, gallery: Any, queries: torch.Tensor, warmup: int,
                            counts: list[int]) -> dict[str, Any]:
    """``query_ms.<name>`` of every ``bench.baselines`` entry, timed exactly as ``query_ms.sift_ransac``: the same
    gallery (indexed once, not timed) and queries, one :class:`~matl.baselines.recognizer.BaselineRecognizer` call
    per query at each thread count (torch's and OpenCV's), kept at its fastest.

    A baseline whose optional package is not installed gets ``query_ms.<name>: null`` and the install hint in
    ``baselines_skipped``; any other failure to build it is an error.

    Returns:
        ``{"query_ms": {name: ms}, "baselines": {name: {ms_by_threads, threads, index_seconds, options}},
        "baselines_skipped": {name: reason}}`` (the last two only when non-empty).
    """
    from matl.baselines.recognizer import BaselineRecognizer, build_baseline

    query_ms: dict[str, float | None] = {}
    details: dict[str, Any] = {}
    skipped: dict[str, str] = {}
    for name in extra_baseline_names(cfg, options):
        node = cfg.baselines[name]
        try:
            matcher = build_baseline(node, name)
        except MatlError as error:
            if _missing_package(error) is None:
                raise
            query_ms[name], skipped[name] = None, str(error)
            log.info("bench: %s skipped: %s", name, error)
            continue
        log.info("bench: query_ms.%s", name)
        start = time.perf_counter()
        baseline = BaselineRecognizer(matcher, gallery)  # indexes the gallery once (not part of query_ms)
        index_s = time.perf_counter() - start
        by_threads = {}
        for n in counts:
            by_threads[str(n)] = median_query_ms(baseline, queries, warmup, n)
        threads = int(min(by_threads, key=lambda n: by_threads[n]))
        query_ms[name] = by_threads[str(threads)]
        details[name] = {"ms_by_threads": by_threads, "threads": threads, "index_seconds": index_s,
                         "options": {k: v for k, v in OmegaConf.to_container(node, resolve=True).items()
                                     if k != "_target_"}}
    out: dict[str, Any] = {"query_ms": query_ms}
    if details:
        out["baselines"] = details
    if skipped:
        out["baselines_skipped"] = skipped
    return out

