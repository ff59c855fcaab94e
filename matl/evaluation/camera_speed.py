"""``query_ms_camera``: what a camera delivers, RGB crops without a mask, timed through the public API.

The bench's ``query_ms`` times the recognizer on test queries whose background is already 0. A robot's crop
comes from a detector's box on a real scene: no mask, a background, neighbours and occluders, camera effects.
Every RGB crop first goes through the foreground step (``foreground``: GrabCut by default, again from wider
insets when the answer does not verify), then the networks, the search, verification and refinement. Here:

* **Crops** (:func:`make_crops`): products of ``camera_data`` (matl.unseen's held-out products, never trained
  on) under the queries' random poses, each on a crop of a real photo (:class:`~matl.evaluation.conditions.Backgrounds`,
  :func:`~matl.evaluation.conditions.composite`); by ``bench.camera.mix`` alone, with a neighbouring product
  cut by the crop's edge (:class:`~matl.evaluation.conditions.Clutter`), or with that neighbour and occluders
  over the product (:class:`matl.data.occluders.Occluders`); a ``bench.camera.photometric`` share through the
  camera model (:class:`~matl.evaluation.conditions.Photometric`: a JPEG file), the rest PNG files. The files
  are decoded once before any timing (``breakdown_camera.decode_ms``: OpenCV, per crop).
* **Methods**, each through the public API on the SAME decoded crops, the gallery the same folder of the
  products' canonical images: ``matl`` (:meth:`matl.Recognizer.pretrained`, ``refine=false``), ``matl_refine``
  (the same with the bench's refiner), ``matl_fast_refine`` (``Recognizer.pretrained("fast")``, refined) with
  the bench's ``foreground`` (null: the library's default) and ``runtime``, every other setting the library's
  (verification, open set); ``sift_ransac``: the bench's keypoint baseline as ``matl.predict baseline=...``
  answers a file (:class:`~matl.inference.baseline_files.KeypointFileRecognizer`: the crop as given, no mask needed).
* **Timing** as ``query_ms``: every method at each thread count (torch's and OpenCV's), then its fastest in
  ``bench.rounds`` rounds in which the methods alternate (:mod:`matl.utils.timing`); a call answers one crop
  (``query_ms_camera``, the median) or ``bench.batch`` crops of a frame (``query_ms_camera_batch``, ms per crop
  over whole batches: a throughput).
* **Where the time goes** (``breakdown_camera``): one more pass of each MATL method at its fastest thread count
  with :meth:`matl.Recognizer.time_stages` on, the mean per crop of each stage the API ran, ``other`` the rest
  of the call; with the decoding they add up to ``total_ms``.
"""

from __future__ import annotations

import logging
import statistics
import tempfile
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig, ListConfig, OmegaConf

from matl.utils.errors import MatlError
from matl.utils.instantiate import instantiate_node
from matl.utils.timing import (
    StageTimer,
    alternating_batch_query_ms,
    alternating_query_ms,
    batch_query_ms,
    median_query_ms,
    stage_query_ms,
)

# the models, the catalogs and OpenCV are imported inside the functions: a bad option is reported in a second

log = logging.getLogger(__name__)

METHODS = ("matl", "matl_refine", "matl_fast_refine", "sift_ransac")
KINDS = ("background", "clutter", "occluded")
#: the stages of a MATL answer, in the order a query runs them (matl.Recognizer.time_stages)
STAGES = ("foreground", "framing", "networks", "search", "alignment", "refinement", "verification", "lookalikes",
          "keypoints", "uncover", "retries", "flow")


def camera_options(options: DictConfig) -> DictConfig:
    """``bench.camera``, checked against the bench's sizes (a one-line error names the key and the fix)."""
    camera = options.get("camera")
    if camera is None:
        raise MatlError("bench.camera is missing: conf/bench.yaml holds it (crops, seed, products, mix, photometric)")

    def integer(value: Any) -> bool:
        return isinstance(value, int) and not isinstance(value, bool)

    crops, seed, products = camera.get("crops"), camera.get("seed"), camera.get("products")
    if not integer(crops) or crops < 0:
        raise MatlError(f"bench.camera.crops={crops} is invalid: use an integer >= 0 (0: query_ms_camera not timed)")
    if not integer(seed) or seed < 0:
        raise MatlError(f"bench.camera.seed={seed} is invalid: use an integer >= 0")
    if products is not None and (not integer(products) or products < 1):
        raise MatlError(f"bench.camera.products={products} is invalid: use an integer >= 1, or null for all")
    mix = camera.get("mix")
    shares = OmegaConf.to_container(mix) if isinstance(mix, DictConfig) else mix
    if (not isinstance(shares, Mapping) or set(shares) - set(KINDS) or not shares
            or any(isinstance(v, bool) or not isinstance(v, (int, float)) or v < 0 for v in shares.values())
            or sum(shares.values()) <= 0):
        raise MatlError(f"bench.camera.mix={shares} is invalid: use shares >= 0 (not all 0) of {', '.join(KINDS)}")
    camera_occluders(camera)
    photometric = camera.get("photometric")
    if isinstance(photometric, bool) or not isinstance(photometric, (int, float)) or not 0 <= photometric <= 1:
        raise MatlError(f"bench.camera.photometric={photometric} is invalid: use a share in [0, 1]")
    if crops > 0:
        warmup, batch = int(options.query_warmup), int(options.batch)
        if crops < warmup + 1:
            raise MatlError(f"bench.camera.crops={crops} is smaller than bench.query_warmup + 1 = {warmup + 1}: "
                            "raise bench.camera.crops")
        if batch and crops < 2 * batch:
            raise MatlError(f"bench.camera.crops={crops} does not make two batches of bench.batch={batch} (one "
                            f"untimed): use bench.camera.crops >= {2 * batch}, or bench.batch=0")
    return camera


def camera_occluders(camera: DictConfig) -> Any:
    """The :class:`~matl.data.occluders.Occluders` of ``bench.camera.occluders`` (kinds' weights, hidden range)."""
    from matl.data.occluders import Occluders

    node = camera.get("occluders")
    if not isinstance(node, DictConfig) or "kinds" not in node or "hidden" not in node:
        raise MatlError(f"bench.camera.occluders={node} is invalid: use {{kinds: {{product: 1, gripper: 1, ...}}, "
                        "hidden: [low, high]}}")
    hidden = OmegaConf.to_container(node.hidden) if isinstance(node.hidden, ListConfig) else node.hidden
    try:
        return Occluders(OmegaConf.to_container(node.kinds) if isinstance(node.kinds, DictConfig) else node.kinds,
                         hidden)
    except MatlError as error:
        raise MatlError(f"bench.camera.occluders: {error}") from None


# ------------------------------------------------------------------------------------------- crops
@dataclass
class CameraCrop:
    """One crop as a camera delivers it.

    Attributes:
        data: the encoded file: PNG, or JPEG when it went through the camera model.
        kind: ``background``, ``clutter`` or ``occluded`` (:data:`KINDS`).
        photometric: whether it went through the camera model.
        object, plane: what it shows (the truth).
    """

    data: bytes
    kind: str
    photometric: bool
    object: str
    plane: str


def crop_kinds(mix: Mapping[str, float], count: int, seed: int) -> list[str]:
    """``count`` kinds in the proportions of ``mix`` (largest remainders), in a random order of ``seed``."""
    shares = np.array([float(mix.get(k, 0.0)) for k in KINDS])
    exact = shares / shares.sum() * count
    counts = np.floor(exact).astype(int)
    for k in np.argsort(-(exact - counts), kind="stable")[:count - int(counts.sum())]:
        counts[k] += 1
    kinds = np.repeat(np.array(KINDS), counts)
    return [str(k) for k in np.random.default_rng([seed, 1]).permutation(kinds)]


def make_crops(cs: Any, sampler: Any, camera: DictConfig) -> list[CameraCrop]:
    """``camera.crops`` crops of the products of ``cs`` (:class:`~matl.data.canonical.CanonicalSet`) at its image
    size, from ``camera.seed`` (see the module docstring); the poses are ``sampler``'s (the queries')."""
    import cv2

    from matl.evaluation.conditions import (
        Clutter,
        Photometric,
        composite,
        condition_rng,
        heldout_backgrounds,
        other_plane,
        sample_poses,
        to_uint8,
        warp_planes,
    )

    count, seed = int(camera.crops), int(camera.seed)
    size = int(cs.image_size)
    plane, query_H_canon = sample_poses(cs, sampler, count, seed)
    images, masks = warp_planes(cs, plane, query_H_canon)
    kinds = crop_kinds(OmegaConf.to_container(camera.mix), count, seed)
    through_camera = np.random.default_rng([seed, 2]).permutation(count) < round(float(camera.photometric) * count)
    backgrounds, clutter, lens = heldout_backgrounds(), Clutter(), Photometric()
    occluders = camera_occluders(camera)
    if "occluded" in kinds and occluders.kinds.get("product", 0.0) > 0 and cs.num_objects < 2:
        raise MatlError("bench.camera.mix.occluded lays other products over a crop's: use bench.camera.products >= 2, "
                        "or bench.camera.occluders.kinds.product=0")
    crops = []
    for i in range(count):
        p, rng = int(plane[i]), condition_rng(seed, "camera", i)
        scene = backgrounds.sample(size, rng)
        if kinds[i] != "background":  # a neighbour cut by the crop's edge, behind the product
            other = other_plane(cs, p, rng)
            g = torch.Generator().manual_seed(int(rng.integers(2**62)))
            own_H = sampler.sample(1, (size, size), g)[0]
            neighbour, neighbour_mask = warp_planes(cs, torch.tensor([other]),
                                                    clutter.neighbour_H(own_H, size, rng)[None])
            scene = composite(scene, neighbour[0], neighbour_mask[0])
        scene = composite(scene, images[i], masks[i])
        if kinds[i] == "occluded":  # the other products' prints lie on it; the bin wall's texture another photo
            others = np.flatnonzero(cs.plane_object != cs.plane_object[p])
            products = [(cs.images[k].astype(np.float64) / 255.0, cs.masks[k].astype(np.float64)) for k in others]
            scene, _, _ = occluders.apply(scene, masks[i], rng, products, floor=backgrounds.sample(size, rng))
        if through_camera[i]:
            data, _ = lens.apply(scene, rng)
        else:
            data = cv2.imencode(".png", cv2.cvtColor(to_uint8(scene), cv2.COLOR_RGB2BGR))[1].tobytes()
        crops.append(CameraCrop(data, kinds[i], bool(through_camera[i]), cs.object_names[int(cs.plane_object[p])],
                                cs.plane_names[p]))
    return crops


def decode_crops(crops: list[CameraCrop]) -> tuple[np.ndarray, list[float]]:
    """The crops decoded as a camera's frames are (OpenCV): ``(Q, H, W, 3)`` uint8 RGB, and each one's ms."""
    import cv2

    arrays, ms = [], []
    for crop in crops:
        start = time.perf_counter()
        bgr = cv2.imdecode(np.frombuffer(crop.data, np.uint8), cv2.IMREAD_COLOR)
        arrays.append(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB))
        ms.append((time.perf_counter() - start) * 1000.0)
    return np.stack(arrays), ms


# ------------------------------------------------------------------------------------------ methods
def camera_products(cfg: DictConfig, size: int, products: int | None) -> Any:
    """``camera_data``'s products at ``size`` px (the first ``products`` of them; None: all)."""
    from matl.data.canonical import load_canonical

    source = instantiate_node(cfg.camera_data.source, "camera_data.source")
    cs = load_canonical(source, size, cfg.paths.cache_dir)
    if products is not None:
        if products > cs.num_objects:
            raise MatlError(f"bench.camera.products={products} is more than camera_data's {cs.num_objects} products: "
                            f"use at most {cs.num_objects}, or null")
        cs = cs.subset_objects(list(range(products)))
    return cs


def camera_recognizers(cfg: DictConfig, device: torch.device) -> dict[str, Any]:
    """The MATL methods' :class:`matl.Recognizer` s, not enrolled yet (see the module docstring)."""
    from matl.inference.api import Recognizer
    from matl.inference.runtime import runtime_option

    options: dict[str, Any] = {"device": str(device), "runtime": runtime_option(cfg)}
    if cfg.get("foreground") is not None:  # else the library's default
        options["foreground"] = cfg.foreground
    return {"matl": Recognizer.pretrained(refine=False, **options),
            "matl_refine": Recognizer.pretrained(refine=instantiate_node(cfg.refiner, "refiner"), **options),
            "matl_fast_refine": Recognizer.pretrained("fast", refine=instantiate_node(cfg.refiner, "refiner"),
                                                      **options)}


def _matl_call(recognizer: Any) -> Callable[[torch.Tensor], Any]:
    """A crop batch ``(B, H, W, 3)`` uint8 as a user hands it over: a list of ``HxWx3`` uint8 RGB arrays."""
    return lambda crops: recognizer.predict([c.numpy() for c in crops])


def _file_call(recognizer: Any) -> Callable[[torch.Tensor], Any]:
    """The same for a keypoint file recognizer, whose calls take float RGB in [0, 1] (as predict's files)."""
    return lambda crops: recognizer.predict_details([c.numpy().astype(np.float32) / 255.0 for c in crops])[0]


def _fastest(by_threads: dict[str, float]) -> int:
    return int(min(by_threads, key=lambda n: by_threads[n]))


def measure_camera(cfg: DictConfig, options: DictConfig, device: torch.device, counts: list[int]) -> dict[str, Any]:
    """``query_ms_camera`` and the rest (module docstring); empty when ``bench.camera.crops`` is 0.

    Returns:
        ``query_ms_camera``, ``speedup_camera_vs_sift``, with ``bench.batch`` ``query_ms_camera_batch`` and
        ``speedup_camera_vs_sift_batch``, ``camera_timing`` (how) and ``breakdown_camera`` (where the time goes).
    """
    from matl.baselines.recognizer import build_baseline
    from matl.evaluation.unseen import write_gallery
    from matl.inference.baseline_files import KeypointFileRecognizer

    camera = camera_options(options)
    if int(camera.crops) == 0:
        return {}
    warmup, batch, rounds = int(options.query_warmup), int(options.batch), int(options.rounds)
    recognizers = camera_recognizers(cfg, device)
    size, num_anchors = recognizers["matl"].image_size, recognizers["matl"].num_anchors
    cs = camera_products(cfg, size, camera.get("products"))
    sampler = instantiate_node(cfg.camera_data.homography, "camera_data.homography")
    crops = make_crops(cs, sampler, camera)
    decoded, decode_ms = decode_crops(crops)
    queries = torch.from_numpy(decoded)  # (Q, S, S, 3) uint8: what every method is handed
    baseline_name = str(cfg.baseline._target_).rsplit(".", 1)[-1]
    setup: dict[str, dict[str, float]] = {}
    with tempfile.TemporaryDirectory(prefix="matl_bench_camera_") as folder:
        write_gallery(cs, Path(folder))  # <object>/<plane>.png: the same files for every method
        for name, recognizer in recognizers.items():
            start = time.perf_counter()
            recognizer.enrol(folder, cache=False)
            enrolled = time.perf_counter()
            _ = recognizer.threshold  # the open-set calibration (threshold=auto), once per gallery
            setup[name] = {"enrol_s": enrolled - start, "calibration_s": time.perf_counter() - enrolled}
        start = time.perf_counter()
        sift = KeypointFileRecognizer(build_baseline(cfg.baseline, baseline_name), baseline_name, size, num_anchors)
        sift.enrol(folder)
        setup["sift_ransac"] = {"enrol_s": time.perf_counter() - start}
    calls = {name: _matl_call(r) for name, r in recognizers.items()}
    calls["sift_ransac"] = _file_call(sift)

    log.info("bench: query_ms_camera (%d crops, %s)", len(crops), ", ".join(calls))
    by_threads = {name: {str(n): median_query_ms(call, queries, warmup, n) for n in counts}
                  for name, call in calls.items()}
    threads = {name: _fastest(ms) for name, ms in by_threads.items()}
    query_ms = alternating_query_ms({name: (call, threads[name]) for name, call in calls.items()}, queries, warmup,
                                    rounds)
    out: dict[str, Any] = {"query_ms_camera": query_ms,
                           "speedup_camera_vs_sift": _speedups(query_ms)}
    batch_by_threads: dict[str, dict[str, float]] = {}
    batch_threads: dict[str, int] = {}
    if batch:
        batch_by_threads = {name: {str(n): batch_query_ms(call, queries, batch, 1, n) for n in counts}
                            for name, call in calls.items()}
        batch_threads = {name: _fastest(ms) for name, ms in batch_by_threads.items()}
        batched = alternating_batch_query_ms({name: (call, batch_threads[name]) for name, call in calls.items()},
                                             queries, batch, 1, rounds)
        out.update(query_ms_camera_batch=batched, speedup_camera_vs_sift_batch=_speedups(batched))

    breakdown: dict[str, Any] = {"decode_ms": statistics.fmean(decode_ms),
                                 "decode_ms_median": statistics.median(decode_ms)}
    for name, recognizer in recognizers.items():
        breakdown[name] = measure_stages(recognizer, calls[name], queries, warmup, threads[name],
                                         breakdown["decode_ms"])
    answers = {name: call(queries) for name, call in calls.items()}  # untimed: is the work timed the real one?
    rec_acc = {name: float(np.mean([m.object == c.object for m, c in zip(got, crops, strict=True)]))
               for name, got in answers.items()}
    first = recognizers["matl"].options()
    out["camera_timing"] = {
        "crops": len(crops), "warmup": warmup, "rounds": rounds, "batch": batch,
        "batches": len(crops) // batch - 1 if batch else 0, "seed": int(camera.seed),
        "kinds": {k: sum(c.kind == k for c in crops) for k in KINDS},
        "photometric": sum(c.photometric for c in crops), "crop_px": size,
        "products": cs.num_objects, "planes": cs.num_planes, "gallery_anchors": cs.num_planes * num_anchors,
        "foreground": first["foreground"], "runtime": first["runtime"], "runtime_fallback": first["runtime_fallback"],
        "refiner": type(recognizers["matl_refine"].refiner).__name__, "baseline": baseline_name,
        "threads": threads, "ms_by_threads": by_threads, "batch_threads": batch_threads,
        "batch_ms_by_threads": batch_by_threads, "setup": setup, "rec_acc": rec_acc,
        "statistic": "query_ms_camera: median over single-crop calls, the methods alternating in bench.rounds "
                     "rounds, each at its fastest thread count; query_ms_camera_batch: the wall clock of the timed "
                     "batches (one untimed a pass) over their crops, rounds alike",
        "timed_region": "one public call per crop (or batch): matl.Recognizer.predict on uint8 RGB arrays "
                        "(foreground step, retries, networks, search, verification, refinement, pose in the crop's "
                        "pixels, open-set answer); sift_ransac: KeypointFileRecognizer.predict_details, as "
                        "matl.predict baseline=... answers a file, the crop as given; decoding measured apart",
        "rec_acc_note": "share of the crops whose answer names the product shown (one untimed batch call each)",
    }
    out["breakdown_camera"] = breakdown
    return out


def _speedups(query_ms: dict[str, float]) -> dict[str, float | None]:
    sift = query_ms.get("sift_ransac")
    return {name: (sift / ms if sift and ms else None) for name, ms in query_ms.items() if name != "sift_ransac"}


def measure_stages(recognizer: Any, call: Callable[[torch.Tensor], Any], queries: torch.Tensor, warmup: int,
                   threads: int, decode_ms: float) -> dict[str, Any]:
    """Where a MATL method's single-crop call spends its milliseconds (:meth:`matl.Recognizer.time_stages`), means
    per crop at ``threads``; ``stages_ms`` adds the decoding (measured apart) and adds up to ``total_ms``."""
    timer = StageTimer()
    recognizer.time_stages(timer)
    try:
        parts = stage_query_ms(call, queries, timer, warmup, threads)
    finally:
        recognizer.time_stages(None)
    stages = {"decode": decode_ms, **{k: parts["stages_ms"].get(k, 0.0) for k in STAGES},
              "other": parts["stages_ms"]["other"]}
    calls = parts["calls_per_query"]
    return {"threads": threads, "total_ms": decode_ms + parts["call_ms"], "call_ms": parts["call_ms"],
            "call_ms_median": parts["call_ms_median"], "stages_ms": stages, "within_ms": parts["within_ms"],
            "retried_share": calls.get("retries/foreground", 0.0)}


def summary_rows(results: dict[str, Any]) -> list[tuple[str, str, str]]:
    """Rows ``(measure, value, note)`` of the bench's summary table for the camera crops (none when not timed)."""
    q = results.get("query_ms_camera")
    if not q:
        return []
    how, parts = results["camera_timing"], results["query_timing"].get("breakdown_camera", {})
    batched = results.get("query_ms_camera_batch") or {}
    speedup, speedup_batch = results["speedup_camera_vs_sift"], results.get("speedup_camera_vs_sift_batch") or {}
    rows = []
    for name in METHODS:
        note = f"{how['threads'][name]} thread(s); rec_acc {how['rec_acc'][name]:.2f}"
        if speedup.get(name):
            note += f"; {speedup[name]:.1f}x sift"
        if name in batched:
            note += f"; batch {how['batch']}: {batched[name]:.2f} ms" + (
                f" ({speedup_batch[name]:.1f}x)" if speedup_batch.get(name) else "")
        rows.append((f"query_ms_camera.{name}", f"{q[name]:.2f}", note))
    for name in METHODS[:3]:
        stages = parts[name]["stages_ms"]
        rows.append((f"breakdown_camera.{name} (ms)", f"{parts[name]['total_ms']:.2f}",
                     ", ".join(f"{k} {v:.2f}" for k, v in stages.items() if abs(v) >= 0.005)))
    return rows
