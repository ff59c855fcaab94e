"""matl.bench: the quick variant writes bench.json with every key and sane values."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
import torch

from matl.evaluation.speed import REQUIRED_KEYS, run_bench
from matl.utils.errors import MatlError
from tests.conftest import compose_config

QUICK = ["bench.quick=true", "ckpt=null", "data.image_size=32", "data.train_triplets=64", "data.val_queries=8",
         "data.test_queries=16", "data.batch_size=16"]


def test_quick_bench_writes_every_key(tmp_path: Path, cache_dir: Path) -> None:
    cfg = compose_config("bench", [*QUICK, f"paths.cache_dir={cache_dir}"], tmp_path)
    results = run_bench(cfg)
    saved = json.loads((tmp_path / "bench.json").read_text())
    assert set(REQUIRED_KEYS) <= set(saved)
    assert saved["quick"] is True

    assert saved["train_triplets_per_s"] > 0 and 0 < saved["data_time_fraction"] < 1
    assert saved["train"]["batch_size"] == 16 and saved["train"]["steps"] == 2

    q, timing = saved["query_ms"], saved["query_timing"]
    assert q["matl"] > 0 and q["sift_ransac"] > 0 and q["matl_refine"] > 0
    assert timing["gallery_anchors"] == 152 * 4 and timing["gallery_planes"] == 152  # ARC-size gallery
    assert timing["queries"] == 3 and timing["weights"].startswith("untrained")
    assert math.isclose(saved["speedup_vs_sift"], q["sift_ransac"] / q["matl"], rel_tol=1e-9)
    assert math.isclose(saved["refine_added_ms"], q["matl_refine"] - q["matl"], rel_tol=1e-9)
    # each method timed at every thread count up to the run's, reported at its fastest; MATL by its compiled graph
    by, sift_by = timing["matl_ms_by_threads"], timing["sift_ms_by_threads"]
    assert set(by) == set(sift_by) == {str(n) for n in range(1, torch.get_num_threads() + 1)}
    assert q["matl"] == by[str(timing["matl_threads"])] == min(by.values())
    assert q["sift_ransac"] == sift_by[str(timing["sift_threads"])] == min(sift_by.values())
    assert timing["matl_path"].startswith("compiled")
    # where a refined query's time goes (refiner=fast, the default): each part > 0, the refinement per level
    parts = timing["breakdown"]
    assert parts["refiner"] == "FastRefiner" and parts["threads"] == timing["matl_threads"]
    for key in ("networks_ms", "stn_ms", "features_ms", "search_ms", "refine_ms"):
        assert parts[key] > 0, key
    assert "align_ms" not in parts and parts["refine_skips_align"] is False  # the default config has no stage
    assert len(parts["refine_level_ms"]) == 3 and all(ms > 0 for ms in parts["refine_level_ms"])  # 32, 16, 8 px
    assert float(timing["notes"]["refine_templates_mb"]) > 0

    scaling = saved["gallery_scaling"]
    assert [row["anchors"] for row in scaling] == [600, 2000]
    fixed = saved["gallery_scaling_info"]["fixed_query_ms"]
    for row in scaling:
        assert row["search_ms"] > 0 and math.isclose(row["query_ms"], fixed + row["search_ms"], rel_tol=1e-9)
        if "faiss_recall_at_1" in row:  # faiss installed
            assert 0 <= row["faiss_recall_at_1"] <= 1 and row["faiss_query_ms"] > 0
    assert "random unit embeddings" in saved["gallery_scaling_info"]["method"]

    # rendering needs OpenGL: a number, or null with the reason
    assert (saved["render_images_per_s"] or 0) > 0 or saved["render"].get("skipped")
    assert results["query_ms"] == q


def test_bench_rejects_bad_sizes(tmp_path: Path) -> None:
    cfg = compose_config("bench", ["bench.queries=0"], tmp_path)
    with pytest.raises(MatlError, match=r"bench\.queries=0 is invalid"):
        run_bench(cfg)
    cfg = compose_config("bench", ["bench.query_threads=0"], tmp_path)
    with pytest.raises(MatlError, match=r"bench\.query_threads=0 is invalid"):
        run_bench(cfg)
