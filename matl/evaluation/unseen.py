"""The unseen-products benchmark: gallery and query files of products a checkpoint never saw, predicted and scored.

The library side of ``python -m matl.unseen`` (the command and its options: :mod:`matl.unseen`). Every
condition (:mod:`matl.evaluation.conditions`) is written from the same products and query poses into
``<out>/<condition>/`` (:mod:`matl.evaluation.condition_writers`) and predicted by every method through
predict's library function, in this process (:mod:`matl.evaluation.unseen_methods`: MATL, MATL with
refinement, and the keypoint baselines with ``baseline=``, on the same files framed the same way), scored
by :func:`~matl.evaluation.unseen_results.score_condition` (:mod:`matl.evaluation.score`'s metrics) and timed
in this process on the same queries.
"""

from __future__ import annotations

import itertools
import json
import logging
from pathlib import Path
from typing import Any

import hydra
import torch
from omegaconf import DictConfig, ListConfig, OmegaConf

from matl.data.canonical import load_canonical, require_models
from matl.data.occluders import Occluders
from matl.evaluation.catalog import check_catalog, run_catalog
from matl.evaluation.condition_writers import WRITERS, Queries, write_gallery
from matl.evaluation.conditions import CONDITIONS, sample_poses
from matl.evaluation.open_set import open_set_summary, plot_open_set
from matl.evaluation.score import METRICS, write_rows
from matl.evaluation.unseen_methods import (
    MATL_METHODS,
    METHODS,
    MethodRun,
    foreground_choice,
    own_command,
    score_command,
    shared_options,
    time_methods,
)
from matl.evaluation.unseen_results import (
    QUERY_FIELDS,
    TABLE_METRICS,
    benchmark_table,
    breakdown_groups,
    breakdown_result,
    headline_queries,
    score_condition,
    write_speed_accuracy,
)
from matl.inference.runtime import runtime_option
from matl.models.checkpoint import checkpoint_info, load_checkpoint
from matl.utils.config import validate_config
from matl.utils.errors import MatlError

log = logging.getLogger(__name__)

SYNTHETIC = "matl.data.catalog.SyntheticCatalog"
SHELVES = "matl.data.catalog.shelves.ShelfCatalog"
CROP_FILL = 0.6  # the catalogs frame each plane's longer side at 0.6 of the image (data.source.fill)


# ------------------------------------------------------------------------------------ never seen
def _catalog_products(source: dict[str, Any]) -> list[Any]:
    """The product specs of a procedural catalog's config (``SyntheticCatalog``, ``ShelfCatalog``): the
    catalog is built from its own config, which renders nothing until asked."""
    return hydra.utils.instantiate(source).products()


def seen_products(train_data: dict[str, Any], test_source: Any,
                  test_names: list[str]) -> tuple[dict[str, str], dict[str, list[str]], str]:
    """Which test products the training catalog holds, and which are only related to one.

    Args:
        train_data: the checkpoint's ``data`` config (``matl_config["data"]``).
        test_source: the instantiated source of the test products.
        test_names: the test set's object names.
    Returns:
        ``(seen, related, how)``: ``seen`` maps a test product to the reason it counts as seen (same
        name, or same brand and title); ``related`` lists looser kinships kept in the test (same
        title under another brand, same brand and kind); ``how`` says what was compared.
    """
    source = train_data.get("source") or {}
    objects = train_data.get("objects")
    if source.get("_target_") not in (SYNTHETIC, SHELVES) or not hasattr(test_source, "products"):
        kind = source.get("_target_", "?")
        return {}, {}, f"not verified: the training source is {kind}, not a procedural catalog"
    train = _catalog_products(source)
    if objects is not None:
        train = [train[int(i)] for i in objects]
    by_name = {p.name: p for p in train}
    by_title = {(p.brand.name, p.title): p for p in train}
    seen: dict[str, str] = {}
    related: dict[str, list[str]] = {}
    for p in test_source.products():
        if p.name not in test_names:
            continue
        if p.name in by_name:
            seen[p.name] = f"same name as training product {p.name}"
        elif (p.brand.name, p.title) in by_title:
            seen[p.name] = f"same brand and title as training product {by_title[(p.brand.name, p.title)].name}"
        else:
            kin = [f"same title as {q.name}" for q in train if q.title == p.title]
            kin += [f"same brand and kind as {q.name}" for q in train
                    if (q.brand.name, q.kind) == (p.brand.name, p.kind)]
            if kin:
                related[p.name] = kin
    what = (f"ShelfCatalog(shelves={source.get('shelves')}, first_seed={source.get('first_seed')})"
            if source.get("_target_") == SHELVES else
            f"SyntheticCatalog(catalog={source.get('catalog')!r}, seed={source.get('seed')})")
    return seen, related, f"product specs compared with the training catalog {what}"


def left_out_products(names: list[str], fraction: float, seed: int) -> list[str]:
    """``round(fraction * len(names))`` products drawn with ``seed``, kept out of the gallery (open set)."""
    count = round(fraction * len(names))
    order = torch.randperm(len(names), generator=torch.Generator().manual_seed(int(seed) + 1)).tolist()
    return sorted(names[i] for i in order[:count])


def _left_out_dir(out: Path, name: str) -> Path:
    (out / "left_out").mkdir(exist_ok=True)
    return out / "left_out" / name


# ------------------------------------------------------------------------------------ entry point
def _names(value: Any, valid: tuple[str, ...], key: str, allow_all: bool) -> list[str]:
    """A single name, ``all`` or a list, checked against ``valid`` (one-line error naming them)."""
    items = list(value) if isinstance(value, (list, tuple, ListConfig)) else [value]
    if allow_all and items == ["all"]:
        return list(valid)
    options = ", ".join(valid) + (" or all" if allow_all else "")
    bad = [v for v in items if not isinstance(v, str) or v not in valid]
    if bad or not items or len(set(items)) != len(items):
        shown = value if not isinstance(value, ListConfig) else OmegaConf.to_container(value)
        raise MatlError(f"{key}={shown} is invalid: use {'one or a list' if allow_all else 'a list'} of {options}")
    return [str(v) for v in items]


def _ranges(cfg: DictConfig, keys: list[str]) -> None:
    for key in keys:
        value = OmegaConf.select(cfg, key)
        ok = isinstance(value, (list, ListConfig)) and len(value) == 2 and all(
            isinstance(v, (int, float)) and not isinstance(v, bool) for v in value) and value[0] <= value[1]
        if not ok:
            raise MatlError(f"{key}={value} is invalid: use [low, high] with low <= high")


def _check_occluded(cfg: DictConfig) -> None:
    """``occluded.*``: the occluders' kinds and range, the floors' weights, the RGBA share, the bins."""
    node = cfg.occluded
    kinds = OmegaConf.to_container(node.kinds) if isinstance(node.kinds, DictConfig) else node.kinds
    try:
        Occluders(kinds, tuple(node.hidden))
    except MatlError as error:
        raise MatlError(f"occluded: {error}") from None
    floors = OmegaConf.to_container(node.floors) if isinstance(node.floors, DictConfig) else node.floors
    if not isinstance(floors, dict) or not floors or not set(floors) <= {"dark", "texture"} or not all(
            isinstance(w, (int, float)) and not isinstance(w, bool) and w >= 0 for w in floors.values()) \
            or sum(floors.values()) <= 0:
        raise MatlError(f"occluded.floors={floors} is invalid: use weights >= 0 of dark and texture, not all 0, "
                        "e.g. {dark: 0.5, texture: 0.5}")
    share = node.rgba_share
    if not isinstance(share, (int, float)) or isinstance(share, bool) or not 0.0 <= share <= 1.0:
        raise MatlError(f"occluded.rgba_share={share} is invalid: use a fraction in [0, 1] of RGBA query files")
    bins = node.bins
    if not isinstance(bins, (list, ListConfig)) or not bins or not all(
            isinstance(b, (int, float)) and not isinstance(b, bool) and 0.0 < b < 1.0 for b in bins) \
            or any(a >= b for a, b in itertools.pairwise(bins)):
        shown = OmegaConf.to_container(bins) if isinstance(bins, ListConfig) else bins
        raise MatlError(f"occluded.bins={shown} is invalid: use increasing upper edges in (0, 1) of the "
                        "hidden-fraction bins, e.g. [0.2, 0.35, 0.5]")


def _check(cfg: DictConfig) -> tuple[list[str], list[str]]:
    """Validate a composed ``conf/unseen.yaml``; returns the conditions and the methods."""
    validate_config(cfg)
    runtime_option(cfg)  # runtime=torch|onnxruntime
    if cfg.get("ckpt") in (None, ""):
        raise MatlError("ckpt=... is required: python -m matl.unseen ckpt=<checkpoint> [condition=all] "
                        "[data=heldout] [out=<dir>]")
    condition = cfg.get("condition")
    items = list(condition) if isinstance(condition, (list, tuple, ListConfig)) else [condition]
    if "catalog" in items and items != ["catalog"]:
        raise MatlError("condition=catalog runs alone (its own products and galleries): python -m matl.unseen "
                        "condition=catalog ckpt=... 'catalog_sizes=[20,200,2000]'")
    conditions = ["catalog"] if items == ["catalog"] else _names(condition, CONDITIONS, "condition",
                                                                  allow_all=True)
    check_catalog(cfg)
    methods = _names(cfg.get("methods"), METHODS, "methods", allow_all=False)
    for key, low in (("queries", 1), ("query_seed", 0), ("file_size", 16), ("sizes.gallery", 16), ("sizes.query", 16),
                     ("timing.queries", 0), ("timing.warmup", 0), ("timing.threads", 1), ("view.seed", 0)):
        value = OmegaConf.select(cfg, key)
        if value is None and key == "file_size":
            continue
        if not isinstance(value, int) or isinstance(value, bool) or value < low:
            raise MatlError(f"{key}={value} is invalid: use an integer >= {low}")
    _ranges(cfg, [f"photometric.{k}" for k in cfg.photometric] + ["mask.offset_px", "mask.ragged_px",
                                                                   "clutter.distance", "backgrounds.crop"]
            + ["occluded.hidden"] + [f"occluded.dark_floor.{k}" for k in ("level", "noise", "vignetting")])
    _check_occluded(cfg)
    leave_out = cfg.get("leave_out", 0.0)
    if not isinstance(leave_out, (int, float)) or isinstance(leave_out, bool) or not 0.0 <= leave_out < 1.0:
        raise MatlError(f"leave_out={leave_out} is invalid: use a fraction in [0, 1) of the products kept out of "
                        "the gallery (open set)")
    for key in ("exclude_seen", "gallery_crop"):
        if not isinstance(cfg.get(key), bool):
            raise MatlError(f"{key}={cfg.get(key)} is invalid: use true or false")
    return conditions, methods


def primary_method(methods: list[str]) -> str:
    """The method whose metrics are ``unseen.json``'s top level: MATL's (plain first), else the first."""
    return next((m for m in ("matl", "matl_refine") if m in methods), methods[0])


def _products(cfg: DictConfig, train_data: dict[str, Any], file_size: int) -> tuple[Queries, dict[str, Any]]:
    """The held-out products (seen ones dropped) and the queries' planes and poses; plus what was checked."""
    from matl.data.prepare import instantiate_source

    source = instantiate_source(cfg)
    sampler = hydra.utils.instantiate(cfg.data.homography)
    cs = load_canonical(source, file_size, cfg.paths.cache_dir)
    objects = OmegaConf.select(cfg, "data.objects")
    source_objects = list(range(cs.num_objects)) if objects is None else [int(o) for o in objects]
    if objects is not None:
        cs = cs.subset_objects(source_objects)
    seen, related, how = seen_products(train_data, source, cs.object_names)
    if not cfg.exclude_seen:
        seen = {}
    keep = [i for i, name in enumerate(cs.object_names) if name not in seen]
    if not keep:
        raise MatlError(f"every product of {source!r} is in the checkpoint's training catalog: pick another "
                        "data= (e.g. heldout) or data.source.seed=")
    cs = cs.subset_objects(keep)
    log.info("unseen: %d products (%d planes), %d excluded as seen: %s", cs.num_objects, cs.num_planes, len(seen),
             sorted(seen))
    plane, query_H_canon = sample_poses(cs, sampler, int(cfg.queries), int(cfg.query_seed))
    queries = Queries(cs, plane, query_H_canon, int(cfg.query_seed), source, [source_objects[i] for i in keep], cfg)
    return queries, {"seen": seen, "related": related, "how": how}


def _settings(cfg: DictConfig, condition: str) -> dict[str, Any] | None:
    """The config values a condition was made with (for unseen.json)."""
    keys = {"photometric": ["photometric"], "mask": ["mask", "backgrounds"], "clutter": ["clutter", "backgrounds"],
            "occluded": ["occluded", "backgrounds"], "view": ["view"], "sizes": ["sizes"]}.get(condition)
    if keys is None:
        return None
    return {k: OmegaConf.to_container(cfg[k], resolve=True) for k in keys}


def _fills(cfg: DictConfig) -> tuple[float, float]:
    """predict's ``gallery_fill`` and ``query_fill`` of the written files (``gallery_fill`` null: by
    ``gallery_crop``)."""
    crop = bool(cfg.gallery_crop)
    gallery_fill = cfg.gallery_fill if cfg.gallery_fill is not None else (CROP_FILL if crop else 1.0)
    return float(gallery_fill), float(cfg.query_fill)


def run_condition(condition: str, q: Queries, cfg: DictConfig, methods: list[str], ckpt_path: Path, size: int,
                  num_anchors: int, checked: dict[str, Any], train_data: dict[str, Any], out: Path) -> dict[str, Any]:
    """Write one condition's gallery and queries into ``out``, predict and score them with every method;
    returns what ``<out>/unseen.json`` holds."""
    from matl.utils.io import write_json

    for sub in ("gallery", "queries"):
        if (out / sub).exists() and any((out / sub).iterdir()):
            raise MatlError(f"out={out} already holds {sub}/ from an earlier run: use a new out= folder")
    out.mkdir(parents=True, exist_ok=True)
    crop = bool(cfg.gallery_crop)
    gallery_fill, query_fill = _fills(cfg)
    gallery_cs = q.at_size(int(cfg.sizes.gallery)) if condition == "sizes" else q.cs
    gallery_files, canon_H_file = write_gallery(gallery_cs, out / "gallery", crop)
    truth = WRITERS[condition](q, out / "queries", gallery_files, canon_H_file, out)
    cs = q.cs
    left_out = left_out_products(cs.object_names, float(cfg.leave_out), int(cfg.query_seed))
    for name in left_out:  # their gallery files move out of the gallery: predict never sees them
        (out / "gallery" / name).rename(_left_out_dir(out, name))
    for t in truth:
        t["enrolled"] = t["object"] not in left_out
        if not t["enrolled"]:
            t["gallery_image"] = str(Path("left_out") / Path(t["gallery_image"]).relative_to("gallery"))
    enrolled = [t for t in truth if t["enrolled"]]
    truth_path = out / "truth.jsonl"
    truth_path.write_text("".join(json.dumps(t) + "\n" for t in enrolled))
    headline = headline_queries(enrolled)
    headline_path = truth_path  # the queries of the headline numbers (all, or the RGB ones of a mixed condition)
    if len(headline) < len(enrolled):
        headline_path = out / "truth_rgb.jsonl"
        headline_path.write_text("".join(json.dumps(enrolled[i]) + "\n" for i in headline))
    groups = breakdown_groups(enrolled, headline, [float(e) for e in cfg.occluded.bins])
    if left_out:
        (out / "truth_left_out.jsonl").write_text("".join(json.dumps(t) + "\n" for t in truth if not t["enrolled"]))

    threshold = cfg.get("threshold", "auto") if left_out else None  # leave_out=0: the closed-set benchmark
    shared = shared_options(cfg, ckpt_path, out, threshold, gallery_fill, query_fill)
    primary = primary_method(methods)
    runs = {m: MethodRun.of(m, cfg, shared, out / ("predictions.jsonl" if m == primary else f"predictions_{m}.jsonl"))
            for m in methods}
    per_method: dict[str, dict[str, Any]] = {}
    rows_of: dict[str, list[dict[str, Any]]] = {}
    scored_groups: dict[str, dict[str, dict[str, dict[str, Any]]]] = {}
    for method, run in runs.items():
        pred_path = run.options["out"]
        log.info("unseen: %s: predicting %d queries with %s", condition, len(truth), method)
        run.run()  # predict's library function, in this process
        summary, rows, scored_groups[method] = score_condition(pred_path, truth_path, headline, groups, size,
                                                               gallery_fill, query_fill)
        summary["truth"] = str(headline_path)
        for row, t in zip(rows, enrolled, strict=True):  # a mixed condition's own fields, per query
            row.update({k: t[k] for k in QUERY_FIELDS if k in t})
        per_method[method] = {**{k: summary[k] for k in METRICS}, "query_ms": None, "summary": summary,
                              "predictions": pred_path.name,
                              "per_query": "per_query.csv" if method == primary else f"per_query_{method}.csv",
                              "commands": {"predict": run.command,
                                           "score": score_command(pred_path, headline_path, ckpt_path, gallery_fill,
                                                                  query_fill, out / f"score_{method}")}}
        rows_of[method] = rows

    timing = None
    if int(cfg.timing.queries) > 0:
        rgba = {t["image"] for t in truth if t.get("rgba")} if len(headline) < len(enrolled) else set()
        files = [f for f in sorted((out / "queries").iterdir()) if str(f.relative_to(out)) not in rgba]  # headline's
        files = files[: int(cfg.timing.queries) + int(cfg.timing.warmup)]
        warmup = min(int(cfg.timing.warmup), max(len(files) - 1, 0))
        recognizers = {m: run.recognizer().enrol(out / "gallery") for m, run in runs.items()}
        for method, ms in time_methods(recognizers, files, warmup, int(cfg.timing.threads)).items():
            per_method[method]["query_ms"] = ms
        timing = {"queries": len(files) - warmup, "warmup": warmup, "threads": int(cfg.timing.threads),
                  "statistic": "median over single-query calls (batch of 1), gallery in memory, file decoded"}

    open_set = None
    if left_out and primary in MATL_METHODS:
        pred_path = out / per_method[primary]["predictions"]
        predictions = {str(Path(r["image"]).relative_to(out)) if Path(r["image"]).is_absolute() else r["image"]: r
                       for r in map(json.loads, pred_path.read_text().splitlines())}
        open_set = open_set_summary(truth, predictions)
        write_json(out / "open_set.json", {**open_set, "left_out": left_out})
        plot_open_set(open_set, out / "open_set.png")
        open_set = {k: v for k, v in open_set.items() if k != "curve"}
        log.info("unseen: open set %s", json.dumps(open_set))

    summary, rows = per_method[primary]["summary"], [rows_of[primary][i] for i in headline]
    related = checked["related"]
    unrelated = [r for r in rows if r["true_object"] not in related]
    result = {
        **{k: summary[k] for k in METRICS},
        "rec_acc_unrelated": sum(r["correct"] for r in unrelated) / len(unrelated) if unrelated else None,
        "num_queries_unrelated": len(unrelated),
        "num_queries": summary["num_queries"], "missing_predictions": summary["missing_predictions"],
        "num_queries_all": len(enrolled), "headline": "all" if len(headline) == len(enrolled) else "rgb",
        "num_objects": cs.num_objects, "num_planes": cs.num_planes,
        "condition": condition, "condition_settings": _settings(cfg, condition), "method": primary,
        "foreground": foreground_choice(cfg),
        "methods": {m: {k: v for k, v in r.items() if k != "summary"} for m, r in per_method.items()},
        "timing": timing,
        "checkpoint": str(ckpt_path), "image_size": size, "N": num_anchors,
        "data": OmegaConf.to_container(cfg.data.source, resolve=True), "products": list(cs.object_names),
        "excluded_seen": checked["seen"], "related": related, "seen_check": checked["how"],
        "train_data": train_data.get("source"),
        "query_seed": int(cfg.query_seed), "file_size": cs.image_size, "gallery_crop": crop,
        "gallery_fill": gallery_fill, "query_fill": query_fill, "refine": primary == "matl_refine",
        "homography": OmegaConf.to_container(cfg.data.homography, resolve=True),
        "pose_threshold_px": summary["pose_threshold_px"],
        "per_object": summary["per_object"], "confusions": summary["confusions"],
        "commands": {"unseen": own_command(), **per_method[primary]["commands"]},
        "files": {"gallery": "gallery", "queries": "queries", "truth": truth_path.name,
                  "predictions": per_method[primary]["predictions"], "per_query": "per_query.csv",
                  **({"truth_headline": headline_path.name} if headline_path != truth_path else {}),
                  **({"masks": "masks"} if (out / "masks").is_dir() else {})},
    }
    if groups:
        result["breakdown"] = breakdown_result(groups, scored_groups, [float(e) for e in cfg.occluded.bins],
                                               result["headline"])
    if open_set is not None:
        result["open_set"] = {**open_set, "left_out": left_out, "curve": "open_set.json", "figure": "open_set.png"}
    write_json(out / "unseen.json", result)
    for method, method_rows in rows_of.items():
        write_rows(out / per_method[method]["per_query"], method_rows)
    log.info("unseen: %s: %s", condition, json.dumps({m: {k: r[k] for k in TABLE_METRICS}
                                                      for m, r in per_method.items()}))
    return result


def unseen(cfg: DictConfig) -> dict[str, Any]:
    """Run the benchmark for a composed ``conf/unseen.yaml``.

    Each condition writes ``<out>/<condition>/`` (gallery, queries, truth, predictions per method,
    ``unseen.json``, ``per_query.csv``), or ``<out>/`` itself when ``condition`` names one condition;
    ``<out>/benchmark.json`` and ``benchmark.md`` hold the table.

    Returns:
        The last condition's ``unseen.json`` content, with ``benchmark`` (``benchmark.json``'s content).
    """
    from matl.utils.io import write_json

    conditions, methods = _check(cfg)
    from matl.models.checkpoint import resolve_checkpoint_keyword

    ckpt_path = Path(resolve_checkpoint_keyword(str(cfg.ckpt))).expanduser().resolve()  # pretrained[_fast]: shipped
    ckpt = load_checkpoint(ckpt_path)
    size, num_anchors = checkpoint_info(ckpt, ckpt_path)
    train_data = (ckpt.get("matl_config") or {}).get("data") or {}
    del ckpt
    out = Path(cfg.out).expanduser().resolve()
    if conditions == ["catalog"]:
        for method in cfg.catalog.methods:  # predict's options, the model, a matcher: before any file is written
            MethodRun.of(str(method), cfg, shared_options(cfg, ckpt_path, out, cfg.get("threshold", "auto"), 1.0,
                                                          float(cfg.query_fill)), out / "predictions.jsonl").check()
        return run_catalog(cfg, ckpt_path, size, out)
    # one condition by name: its files straight into out/; all or a list: out/<condition>/ each
    flat = isinstance(cfg.condition, str) and cfg.condition != "all"
    folders = {c: out if flat else out / c for c in conditions}
    for folder in folders.values():
        for sub in ("gallery", "queries"):
            if (folder / sub).exists() and any((folder / sub).iterdir()):
                raise MatlError(f"out={out} already holds {folder.relative_to(out) / sub}/ from an earlier run: use a "
                                "new out= folder")
    threshold = cfg.get("threshold", "auto") if float(cfg.leave_out) > 0 else None
    shared = shared_options(cfg, ckpt_path, out, threshold, *_fills(cfg))
    for method in methods:  # predict's options, the model, a baseline's matcher: checked before any file is written
        MethodRun.of(method, cfg, shared, out / "predictions.jsonl").check()
    if "view" in conditions:
        from matl.data.prepare import instantiate_source

        require_models(instantiate_source(cfg), "condition=view")
    q, checked = _products(cfg, train_data, int(cfg.file_size or size))
    results = {}
    for condition in conditions:
        results[condition] = run_condition(condition, q, cfg, methods, ckpt_path, size, num_anchors, checked,
                                           train_data, folders[condition])
    data, text = benchmark_table(results, methods, own_command())
    data["files"] = {c: str((folders[c] / "unseen.json").relative_to(out)) for c in conditions}
    data["speed_accuracy"] = write_speed_accuracy(data, folders, out)
    write_json(out / "benchmark.json", data)
    (out / "benchmark.md").write_text(text)
    log.info("unseen: benchmark -> %s\n%s", out / "benchmark.md", text)
    return {**results[conditions[-1]], "benchmark": data}
