"""Speed measurements against a reference measured in the same run: ``bench.json`` and a summary table.

The library side of ``python -m matl.bench`` (what each number means: :mod:`matl.bench`).
"""

from __future__ import annotations

import logging
import math
import os
import platform
import statistics
import tempfile
import time
import warnings
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig, ListConfig, OmegaConf, open_dict
from rich.console import Console
from rich.table import Table

from matl.utils.config import validate_config
from matl.utils.errors import CONF_DIR, MatlError
from matl.utils.instantiate import instantiate_node
from matl.utils.io import write_json
from matl.utils.timing import alternating_query_ms, batch_query_ms, median_query_ms

# matl.models (kornia, Lightning) is imported inside the functions: a bad option is reported in a second

log = logging.getLogger(__name__)

REQUIRED_KEYS = ("train_triplets_per_s", "data_time_fraction", "query_ms", "speedup_vs_sift", "gallery_scaling",
                 "render_images_per_s")


# ------------------------------------------------------------------------------------------ helpers
def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _synced(fn: Callable[[torch.Tensor], Any], device: torch.device) -> Callable[[torch.Tensor], Any]:
    """``fn`` followed by a device sync, so GPU timings include the work and not just its launch."""
    def call(x: torch.Tensor) -> Any:
        out = fn(x)
        _sync(device)
        return out
    return call


def bench_options(cfg: DictConfig) -> DictConfig:
    """``cfg.bench``, with ``cfg.bench_quick`` merged over it when ``bench.quick=true``; checked."""
    options = cfg.bench
    if options.get("quick"):
        options = OmegaConf.merge(options, cfg.get("bench_quick") or {})
    for key in ("train_steps", "queries", "scaling_queries", "batch_count", "rounds"):
        if not isinstance(options[key], int) or options[key] < 1:
            raise MatlError(f"bench.{key}={options[key]} is invalid: use an integer >= 1")
    for key in ("train_warmup", "query_warmup", "scaling_warmup", "render_objects", "batch"):
        if not isinstance(options[key], int) or options[key] < 0:
            raise MatlError(f"bench.{key}={options[key]} is invalid: use an integer >= 0")
    threads = options.get("query_threads")
    if threads is not None and (not isinstance(threads, int) or isinstance(threads, bool) or threads < 1):
        raise MatlError(f"bench.query_threads={threads} is invalid: use an integer >= 1, or null for the run's threads")
    extra_baseline_names(cfg, options)
    anchors = list(options.scaling_anchors)
    if any(not isinstance(a, int) or a < 1 for a in anchors):
        raise MatlError(f"bench.scaling_anchors={anchors} is invalid: use a list of integers >= 1")
    return options


def system_info(device: torch.device) -> dict[str, Any]:
    """What the numbers depend on: hardware, threads, library versions and the load when started."""
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            cpu = next((line.split(":", 1)[1].strip() for line in f if line.startswith("model name")), cpu)
    except OSError:
        pass
    info: dict[str, Any] = {
        "cpu": cpu, "cpu_count": os.cpu_count(), "torch_threads": torch.get_num_threads(),
        "omp_num_threads": os.environ.get("OMP_NUM_THREADS"), "torch": torch.__version__,
        "python": platform.python_version(), "platform": platform.platform(), "device": str(device),
        "load_average_1min": os.getloadavg()[0] if hasattr(os, "getloadavg") else None,
    }
    if device.type == "cuda":
        info["gpu"] = torch.cuda.get_device_name(device)
    return info


def _cycle(loader: Any) -> Iterator[dict[str, torch.Tensor]]:
    while True:
        yield from loader


# -------------------------------------------------------------------------------------- training
def measure_training(datamodule: Any, model: Any, steps: int, warmup: int, device: torch.device) -> dict[str, Any]:
    """Training throughput and the share of a step spent making images (``materialize``).

    Each step: collate the next parameter batch, move it to ``device``, ``materialize`` it (timed),
    ``training_step``, backward and the optimiser step. Medians are reported per step; the
    throughput and fraction are totals over the timed steps.
    """
    model.to(device).train()
    optimizers = model.configure_optimizers()
    optimizer = optimizers["optimizer"] if isinstance(optimizers, dict) else optimizers
    loader = datamodule.train_dataloader()
    batches = _cycle(loader)
    step_s, data_s, load_s = [], [], []
    with warnings.catch_warnings():
        # training_step logs through self.log, which warns (and does nothing) without a Trainer
        warnings.filterwarnings("ignore", message=".*self.log.*")
        warnings.filterwarnings("ignore", message=".*self.trainer.*")
        for i in range(warmup + steps):
            _sync(device)
            t0 = time.perf_counter()
            params = {k: v.to(device) for k, v in next(batches).items()}
            _sync(device)
            t1 = time.perf_counter()
            batch = datamodule.materialize(params)
            _sync(device)
            t2 = time.perf_counter()
            loss = model.training_step(batch, i)
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
            _sync(device)
            t3 = time.perf_counter()
            if i >= warmup:
                step_s.append(t3 - t0)
                data_s.append(t2 - t1)
                load_s.append(t1 - t0)
    total = sum(step_s)
    batch_size = int(datamodule.batch_size)
    return {
        "train_triplets_per_s": steps * batch_size / total,
        "data_time_fraction": sum(data_s) / total,
        "train": {
            "steps": steps, "warmup": warmup, "batch_size": batch_size, "image_size": int(datamodule.image_size),
            "N": int(datamodule.num_anchors), "optimizer": type(optimizer).__name__,
            "step_ms_median": 1e3 * statistics.median(step_s),
            "materialize_ms_median": 1e3 * statistics.median(data_s),
            "loader_ms_median": 1e3 * statistics.median(load_s),
            "loader_time_fraction": sum(load_s) / total,
            "includes": "collate + materialize + training_step + backward + optimizer step; not Lightning's loop",
        },
    }


# --------------------------------------------------------------------------------------- queries
def _query_images(datamodule: Any, count: int, device: torch.device) -> torch.Tensor:
    """The first ``count`` test queries ``(count, 3, S, S)`` (materialised like eval's)."""
    params = {k: v[:count].to(device) for k, v in datamodule.test_set.params.items()}
    return datamodule.materialize(params)["query"]


def measure_queries(cfg: DictConfig, options: DictConfig, datamodule: Any, model: Any, weights: str,
                    device: torch.device) -> dict[str, Any]:
    """``query_ms`` of MATL (exact, refined, faiss) and of the keypoint baseline on the same queries."""
    from matl.baselines.recognizer import BaselineRecognizer, build_baseline
    from matl.inference.options import search_name
    from matl.inference.refine import RefinedRecognizer
    from matl.inference.runtime import apply_runtime_option
    from matl.models.search import ExactSearch

    warmup, count = int(options.query_warmup), int(options.queries)
    queries = _query_images(datamodule, warmup + count, device)
    if len(queries) < warmup + count:
        raise MatlError(f"data.test_queries={len(queries)} is smaller than bench.queries + bench.query_warmup "
                        f"= {warmup + count}")
    gallery = datamodule.gallery
    model.to(device).eval()
    recognizer = model.build_recognizer(gallery)
    runtime = apply_runtime_option(recognizer, cfg)  # runtime=onnxruntime: the query networks in onnxruntime
    query_ms: dict[str, float | None] = {}
    notes: dict[str, str] = {}

    # every method at each thread count (bench.query_threads, or 1..the run's), then at its fastest
    counts = thread_counts(options)
    by_threads = {str(n): median_query_ms(_synced(recognizer, device), queries, warmup, n) for n in counts}
    threads = int(min(by_threads, key=lambda n: by_threads[n]))
    query_ms["matl"] = by_threads[str(threads)]
    int8 = measure_int8(cfg, datamodule, model, queries, warmup, counts, device)  # quantize=int8 only
    query_ms.update(int8.pop("query_ms"))
    onnx = measure_onnx(model, gallery, queries, warmup, counts, device)  # with onnxruntime installed
    query_ms.update(onnx.pop("query_ms"))
    breakdown: dict[str, Any] = {}
    refine_by_threads: dict[str, float] = {}
    refine_threads = None
    refined = refined_int8 = None
    if options.refine:
        refiner = instantiate_node(cfg.refiner, "refiner")
        start = time.perf_counter()
        refined = RefinedRecognizer(recognizer, refiner)  # the per-anchor data of refiner=fast: once, at enrolment
        notes["refine_templates_s"] = f"{time.perf_counter() - start:.3f}"
        if getattr(refined, "templates", None) is not None and hasattr(refined.templates, "nbytes"):
            notes["refine_templates_mb"] = f"{refined.templates.nbytes / 1e6:.1f}"
        # timed at every thread count like each method, kept at its fastest (the refinement runs on one core: its
        # fastest count need not be the networks')
        refine_by_threads = {str(n): median_query_ms(_synced(refined, device), queries, warmup, n) for n in counts}
        refine_threads = int(min(refine_by_threads, key=lambda n: refine_by_threads[n]))
        query_ms["matl_refine"] = refine_by_threads[str(refine_threads)]
        breakdown = measure_breakdown(model, recognizer, refined, queries, warmup, refine_threads, device)
        if int8.get("recognizer") is not None:  # quantize=int8: the int8 query path, refined the same way
            refined_int8 = RefinedRecognizer(int8["recognizer"], refiner, templates=refined.templates)
            query_ms["matl_int8_refine"] = median_query_ms(_synced(refined_int8, device), queries, warmup,
                                                           int8["matl_int8_threads"])
    int8.pop("recognizer", None)
    torch_ms = measure_torch_runtime(recognizer, refined, queries, warmup, counts, device)  # runtime=onnxruntime
    query_ms.update(torch_ms.pop("query_ms"))
    if options.faiss and hasattr(recognizer, "use_search"):
        faiss_node = cfg.search if search_name(cfg.get("search")) == "faiss" else _default_faiss_node()
        try:
            recognizer.use_search(instantiate_node(faiss_node, "search"))
            query_ms["matl_faiss"] = median_query_ms(_synced(recognizer, device), queries, warmup, threads)
        except MatlError as error:  # faiss not installed: reported, not fatal
            query_ms["matl_faiss"] = None
            notes["matl_faiss"] = str(error)
        recognizer.use_search(ExactSearch)

    baseline_name = str(cfg.baseline._target_).rsplit(".", 1)[-1]
    matcher = build_baseline(cfg.baseline, baseline_name)
    start = time.perf_counter()
    baseline = BaselineRecognizer(matcher, gallery)  # indexes the gallery once (not part of query_ms)
    index_s = time.perf_counter() - start
    cpu_queries = queries.cpu()
    sift_by_threads = {}
    for n in counts:  # torch's and OpenCV's threads alike, as every method's (matl.utils.timing.compute_threads)
        sift_by_threads[str(n)] = median_query_ms(baseline, cpu_queries, warmup, n)
    sift_threads = int(min(sift_by_threads, key=lambda n: sift_by_threads[n]))
    query_ms["sift_ransac"] = sift_by_threads[str(sift_threads)]
    # the headline numbers again, the methods alternating in bench.rounds rounds, each at its fastest thread count:
    # the ratios of query_ms then do not depend on how the shared machine's speed drifted between the passes above
    # (those stay in *_ms_by_threads)
    turns = {"matl": (_synced(recognizer, device), threads), "sift_ransac": (lambda x: baseline(x.cpu()), sift_threads)}
    if refined is not None:
        turns["matl_refine"] = (_synced(refined, device), refine_threads)
    query_ms.update(alternating_query_ms(turns, queries, warmup, int(options.rounds)))
    extra = measure_extra_baselines(cfg, options, gallery, cpu_queries, warmup, counts)  # bench.baselines
    query_ms.update(extra.pop("query_ms"))
    batched: dict[str, Any] = {}
    if options.batch:  # the crops of one camera frame in one call
        methods = {"matl": _synced(recognizer, device), "matl_refine": refined and _synced(refined, device),
                   "matl_int8_refine": refined_int8 and _synced(refined_int8, device), "sift_ransac": baseline}
        batched = measure_batches(options, datamodule, {k: v for k, v in methods.items() if v is not None}, counts,
                                  device)

    timing = {
        "queries": count, "warmup": warmup,
        "statistic": "median over single-query calls (batch of 1); matl, matl_refine and sift_ransac over bench.rounds "
                     "rounds in which they alternate, each at its fastest thread count",
        "rounds": int(options.rounds),
        "gallery_anchors": len(gallery), "gallery_planes": int(gallery.plane_index.max()) + 1,
        "N": gallery.num_anchors, "image_size": gallery.image_size, "weights": weights,
        "baseline": baseline_name, "baseline_options": {k: v for k, v in OmegaConf.to_container(
            cfg.baseline, resolve=True).items() if k != "_target_"},
        "baseline_index_seconds": index_s,
        "same_queries": "the first queries+warmup test queries of data (seed) for every method",
        "timed_region": "one recognizer (or baseline) call per query, wall clock: networks, gallery search, pose",
        "threads": "each method timed at every thread count in matl_ms_by_threads / matl_refine_ms_by_threads / "
                   "sift_ms_by_threads (torch's intra-op threads and OpenCV's alike, for every method); query_ms holds "
                   "each method at its fastest",
        "matl_threads": threads, "matl_refine_threads": refine_threads, "sift_threads": sift_threads,
        "matl_ms_by_threads": by_threads, "matl_refine_ms_by_threads": refine_by_threads,
        "sift_ms_by_threads": sift_by_threads,
        "matl_path": _query_path(recognizer, queries[:1]),
        "matl_align": "the alignment stage runs in query_ms.matl (after the search)" if getattr(
            recognizer, "align", None) is not None else None,
        "breakdown": breakdown,
        **runtime,
        **torch_ms,
        **int8,
        **onnx,
        **extra,
    }
    if notes:
        timing["notes"] = notes
    return {"query_ms": query_ms, "query_timing": timing, **batched}


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
        by_threads = {str(n): median_query_ms(_synced(recognizer, device), queries, warmup, n) for n in counts}
        threads = int(min(by_threads, key=lambda n: by_threads[n]))
        query_ms = {"matl_torch": by_threads[str(threads)]}
        if refined is not None:  # at every thread count, kept at its fastest (as matl_refine)
            query_ms["matl_torch_refine"] = min(median_query_ms(_synced(refined, device), queries, warmup, n)
                                                for n in counts)
    finally:
        recognizer.onnx = path
    return {"query_ms": query_ms, "matl_torch_ms_by_threads": by_threads, "matl_torch_threads": threads}


def measure_batches(options: DictConfig, datamodule: Any, methods: dict[str, Callable[[torch.Tensor], Any]],
                    counts: list[int], device: torch.device) -> dict[str, Any]:
    """``query_ms_batch``: milliseconds per query when ``bench.batch`` queries (the crops of one camera frame) are
    answered in one call: the wall clock of ``bench.batch_count`` batches (after one untimed) over their queries, a
    throughput, so every slow query counts in full (unlike ``query_ms``'s median); the same test queries for every
    method, each at every thread count of ``counts`` (torch's, and OpenCV's) and kept at its fastest. MATL batches
    its networks and search (and refines query by query); a keypoint baseline answers query by query."""
    batch, count = int(options.batch), int(options.batch_count)
    queries = _query_images(datamodule, batch * (count + 1), device)
    if len(queries) < batch * (count + 1):
        raise MatlError(f"data.test_queries={len(queries)} is smaller than bench.batch x (bench.batch_count + 1) "
                        f"= {batch * (count + 1)}")
    ms: dict[str, float] = {}
    threads: dict[str, int] = {}
    for name, predict in methods.items():
        inputs = queries if name.startswith("matl") else queries.cpu()
        by_threads = {}
        for n in counts:
            by_threads[n] = batch_query_ms(predict, inputs, batch, 1, n)
        threads[name] = min(by_threads, key=lambda n: by_threads[n])
        ms[name] = by_threads[threads[name]]
    out: dict[str, Any] = {"query_ms_batch": ms, "batch_timing": {
        "batch": batch, "batches": count, "threads": threads,
        "statistic": "wall clock of the timed batches / their queries (a throughput: a slow query counts in "
                     "full), after one untimed batch"}}
    for name in ("matl_refine", "matl_int8_refine"):
        if ms.get(name) and ms.get("sift_ransac"):
            out[f"speedup_vs_sift_{name.removeprefix('matl_')}_batch"] = ms["sift_ransac"] / ms[name]
    return out


def measure_breakdown(model: Any, recognizer: Any, refined: Any, queries: torch.Tensor, warmup: int,
                      threads: int, device: torch.device) -> dict[str, Any]:
    """Where a refined MATL query's milliseconds go: the median over the same single queries of each part,
    timed alone at the refined query's thread count (so the parts need not add up exactly to ``query_ms.matl_refine``).

    ``networks_ms``: ``c(s(q))`` by the recognizer's own path (onnxruntime with ``runtime=onnxruntime``, else the
    compiled graph when it applies);
    ``stn_ms`` / ``features_ms``: ``s()`` and ``c()`` alone, eager ``infer``; ``search_ms``: the gallery search
    of the query's embedding; ``align_ms``: the alignment stage against the searched anchor (models with
    ``model.align``; in ``query_ms.matl``, and in ``matl_refine`` unless the refiner skips it:
    ``refiner.start=stn``); ``refine_ms``: the refinement alone from the pose it starts from, and
    ``refine_level_ms`` its median per pyramid level, finest first (``refiner=fast``).
    """
    from matl.utils.timing import compute_threads

    parts: dict[str, list[float]] = {}
    levels: list[list[float]] = []

    def timed(name: str, fn: Callable[[], Any], keep: bool) -> Any:
        _sync(device)
        start = time.perf_counter()
        out = fn()
        _sync(device)
        if keep:
            parts.setdefault(name, []).append(1e3 * (time.perf_counter() - start))
        return out

    g = recognizer.gallery
    stn, feature_net = getattr(model, "stn", None), getattr(model, "feature_net", None)
    align = getattr(recognizer, "align", None)
    with torch.no_grad(), compute_threads(threads):
        for i in range(len(queries)):
            q, keep = queries[i:i + 1], i >= warmup
            features, query_H_anchor, _, warped = timed("networks_ms", lambda q=q: recognizer.embed_queries(q), keep)
            if stn is not None and hasattr(stn, "infer"):
                out = timed("stn_ms", lambda q=q: stn.infer(q), keep)
                if feature_net is not None and hasattr(feature_net, "infer"):
                    timed("features_ms", lambda w=out.warped: feature_net.infer(w), keep)
            index, _ = timed("search_ms", lambda f=features: recognizer.search.search(f), keep)
            if align is not None and query_H_anchor is not None:
                aligned = timed("align_ms", lambda q=q, a=g.images[index], h=query_H_anchor, w=warped:
                                align.infer(q, a, h, w), keep).query_H_anchor
                if not refined.skips_align:  # refiner.start=align: the refinement starts from the stage's pose
                    query_H_anchor = aligned
            if query_H_anchor is None:
                continue
            start = query_H_anchor.double()
            if refined.templates is not None:
                timed("refine_ms", lambda q=q, i=index, h=start: refined.refiner(q, i, h, refined.templates), keep)
                if keep and getattr(refined.refiner, "last_level_ms", None):
                    levels.append(list(refined.refiner.last_level_ms))
            else:
                timed("refine_ms", lambda q=q, i=index, h=start: refined.refiner(q, g.images[i], h), keep)
    result: dict[str, Any] = {k: statistics.median(v) for k, v in parts.items()}
    if levels:
        result["refine_level_ms"] = [statistics.median(ms[k] for ms in levels if len(ms) > k)
                                     for k in range(max(len(ms) for ms in levels))]
    result["refiner"] = type(refined.refiner).__name__
    result["refine_skips_align"] = bool(refined.skips_align)
    result["threads"] = threads
    return result


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
    by_threads = {str(n): median_query_ms(_synced(recognizer, device), queries, warmup, n) for n in counts}
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


def thread_counts(options: DictConfig) -> list[int]:
    """The thread counts single queries are timed at: ``[bench.query_threads]``, or 1..the run's (null)."""
    value = options.get("query_threads")
    return [int(value)] if value is not None else list(range(1, torch.get_num_threads() + 1))


def _query_path(recognizer: Any, query: torch.Tensor) -> str:
    """Which code answered a single query: onnxruntime, the compiled TorchScript graph or the eager networks."""
    if getattr(recognizer, "onnx", None) is not None:
        return "onnxruntime (s()'s regressor and c(); s()'s warps in OpenCV: runtime=onnxruntime)"
    compiled = recognizer._compiled_path(query) if hasattr(recognizer, "_compiled_path") else None
    if compiled is not None and compiled.failure is None and compiled._graph is not None:
        return "compiled (TorchScript, frozen, optimize_for_inference)"
    if compiled is not None and compiled.failure is not None:
        return f"eager infer (compiled path failed: {compiled.failure})"
    return "eager infer" if getattr(recognizer, "fast", False) else "eager forward"


def _default_faiss_node() -> DictConfig:
    """``conf/search/faiss.yaml``, for the faiss timing when the run's search is exact."""
    path = CONF_DIR / "search" / "faiss.yaml"
    node = OmegaConf.load(path)
    assert isinstance(node, DictConfig)
    return node


# ------------------------------------------------------------------------------- gallery scaling
def fixed_query_ms(model: Any, recognizer: Any, queries: torch.Tensor, warmup: int, device: torch.device,
                   threads: int | None = None) -> float:
    """Median milliseconds of ``c(s(query))`` for one query (the part of a query that does not
    depend on the gallery size), by the recognizer's own path (:meth:`TensorRecognizer.embed_queries`)."""
    embed_one = getattr(recognizer, "embed_queries", None)
    if embed_one is None:  # a recognizer without an embedding path (the STN classifier): its networks
        def embed_one(q: torch.Tensor) -> torch.Tensor:
            warped = model.stn(q).warped if getattr(model, "stn", None) is not None else q
            return model.feature_net(warped)
    return median_query_ms(_synced(embed_one, device), queries, warmup, threads)


def measure_scaling(cfg: DictConfig, options: DictConfig, model: Any, fixed_ms: float,
                    device: torch.device, threads: int | None = None) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    """Search latency per gallery size, exact and (when installed) FAISS; see the module docstring."""
    from matl.inference.options import search_name
    from matl.models.search import ExactSearch, FaissSearch, require_faiss

    dim = int(getattr(model.feature_net, "embedding_dim", 0)) or int(
        model.feature_net(torch.zeros(1, 3, model.image_size, model.image_size, device=device)).shape[1])
    count, warmup = int(options.scaling_queries), int(options.scaling_warmup)
    use_faiss, faiss_note = bool(options.faiss), None
    if use_faiss:
        try:
            require_faiss()
        except MatlError as error:
            use_faiss, faiss_note = False, str(error)
    faiss_node = cfg.search if search_name(cfg.get("search")) == "faiss" else _default_faiss_node()
    faiss_kwargs = {k: v for k, v in OmegaConf.to_container(faiss_node, resolve=True).items()
                    if not k.startswith("_")}
    g = torch.Generator().manual_seed(int(cfg.seed))
    rows = []
    for anchors in [int(a) for a in options.scaling_anchors]:
        gallery = torch.nn.functional.normalize(torch.randn(anchors, dim, generator=g), dim=1)
        truth = torch.randint(anchors, (warmup + count,), generator=g)
        # a query is its gallery entry moved by noise of norm ~0.3 (typical of a recognised query)
        noise = torch.randn(warmup + count, dim, generator=g) * (0.3 / math.sqrt(dim))
        queries = torch.nn.functional.normalize(gallery[truth] + noise, dim=1)
        gallery, queries = gallery.to(device), queries.to(device)
        exact = ExactSearch(gallery)
        search_ms = median_query_ms(_synced(lambda q, e=exact: e.search(q), device), queries, warmup, threads)
        exact_index = exact.search(queries)[0]
        row: dict[str, Any] = {"anchors": anchors, "query_ms": fixed_ms + search_ms, "search_ms": search_ms}
        if use_faiss:
            start = time.perf_counter()
            index = FaissSearch(gallery, **faiss_kwargs)
            row["faiss_build_s"] = time.perf_counter() - start
            row["faiss_search_ms"] = median_query_ms(lambda q, i=index: i.search(q), queries, warmup, threads)
            row["faiss_query_ms"] = fixed_ms + row["faiss_search_ms"]
            row["faiss_recall_at_1"] = float((index.search(queries)[0] == exact_index).float().mean())
        rows.append(row)
    info = {
        "embedding_dim": dim, "queries": count, "warmup": warmup, "fixed_query_ms": fixed_ms, "threads": threads,
        "method": "query_ms = fixed_query_ms (STN + feature net of one real query, measured once) + search_ms "
                  "(median single-query search over random unit embeddings of the model's dimension; queries "
                  "are gallery entries plus noise of norm ~0.3)",
        "faiss": ({k: v for k, v in faiss_kwargs.items()} if use_faiss else None),
    }
    if faiss_note:
        info["faiss_note"] = faiss_note
    return rows, info


# --------------------------------------------------------------------------------------- render
def measure_render(cfg: DictConfig, options: DictConfig) -> tuple[float | None, dict[str, Any]]:
    """Canonical renders per second of ``data.source`` (None with a reason when it cannot render)."""
    if not options.render:
        return None, {"skipped": "bench.render=false"}
    from matl.data.render_speed import render_images_per_s
    source = instantiate_node(cfg.data.source, "data.source")
    if not hasattr(source, "models"):
        return None, {"skipped": f"{type(source).__name__} has no meshes to render (photographed canonical images)"}
    try:
        result = render_images_per_s(source, int(cfg.data.image_size), "canonical", max(1, int(options.render_objects)))
    except Exception as error:  # no OpenGL (EGL / OSMesa) on this machine: the other numbers still count
        return None, {"skipped": f"rendering failed: {' '.join(str(error).split()) or type(error).__name__}"}
    details = {k: float(v) for k, v in result.items()}
    details.update(kind="canonical", objects=max(1, int(options.render_objects)), image_size=int(cfg.data.image_size),
                   source=type(source).__name__)
    return float(result["images_per_s"]), details


# -------------------------------------------------------------------------------------------- main
def load_model(cfg: DictConfig) -> tuple[Any | None, str]:
    """The checkpoint's model (and the data's size and N set to its own): ``ckpt=pretrained`` (the default)
    the shipped model, ``ckpt=<path>`` a matl.train checkpoint; ``ckpt=null`` None (the default config's
    model, untrained)."""
    ckpt_path = cfg.get("ckpt")
    if not ckpt_path:
        return None, "untrained: the default config's model, randomly initialised (speed does not depend on weights)"
    from matl.inference.api import SHIPPED, resolve_checkpoint_keyword
    from matl.models.checkpoint import build_model, checkpoint_info, load_checkpoint

    pretrained = str(ckpt_path) in SHIPPED  # ckpt=pretrained / pretrained_fast
    ckpt_path = resolve_checkpoint_keyword(str(ckpt_path))
    ckpt = load_checkpoint(ckpt_path)
    size, num_anchors = checkpoint_info(ckpt, ckpt_path)
    config = ckpt.get("matl_config")
    if not isinstance(config, dict) or "model" not in config:
        raise MatlError(f"checkpoint {ckpt_path} carries no matl_config: not written by matl.train")
    with open_dict(cfg):
        cfg.data.image_size = size  # the gallery and queries must be the checkpoint's size
        cfg.N = num_anchors
    what = f"pretrained: the shipped model {ckpt_path}" if pretrained else f"checkpoint {ckpt_path}"
    return build_model(config["model"], ckpt, ckpt_path), what


def run_bench(cfg: DictConfig, console: Console | None = None) -> dict[str, Any]:
    """Run every measurement of ``cfg`` (see the module docstring); write and return ``bench.json``."""
    validate_config(cfg)
    options = bench_options(cfg)  # before any heavy import
    if str(cfg.get("quantize") or "none") not in ("none", "int8"):
        raise MatlError(f"quantize={cfg.get('quantize')} is invalid: use none or int8")
    from matl.inference.runtime import runtime_option

    runtime_option(cfg)  # runtime=torch|onnxruntime
    if cfg.get("threads"):
        torch.set_num_threads(int(cfg.threads))
    device = torch.device(str(cfg.device) if cfg.device != "auto" else "cuda" if torch.cuda.is_available() else "cpu")
    out_dir = Path(cfg.paths.output_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(int(cfg.seed))

    query_model, weights = load_model(cfg)
    datamodule = instantiate_node(cfg.data, "data")
    datamodule.setup("fit")
    train_model = instantiate_node(cfg.model, "model")
    results: dict[str, Any] = {"quick": bool(options.quick), "system": system_info(device)}

    log.info("bench: training steps")
    results.update(measure_training(datamodule, train_model, int(options.train_steps), int(options.train_warmup),
                                    device))
    model = query_model if query_model is not None else train_model
    log.info("bench: query_ms")
    results.update(measure_queries(cfg, options, datamodule, model, weights, device))
    q = results["query_ms"]
    results["speedup_vs_sift"] = q["sift_ransac"] / q["matl"] if q.get("sift_ransac") and q.get("matl") else None
    if "matl_int8" in q:  # quantize=int8: an extra entry, next to the float numbers
        results["speedup_int8_vs_sift"] = (q["sift_ransac"] / q["matl_int8"] if q.get("sift_ransac")
                                           and q.get("matl_int8") else None)
    results["refine_added_ms"] = q["matl_refine"] - q["matl"] if q.get("matl_refine") is not None else None
    results["speedup_vs_sift_refine"] = (q["sift_ransac"] / q["matl_refine"] if q.get("sift_ransac")
                                         and q.get("matl_refine") else None)
    if "matl_int8_refine" in q:  # quantize=int8 with bench.refine
        results["speedup_int8_vs_sift_refine"] = (q["sift_ransac"] / q["matl_int8_refine"] if q.get("sift_ransac")
                                                  and q.get("matl_int8_refine") else None)

    log.info("bench: gallery scaling")
    queries = _query_images(datamodule, int(options.query_warmup) + int(options.queries), device)
    with torch.no_grad():
        model.eval()
        threads = results["query_timing"]["matl_threads"]  # MATL's fastest thread count, as query_ms.matl
        fixed_ms = fixed_query_ms(model, model.build_recognizer(datamodule.gallery), queries,
                                  int(options.query_warmup), device, threads)
    results["gallery_scaling"], results["gallery_scaling_info"] = measure_scaling(cfg, options, model, fixed_ms, device,
                                                                                  threads)

    log.info("bench: rendering")
    results["render_images_per_s"], results["render"] = measure_render(cfg, options)
    results["config"] = {"bench": OmegaConf.to_container(options, resolve=True), "data": _data_name(cfg),
                         "image_size": int(cfg.data.image_size), "N": int(cfg.N), "seed": int(cfg.seed),
                         "ckpt": cfg.get("ckpt"), "quantize": cfg.get("quantize", "none"),
                         "runtime": cfg.get("runtime", "torch")}
    write_json(out_dir / "bench.json", results)
    print_summary(results, console or Console())
    return results


def _data_name(cfg: DictConfig) -> str:
    try:
        from hydra.core.hydra_config import HydraConfig

        return str(HydraConfig.get().runtime.choices.get("data"))
    except ValueError:  # called as a function (tests)
        source = cfg.data.get("source")
        return str(source.get("catalog")) if source is not None and source.get("catalog") else "?"


def _fmt(value: Any, digits: int = 2) -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:,.{digits}f}"
    return str(value)


def print_summary(results: dict[str, Any], console: Console) -> None:
    """Two rich tables: the headline numbers and the gallery scaling."""
    q, t = results["query_ms"], results["query_timing"]
    table = Table(title=f"matl.bench{' (quick: smoke run, not a measurement)' if results['quick'] else ''}")
    table.add_column("measure")
    table.add_column("value", justify="right")
    table.add_column("note")
    train = results["train"]
    table.add_row("train_triplets_per_s", _fmt(results["train_triplets_per_s"], 1),
                  f"batch {train['batch_size']}, {train['image_size']} px, N={train['N']}")
    table.add_row("data_time_fraction", _fmt(results["data_time_fraction"], 3), "share of a step in materialize")
    table.add_row("query_ms.matl", _fmt(q.get("matl")),
                  f"{t['gallery_anchors']} anchors; {t['weights'].split(':')[0]}; {t['matl_threads']} thread(s); "
                  f"runtime={t.get('runtime')}" + (f" (fallback: {t['runtime_fallback']})"
                                                   if t.get("runtime_fallback") else ""))
    if "matl_refine" in q:
        added = results.get("refine_added_ms")
        # Signed: a model with an alignment stage skips it on the refined path, so this can be negative.
        added_note = "-" if added is None else f"{added:+.2f}"
        table.add_row("query_ms.matl_refine", _fmt(q.get("matl_refine")),
                      f"{added_note} ms against matl; {t.get('matl_refine_threads')} thread(s)")
        table.add_row("speedup_vs_sift_refine", _fmt(results.get("speedup_vs_sift_refine"), 1),
                      "sift_ransac / matl_refine")
    for name in ("matl_torch", "matl_torch_refine"):
        if name in q:
            table.add_row(f"query_ms.{name}", _fmt(q.get(name)), "the same with runtime=torch (compiled graph)")
    if "matl_faiss" in q:
        table.add_row("query_ms.matl_faiss", _fmt(q.get("matl_faiss")), t.get("notes", {}).get("matl_faiss", ""))
    table.add_row("query_ms.sift_ransac", _fmt(q.get("sift_ransac")),
                  f"same {t['queries']} queries; {t['sift_threads']} thread(s)")
    table.add_row("speedup_vs_sift", _fmt(results["speedup_vs_sift"], 1), "sift_ransac / matl")
    for name, ms in q.items():  # bench.baselines
        if name in t.get("baselines", {}) or name in t.get("baselines_skipped", {}):
            table.add_row(f"query_ms.{name}", _fmt(ms), t.get("baselines_skipped", {}).get(name)
                          or f"same {t['queries']} queries; {t['baselines'][name]['threads']} thread(s)")
    if "matl_onnx" in q or "matl_onnx_skipped" in t:
        table.add_row("query_ms.matl_onnx", _fmt(q.get("matl_onnx")), t.get("matl_onnx_skipped")
                      or f"onnxruntime; {t.get('matl_onnx_threads')} thread(s)")
    if "matl_int8" in q:
        table.add_row("query_ms.matl_int8", _fmt(q.get("matl_int8")),
                      t.get("matl_int8_fallback") or f"quantize=int8; {t.get('matl_int8_threads')} thread(s)")
        table.add_row("speedup_int8_vs_sift", _fmt(results.get("speedup_int8_vs_sift"), 1), "sift_ransac / matl_int8")
    if "matl_int8_refine" in q:
        table.add_row("query_ms.matl_int8_refine", _fmt(q.get("matl_int8_refine")), "int8 query path + refine=true")
        table.add_row("speedup_int8_vs_sift_refine", _fmt(results.get("speedup_int8_vs_sift_refine"), 1),
                      "sift_ransac / matl_int8_refine")
    batched = results.get("query_ms_batch") or {}
    if batched:
        size = results["batch_timing"]["batch"]
        table.add_row(f"query_ms_batch ({size} a call)", "", ", ".join(f"{k} {_fmt(v)}" for k, v in batched.items()))
        for key in ("speedup_vs_sift_refine_batch", "speedup_vs_sift_int8_refine_batch"):
            if key in results:
                table.add_row(key, _fmt(results[key], 1), f"per query, {size} queries a call")
    parts = t.get("breakdown") or {}
    if parts:
        names = [k for k in ("networks_ms", "stn_ms", "features_ms", "search_ms", "align_ms", "refine_ms")
                 if k in parts]
        levels = " / ".join(_fmt(v, 3) for v in parts.get("refine_level_ms", []))
        table.add_row("breakdown (ms)", "", ", ".join(f"{k[:-3]} {_fmt(parts[k], 3)}" for k in names)
                      + (f"; refine per level (finest first) {levels}" if levels else ""))
    table.add_row("render_images_per_s", _fmt(results["render_images_per_s"], 1),
                  results["render"].get("skipped", f"{results['render'].get('objects')} objects, canonical"))
    console.print(table)
    fixed = _fmt(results["gallery_scaling_info"]["fixed_query_ms"])
    scaling = Table(title=f"gallery scaling (fixed c(s(q)) {fixed} ms + search on random embeddings)")
    for name in ("anchors", "query_ms", "search_ms", "faiss_query_ms", "faiss_recall_at_1", "faiss_build_s"):
        scaling.add_column(name, justify="right")
    for row in results["gallery_scaling"]:
        scaling.add_row(f"{row['anchors']:,}", _fmt(row["query_ms"]), _fmt(row["search_ms"], 3),
                        _fmt(row.get("faiss_query_ms")), _fmt(row.get("faiss_recall_at_1"), 3),
                        _fmt(row.get("faiss_build_s")))
    console.print(scaling)
