"""The catalogue benchmark: ``python -m matl.unseen condition=catalog``, recognition against gallery size.

A retail picking cell enrols hundreds to tens of thousands of products, many of them near twins. This
benchmark builds one fixed ordering of held-out products (:class:`~matl.data.catalog.lookalikes.LookalikeCatalog`:
photos no training catalog uses, a share of the products in look-alike families) and, for every size ``n`` of
``catalog_sizes``:

1. *Gallery*: the first ``n`` products (``<out>/n<n>/gallery/<object>/<plane>.png``), so smaller galleries are
   subsets of larger ones; the next ``round(catalog.leave_out * n)`` products are *left out*
   (``<out>/n<n>/left_out/``): never enrolled, their queries must be answered unknown.
2. *Queries*: ``queries`` files drawn uniformly over the planes of the gallery's and the left-out products, in
   the ``photometric`` condition's camera (JPEG files, :class:`~matl.evaluation.conditions.Photometric`); the
   truth of the enrolled products' queries in ``truth.jsonl`` (with ``family``: the look-alike family when one
   of its other members is enrolled too), every query's in ``truth_all.jsonl``.
3. *Methods* (``catalog.methods``): predict's code on the files (:class:`~matl.evaluation.unseen_methods.MethodRun`),
   MATL with the open set on (``threshold``, ``auto``: calibrated on the gallery) up to
   ``catalog.calibrate_max_products`` products (every size by default) and a closed set above (the open set needs
   the gallery's calibration, a given threshold too for its answers' scores; it poses and verifies 8 warped copies
   of each of at most ``calibration_planes`` planes); keypoint baselines
   answer a closed set and are predicted up to ``catalog.keypoint_max_products`` (their ``query_ms`` at every
   size).
4. *Scores*: ``rec_acc`` (enrolled queries answered with the right product, as predict answers them),
   ``lookalike_rec_acc`` (the same over queries of products with an enrolled look-alike), ``unknown_rejected``
   (left-out products' queries answered unknown), ``refine_pose_acc_5px`` (matl_refine's poses within 5 px),
   ``query_ms`` (median of single queries, gallery in memory) and ``enrol_s`` (the gallery's enrolment).

Writes ``<out>/catalog.json`` (one row per size), ``<out>/catalog.md`` and ``<out>/catalog.png`` (accuracy and
query time against gallery size).
"""

from __future__ import annotations

import json
import logging
import shutil
import time
from pathlib import Path
from typing import Any

import hydra
import numpy as np
from omegaconf import DictConfig, ListConfig, OmegaConf

from matl.data.canonical import CanonicalSet
from matl.data.catalog.lookalikes import MAX_PRODUCTS, CatalogProduct, LookalikeCatalog, load_lookalikes
from matl.evaluation.condition_writers import Queries, write_gallery, write_photometric
from matl.evaluation.conditions import sample_poses
from matl.evaluation.open_set import open_set_summary
from matl.evaluation.unseen_methods import MATL_METHODS, METHODS, MethodRun, own_command, shared_options, time_methods
from matl.evaluation.unseen_results import score_condition
from matl.utils.errors import MatlError

log = logging.getLogger(__name__)

MAX_GALLERY = 10_000  # the largest gallery catalog_sizes may ask for
ROW_KEYS = ("products", "rec_acc", "lookalike_rec_acc", "unknown_rejected", "refine_pose_acc_5px", "query_ms")


# ------------------------------------------------------------------------------------------ options
def catalog_sizes(cfg: DictConfig) -> list[int]:
    """``catalog_sizes``: distinct integers in [2, :data:`MAX_GALLERY`], sorted (one-line error otherwise)."""
    value = cfg.get("catalog_sizes")
    items = list(value) if isinstance(value, (list, tuple, ListConfig)) else None
    shown = OmegaConf.to_container(value) if isinstance(value, ListConfig) else value
    if not items or not all(isinstance(v, int) and not isinstance(v, bool) and v >= 2 for v in items) \
            or len(set(items)) != len(items):
        raise MatlError(f"catalog_sizes={shown} is invalid: use a list of distinct gallery sizes, integers >= 2, "
                        "e.g. 'catalog_sizes=[20,200,2000]'")
    if max(items) > MAX_GALLERY:
        raise MatlError(f"catalog_sizes={shown} is invalid: the catalogue makes galleries of at most {MAX_GALLERY} "
                        f"products; drop {max(items)}")
    return sorted(int(v) for v in items)


def check_catalog(cfg: DictConfig) -> list[int]:
    """Validate ``catalog_sizes`` and ``catalog.*`` of a composed ``conf/unseen.yaml``; returns the sizes."""
    sizes = catalog_sizes(cfg)
    node = cfg.catalog
    leave_out = node.get("leave_out")
    if not isinstance(leave_out, (int, float)) or isinstance(leave_out, bool) or not 0.0 < leave_out <= 1.0:
        raise MatlError(f"catalog.leave_out={leave_out} is invalid: use a fraction in (0, 1] of the gallery size "
                        "(products kept out, whose queries must be answered unknown)")
    total = max(sizes) + _left_out_count(cfg, max(sizes))
    if total > MAX_PRODUCTS:
        raise MatlError(f"catalog.leave_out={leave_out} is invalid with a gallery of {max(sizes)}: at most "
                        f"{MAX_PRODUCTS} products in all; use a smaller leave_out")
    try:
        _catalog(cfg, max(sizes))
    except ValueError as error:
        raise MatlError(f"catalog.{error}") from None
    methods = list(node.get("methods") or [])
    if not methods or not all(isinstance(m, str) and m in METHODS for m in methods) or len(set(methods)) != len(
            methods) or not any(m in MATL_METHODS for m in methods):
        shown = OmegaConf.to_container(node.methods) if isinstance(node.methods, ListConfig) else node.methods
        raise MatlError(f"catalog.methods={shown} is invalid: use a list of {', '.join(METHODS)} with matl or "
                        "matl_refine in it, e.g. [matl_refine, sift]")
    for key, low in (("calibrate_max_products", 2), ("keypoint_max_products", 0), ("timing_queries", 0), ("seed", 0),
                     ("texture_px", 32)):
        value = node.get(key)
        if not isinstance(value, int) or isinstance(value, bool) or value < low:
            raise MatlError(f"catalog.{key}={value} is invalid: use an integer >= {low}")
    return sizes


def _left_out_count(cfg: DictConfig, n: int) -> int:
    return max(1, round(float(cfg.catalog.leave_out) * n))


def _catalog(cfg: DictConfig, largest: int) -> LookalikeCatalog:
    """The products of the largest gallery and its left-out ones (ValueError: an option the generator refuses)."""
    node = cfg.catalog
    family = node.family_size
    family = tuple(family) if isinstance(family, (list, ListConfig)) else family
    return LookalikeCatalog(largest + _left_out_count(cfg, largest), int(node.seed), node.lookalike_share, family,
                            node.planes, texture_px=int(node.texture_px))


# ------------------------------------------------------------------------------------------ one size
def family_of_enrolled(products: list[CatalogProduct], n: int) -> dict[str, str]:
    """Object name -> look-alike family, for the products among the first ``n`` whose family has another member
    among them too (a gallery of ``n`` holds a near twin of each)."""
    counts: dict[str, int] = {}
    for p in products[:n]:
        if p.family is not None:
            counts[p.family] = counts.get(p.family, 0) + 1
    return {p.spec.name: p.family for p in products[:n] if p.family is not None and counts[p.family] > 1}


def write_size(cfg: DictConfig, cs: CanonicalSet, products: list[CatalogProduct], n: int, out: Path
               ) -> tuple[list[dict[str, Any]], list[str]]:
    """Gallery, left-out products and photometric queries of the gallery of the first ``n`` products into ``out``.

    Returns:
        ``(truth, left_out)``: every query's record (``enrolled``, ``family``, ``change``) and the left-out names.
    """
    m = _left_out_count(cfg, n)
    cs_n = cs.subset_objects(list(range(n + m)))
    sampler = hydra.utils.instantiate(cfg.data.homography)
    plane, query_H_canon = sample_poses(cs_n, sampler, int(cfg.queries), int(cfg.query_seed))
    gallery_files, canon_H_file = write_gallery(cs_n, out / "gallery")
    q = Queries(cs_n, plane, query_H_canon, int(cfg.query_seed), None, list(range(n + m)), cfg)
    truth = write_photometric(q, out / "queries", gallery_files, canon_H_file, out)
    left_out = [p.spec.name for p in products[n:n + m]]
    (out / "left_out").mkdir(exist_ok=True)
    for name in left_out:  # predict never sees them
        shutil.move(str(out / "gallery" / name), str(out / "left_out" / name))
    families = family_of_enrolled(products, n)
    change = {p.spec.name: p.change for p in products[:n + m]}
    for t in truth:
        t["enrolled"] = t["object"] not in left_out
        t["family"] = families.get(t["object"])
        t["change"] = change[t["object"]]
        if not t["enrolled"]:
            t["gallery_image"] = str(Path("left_out") / Path(t["gallery_image"]).relative_to("gallery"))
    (out / "truth.jsonl").write_text("".join(json.dumps(t) + "\n" for t in truth if t["enrolled"]))
    (out / "truth_all.jsonl").write_text("".join(json.dumps(t) + "\n" for t in truth))
    return truth, left_out


def _predictions(path: Path, out: Path) -> dict[str, dict[str, Any]]:
    """predict's records by query path relative to ``out``."""
    records = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    return {str(Path(r["image"]).relative_to(out)) if Path(r["image"]).is_absolute() else r["image"]: r
            for r in records}


def score_method(run: MethodRun, truth: list[dict[str, Any]], out: Path, image_size: int) -> dict[str, Any]:
    """One method's scores of a size's predictions: ``rec_acc`` and ``pose_acc_5px`` over the enrolled products'
    queries, ``lookalike_rec_acc`` over those with an enrolled look-alike, the closed-set ``rec_acc_closed`` and,
    for a MATL method, ``unknown_rejected`` (left-out products' queries answered unknown)."""
    pred_path = Path(run.options["out"])
    enrolled = [t for t in truth if t["enrolled"]]
    summary, rows, _ = score_condition(pred_path, out / "truth.jsonl", list(range(len(enrolled))), {}, image_size)
    predictions = _predictions(pred_path, out)
    twins = [row for row, t in zip(rows, enrolled, strict=True) if t["family"] is not None]
    nearest = [predictions.get(t["image"], {}).get("nearest_object", predictions.get(t["image"], {}).get("object"))
               == t["object"] for t in enrolled]
    result = {"rec_acc": summary["rec_acc"], "rec_acc_closed": float(np.mean(nearest)),
              "lookalike_rec_acc": float(np.mean([r["correct"] for r in twins])) if twins else None,
              "lookalike_queries": len(twins), "pose_acc_5px": summary["pose_acc_5px"],
              "corner_err_px_median": summary["corner_err_px_median"], "unknown_rejected": None}
    if run.method in MATL_METHODS and any(not t["enrolled"] for t in truth):
        open_set = open_set_summary(truth, predictions)
        result.update(unknown_rejected=open_set["unknown_recall"], unknown_precision=open_set["unknown_precision"])
    return result


def run_size(cfg: DictConfig, cs: CanonicalSet, products: list[CatalogProduct], n: int, ckpt_path: Path,
             image_size: int, out: Path, threshold: float | str | None) -> dict[str, Any]:
    """Write, predict, score and time the gallery of the first ``n`` products with MATL's open-set ``threshold``
    (``auto``: calibrated on this gallery; None: the closed set, ``unknown_rejected`` None); returns its row of
    catalog.json."""
    node = cfg.catalog
    started = time.perf_counter()
    truth, left_out = write_size(cfg, cs, products, n, out)
    written_s = time.perf_counter() - started
    shared = shared_options(cfg, ckpt_path, out, threshold, 1.0, float(cfg.query_fill))
    methods = [str(m) for m in node.methods]
    runs = {m: MethodRun.of(m, cfg, shared, out / f"predictions_{m}.jsonl") for m in methods}
    per_method: dict[str, dict[str, Any]] = {m: {"command": run.command} for m, run in runs.items()}
    timed = int(node.timing_queries)
    if timed > 0:  # first, so that enrol_s is a fresh enrolment (features, open-set calibration) and not a cache read
        files = sorted((out / "queries").iterdir())[: timed + int(cfg.timing.warmup)]
        warmup = min(int(cfg.timing.warmup), max(len(files) - 1, 0))
        for method, run in runs.items():
            for cached in (out / "gallery").glob(".matl_*") if method in MATL_METHODS else ():
                cached.unlink()
            started = time.perf_counter()
            recognizer = run.recognizer().enrol(out / "gallery")
            getattr(recognizer, "threshold", None)  # the open-set calibration, else done by the first query
            per_method[method]["enrol_s"] = time.perf_counter() - started
            per_method[method]["query_ms"] = time_methods({method: recognizer}, files, warmup,
                                                          int(cfg.timing.threads))[method]
            del recognizer
    for method, run in runs.items():
        entry = per_method[method]
        if method in MATL_METHODS or n <= int(node.keypoint_max_products):
            log.info("catalog: %d products: predicting %d queries with %s", n, len(truth), method)
            started = time.perf_counter()
            summary = run.run()  # predict's library function on the files (its gallery features: the cache above)
            entry["predict_s"] = time.perf_counter() - started
            entry["threshold"] = summary.get("threshold")
            entry.update(score_method(run, truth, out, image_size))
        else:
            entry["skipped"] = f"gallery of {n} > catalog.keypoint_max_products={int(node.keypoint_max_products)}"
    primary = next(m for m in ("matl_refine", "matl") if m in per_method)
    main = per_method[primary]
    enrolled = [t for t in truth if t["enrolled"]]
    row = {"products": n, "rec_acc": main["rec_acc"], "lookalike_rec_acc": main["lookalike_rec_acc"],
           "unknown_rejected": main["unknown_rejected"] if threshold is not None else None,
           "refine_pose_acc_5px": per_method["matl_refine"]["pose_acc_5px"] if "matl_refine" in per_method else None,
           "query_ms": main.get("query_ms"), "method": primary, "rec_acc_closed": main["rec_acc_closed"],
           "threshold": main.get("threshold"), "threshold_option": threshold,
           "enrol_s": main.get("enrol_s"), "left_out_products": len(left_out),
           "lookalike_products": sum(p.family is not None for p in products[:n]),
           "queries": len(enrolled), "lookalike_queries": main["lookalike_queries"],
           "left_out_queries": len(truth) - len(enrolled), "files_s": written_s,
           "folder": out.name, "methods": per_method}
    log.info("catalog: %s", json.dumps({k: row[k] for k in ROW_KEYS}))
    return row


# ------------------------------------------------------------------------------------------ all sizes
def catalog_title(lookalike_share: float, queries: int, threads: int) -> str:
    """The catalogue figure's title: the look-alike share, the queries per size and the timing's threads."""
    return (f"catalogue of held-out products ({lookalike_share:.0%} in look-alike families), "
            f"{queries} photometric queries per size; query_ms at {threads} thread(s)")


def plot_catalog(rows: list[dict[str, Any]], path: Path, title: str) -> Path:
    """Accuracy (left) and ``query_ms`` (right, log) against gallery size (log) of every row, per method."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sizes = [r["products"] for r in rows]
    fig, (acc, ms) = plt.subplots(1, 2, figsize=(10, 4))
    for key, label in (("rec_acc", "rec_acc"), ("lookalike_rec_acc", "lookalike_rec_acc"),
                       ("unknown_rejected", "unknown_rejected"), ("refine_pose_acc_5px", "refine_pose_acc_5px")):
        acc.plot(sizes, [np.nan if r[key] is None else r[key] for r in rows], "o-",
                 label=f"{rows[0]['method']} {label}")
    baselines = [m for m in rows[0]["methods"] if m not in MATL_METHODS]
    for m in baselines:
        acc.plot(sizes, [r["methods"][m].get("rec_acc", np.nan) for r in rows], "s--", label=f"{m} rec_acc")
    timed = False
    for m in rows[0]["methods"]:
        times = [r["methods"][m].get("query_ms") or np.nan for r in rows]
        timed |= bool(np.isfinite(times).any())
        ms.plot(sizes, times, "o-" if m in MATL_METHODS else "s--", label=m)
    for ax in (acc, ms):
        ax.set_xscale("log")
        ax.set_xlabel("gallery size (products)")
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=7)
    acc.set_ylim(0, 1.02)
    acc.set_ylabel("share of queries")
    if timed:
        ms.set_yscale("log")
    else:  # catalog.timing_queries=0: nothing to put on a log axis
        ms.text(0.5, 0.5, "not timed (catalog.timing_queries=0)", ha="center", va="center", transform=ms.transAxes)
    ms.set_ylabel("query_ms (median, batch of 1)")
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def _fmt(value: Any, digits: int = 3) -> str:
    return "-" if value is None else f"{float(value):.{digits}f}"


def catalog_table(rows: list[dict[str, Any]], command: str) -> str:
    """``catalog.md``: one row per gallery size, MATL's scores and every method's ``query_ms``."""
    methods = list(rows[0]["methods"])
    baselines = [m for m in methods if m not in MATL_METHODS]
    header = ["products", "rec_acc", "lookalike_rec_acc", "unknown_rejected", "refine_pose_acc_5px", "query_ms",
              "enrol_s", *(f"{m} {k}" for m in baselines for k in ("rec_acc", "query_ms"))]
    lines = [f"`{command}`" if command else "(called as a function)", "", "| " + " | ".join(header) + " |",
             "|---" * len(header) + "|"]
    for r in rows:
        cells = [str(r["products"]), _fmt(r["rec_acc"]), _fmt(r["lookalike_rec_acc"]), _fmt(r["unknown_rejected"]),
                 _fmt(r["refine_pose_acc_5px"]), _fmt(r["query_ms"], 1), _fmt(r["enrol_s"], 1)]
        for m in baselines:
            cells += [_fmt(r["methods"][m].get("rec_acc")), _fmt(r["methods"][m].get("query_ms"), 1)]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def run_catalog(cfg: DictConfig, ckpt_path: Path, image_size: int, out: Path) -> dict[str, Any]:
    """Every size of ``catalog_sizes`` into ``<out>/n<size>/``; writes ``<out>/catalog.json`` (after each size, the
    rows so far with ``complete`` false), ``catalog.md`` and ``catalog.png``; returns catalog.json's content."""
    from matl.utils.io import write_json

    sizes = check_catalog(cfg)
    for n in sizes:
        if (out / f"n{n}" / "gallery").exists():
            raise MatlError(f"out={out} already holds n{n}/gallery/ from an earlier run: use a new out= folder")
    catalog = _catalog(cfg, max(sizes))
    file_size = int(cfg.file_size or image_size)
    started = time.perf_counter()
    products = catalog.products()
    cs = load_lookalikes(catalog, file_size, cfg.paths.cache_dir)
    log.info("catalog: %d products (%d planes) in %.1f s", cs.num_objects, cs.num_planes, time.perf_counter() - started)
    rows: list[dict[str, Any]] = []
    limit = int(cfg.catalog.calibrate_max_products)
    for n in sizes:  # above calibrate_max_products: the closed set (the open set needs the gallery's calibration)
        threshold = cfg.get("threshold", "auto") if n <= limit else None
        rows.append(run_size(cfg, cs, products, n, ckpt_path, image_size, out / f"n{n}", threshold))
        write_json(out / "catalog.json", {"command": own_command(), "rows": rows, "complete": False})  # so far
    command = own_command()
    node = OmegaConf.to_container(cfg.catalog, resolve=True)
    plot = plot_catalog(rows, out / "catalog.png", catalog_title(node["lookalike_share"], cfg.queries,
                                                                 cfg.timing.threads))
    data = {"command": command, "rows": rows, "columns": list(ROW_KEYS), "catalog": node,
            "generator": repr(catalog), "checkpoint": str(ckpt_path), "image_size": image_size,
            "file_size": file_size, "queries": int(cfg.queries), "query_seed": int(cfg.query_seed),
            "threshold": cfg.get("threshold", "auto"),
            "photometric": OmegaConf.to_container(cfg.photometric, resolve=True),
            "timing": {"queries": int(cfg.catalog.timing_queries), "warmup": int(cfg.timing.warmup),
                       "threads": int(cfg.timing.threads),
                       "statistic": "median over single-query calls (batch of 1), gallery in memory, file decoded"},
            "files": {"table": "catalog.md", "figure": plot.name}, "complete": True}
    write_json(out / "catalog.json", data)
    (out / "catalog.md").write_text(catalog_table(rows, command))
    log.info("catalog: -> %s\n%s", out / "catalog.json", catalog_table(rows, command))
    return data
