"""Speed measurements against a reference measured in the same run: ``bench.json`` and a summary table.

The library side of ``python -m matl.bench`` (what each number means: :mod:`matl.bench`); the other query paths
timed beside ``query_ms.matl`` are in :mod:`matl.evaluation.speed_paths`, the camera crops (``query_ms_camera``) in
:mod:`matl.evaluation.camera_speed`, ``gallery_scaling`` in :mod:`matl.evaluation.gallery_scaling`, the printed summary
in :mod:`matl.evaluation.speed_summary`.
"""

from __future__ import annotations

import logging
import os
import platform
import statistics
import time
import warnings
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf, open_dict
from rich.console import Console

from matl.evaluation.camera_speed import camera_options, measure_camera
from matl.evaluation.gallery_scaling import default_faiss_node, fixed_query_ms, measure_scaling
from matl.evaluation.speed_paths import (
    extra_baseline_names,
    measure_extra_baselines,
    measure_int8,
    measure_onnx,
    measure_torch_runtime,
)
from matl.evaluation.speed_summary import print_summary
from matl.utils.config import validate_config
from matl.utils.errors import MatlError
from matl.utils.instantiate import instantiate_node
from matl.utils.io import write_json
from matl.utils.timing import alternating_query_ms, batch_query_ms, median_query_ms, synced

# matl.models (kornia, Lightning) is imported inside the functions: a bad option is reported in a second

log = logging.getLogger(__name__)

REQUIRED_KEYS = ("train_triplets_per_s", "data_time_fraction", "query_ms", "speedup_vs_sift", "gallery_scaling",
                 "render_images_per_s")


# ------------------------------------------------------------------------------------------ helpers
def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


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
    camera_options(options)
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
    by_threads = {str(n): median_query_ms(synced(recognizer, device), queries, warmup, n) for n in counts}
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
        refine_by_threads = {str(n): median_query_ms(synced(refined, device), queries, warmup, n) for n in counts}
        refine_threads = int(min(refine_by_threads, key=lambda n: refine_by_threads[n]))
        query_ms["matl_refine"] = refine_by_threads[str(refine_threads)]
        breakdown = measure_breakdown(model, recognizer, refined, queries, warmup, refine_threads, device)
        if int8.get("recognizer") is not None:  # quantize=int8: the int8 query path, refined the same way
            refined_int8 = RefinedRecognizer(int8["recognizer"], refiner, templates=refined.templates)
            query_ms["matl_int8_refine"] = median_query_ms(synced(refined_int8, device), queries, warmup,
                                                           int8["matl_int8_threads"])
    int8.pop("recognizer", None)
    torch_ms = measure_torch_runtime(recognizer, refined, queries, warmup, counts, device)  # runtime=onnxruntime
    query_ms.update(torch_ms.pop("query_ms"))
    if options.faiss and hasattr(recognizer, "use_search"):
        faiss_node = cfg.search if search_name(cfg.get("search")) == "faiss" else default_faiss_node()
        try:
            recognizer.use_search(instantiate_node(faiss_node, "search"))
            query_ms["matl_faiss"] = median_query_ms(synced(recognizer, device), queries, warmup, threads)
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
    turns = {"matl": (synced(recognizer, device), threads), "sift_ransac": (lambda x: baseline(x.cpu()), sift_threads)}
    if refined is not None:
        turns["matl_refine"] = (synced(refined, device), refine_threads)
    query_ms.update(alternating_query_ms(turns, queries, warmup, int(options.rounds)))
    extra = measure_extra_baselines(cfg, options, gallery, cpu_queries, warmup, counts)  # bench.baselines
    query_ms.update(extra.pop("query_ms"))
    batched: dict[str, Any] = {}
    if options.batch:  # the crops of one camera frame in one call
        methods = {"matl": synced(recognizer, device), "matl_refine": refined and synced(refined, device),
                   "matl_int8_refine": refined_int8 and synced(refined_int8, device), "sift_ransac": baseline}
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
    from matl.models.checkpoint import (
        SHIPPED,
        build_model,
        checkpoint_info,
        load_checkpoint,
        resolve_checkpoint_keyword,
    )

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

    camera = measure_camera(cfg, options, device, thread_counts(options))  # bench.camera: RGB crops, no mask
    if camera:
        results["query_timing"]["breakdown_camera"] = camera.pop("breakdown_camera")
        results.update(camera)

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
                         "runtime": cfg.get("runtime", "torch"), "foreground": _choice("foreground")}
    write_json(out_dir / "bench.json", results)
    print_summary(results, console or Console())
    return results


def _choice(group: str) -> str | None:
    """The run's choice of a config group (None: called as a function, or the group left at null)."""
    try:
        from hydra.core.hydra_config import HydraConfig

        choice = HydraConfig.get().runtime.choices.get(group)
    except ValueError:  # called as a function (tests)
        return None
    return None if choice is None else str(choice)


def _data_name(cfg: DictConfig) -> str:
    choice = _choice("data")
    if choice is None:
        source = cfg.data.get("source")
        return str(source.get("catalog")) if source is not None and source.get("catalog") else "?"
    return choice


