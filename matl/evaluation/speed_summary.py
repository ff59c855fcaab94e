"""The summary ``matl.bench`` prints: the headline numbers of ``bench.json`` and the gallery scaling, two tables."""

from __future__ import annotations

from typing import Any

from rich.console import Console
from rich.table import Table

from matl.evaluation.camera_speed import summary_rows


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
    for row in summary_rows(results):  # query_ms_camera: camera crops, the foreground step included
        table.add_row(*row)
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

