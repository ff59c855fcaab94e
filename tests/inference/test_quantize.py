"""The optional int8 query path (``quantize=int8``, matl/inference/quantize.py, docs/speed.md).

Tolerances, on a tiny untrained model at 32 px: the int8 embeddings (unit vectors) are within 0.1 of the
float ones (cosine similarity >= 0.99), its homographies within 0.5 px, its query-to-gallery distances
within 0.05; with an identity STN every gallery anchor retrieves itself by the int8 path, and with a random
STN the nearest anchor of at least 75% of warped toy queries is the float path's (an untrained c() leaves
margins of ~0.005 between anchors: the rest are near-ties).
"""

from __future__ import annotations

import copy
import json
from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf

from matl.evaluation.speed import run_bench
from matl.geometry import HomographySampler, warp_image
from matl.inference.quantize import (
    QuantizedQueryPath,
    apply_quantize_option,
    calibration_images,
    quantize_available,
    quantize_option,
    quantize_recognizer,
)
from matl.models.recognizer import QueryGraph, TensorRecognizer
from matl.utils.errors import MatlError
from tests.conftest import compose_config
from tests.models.test_recognizer import S, gallery, networks
from tests.test_bench import QUICK

pytestmark = pytest.mark.skipif(not quantize_available(), reason="no oneDNN quantised engine in this torch")

EMBEDDING_ATOL = 0.1
COSINE_MIN = 0.99
H_PIXEL_ATOL = 0.5
DISTANCE_ATOL = 0.05


def toy_queries(images: torch.Tensor, count: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """``count`` gallery images warped by mild random homographies, and the index of each source image."""
    g = torch.Generator().manual_seed(seed)
    source = torch.randint(len(images), (count,), generator=g)
    H = HomographySampler(translation=(-0.05, 0.05), rotation_deg=(-10.0, 10.0), scale=(0.95, 1.05),
                          tilt=(-0.05, 0.05)).sample(count, (S, S), g)
    return warp_image(images[source], H.float()), source


@pytest.mark.parametrize("input_norm", ["none", "channel"])
def test_int8_path_agrees_with_float(input_norm: str) -> None:
    feature_net, stn = networks(input_norm=input_norm)
    g = gallery(feature_net)
    calibration = calibration_images(g.images, 128, seed=1)
    path = QuantizedQueryPath(feature_net, stn, S, calibration)
    queries, _ = toy_queries(g.images, 12, seed=2)
    with torch.no_grad():
        float_emb, float_H, float_bad, float_warped = QueryGraph(stn, feature_net, S).eval()(queries)
        emb, H, bad, warped = path(queries)
    assert emb.shape == float_emb.shape and emb.dtype == torch.float32
    assert (emb - float_emb).abs().max() < EMBEDDING_ATOL
    assert torch.nn.functional.cosine_similarity(emb, float_emb).min() >= COSINE_MIN
    assert (H - float_H).abs().max() < H_PIXEL_ATOL
    assert torch.equal(bad, float_bad) and warped.shape == float_warped.shape
    # batch of one (the traced size) and another size give the same rows
    with torch.no_grad():
        assert torch.allclose(path(queries[:1])[0], emb[:1], atol=1e-5)


def test_recognizer_int8_same_nearest_anchor_and_fallbacks() -> None:
    feature_net, stn = networks()
    g = gallery(feature_net)
    calibration = calibration_images(g.images, 128, seed=1)
    # an identity STN and the gallery's own anchors as queries: every query's nearest anchor is itself,
    # by both paths (the gallery is re-embedded by the int8 c(), so queries and gallery share its rounding)
    identity_stn = copy.deepcopy(stn)
    with torch.no_grad():
        identity_stn.regressor.fc2.weight.zero_()
        identity_stn.regressor.fc2.bias.zero_()
    rec = TensorRecognizer(feature_net, identity_stn, g)
    assert quantize_recognizer(rec, calibration) is None and rec.quantized is not None
    for batch in (g.images, g.images[5:6]):
        expected = torch.arange(len(g))[5:6] if len(batch) == 1 else torch.arange(len(g))
        assert torch.equal(rec(batch).gallery_index, expected)

    # a random STN and warped queries: an untrained c() leaves margins of ~0.005 between anchors, so the
    # nearest anchor agrees for most queries, and every distance is within DISTANCE_ATOL of the float one
    float_rec = TensorRecognizer(feature_net, stn, g)
    rec = TensorRecognizer(feature_net, stn, g)
    assert quantize_recognizer(rec, calibration) is None
    assert not torch.equal(rec.gallery_features, float_rec.gallery_features)  # re-embedded by the int8 c()
    queries, _ = toy_queries(g.images, 40, seed=3)
    expected = float_rec(queries)
    got = rec(queries)
    assert (got.gallery_index == expected.gallery_index).float().mean() >= 0.75
    distance = torch.cdist(rec.embed_queries(queries)[0], rec.gallery_features)
    float_distance = torch.cdist(float_rec.embed_queries(queries)[0], float_rec.gallery_features)
    assert (distance - float_distance).abs().max() < DISTANCE_ATOL
    # the pose: s()'s for every query, and the canonical pose where both paths chose the same anchor (another
    # anchor, of another plane where the margins are this small, has another canonical frame)
    assert torch.allclose(got.query_H_anchor, expected.query_H_anchor, atol=H_PIXEL_ATOL)
    same = got.gallery_index == expected.gallery_index
    assert torch.allclose(got.query_H_canon[same], expected.query_H_canon[same], atol=H_PIXEL_ATOL)
    assert torch.equal(rec(queries[:1]).gallery_index, got.gallery_index[:1])  # batch of one: the same answer
    # the quantised copy is stale once the float weights change: the float path answers again
    with torch.no_grad():
        stn.regressor.fc2.bias.add_(0.01)
    assert not rec.quantized.matches()
    assert torch.allclose(rec.embed_queries(queries)[0], float_rec.embed_queries(queries)[0], atol=1e-5)

    # gallery="float" keeps the float gallery embeddings
    kept = TensorRecognizer(feature_net, stn, g)
    before = kept.gallery_features.clone()
    assert quantize_recognizer(kept, calibration_images(g.images, 64), gallery="float") is None
    assert torch.equal(kept.gallery_features, before)

    # no STN: not quantisable, the recognizer stays float and the reason is returned
    no_stn = TensorRecognizer(feature_net, None, g)
    reason = quantize_recognizer(no_stn, calibration_images(g.images, 16))
    assert reason is not None and "spatial transformer" in reason and no_stn.quantized is None


def test_quantize_option_values() -> None:
    assert quantize_option(OmegaConf.create({})) == "none"
    assert quantize_option(OmegaConf.create({"quantize": "int8"})) == "int8"
    with pytest.raises(MatlError, match="quantize=fp4 is invalid"):
        quantize_option(OmegaConf.create({"quantize": "fp4"}))
    feature_net, stn = networks()
    g = gallery(feature_net)
    rec = TensorRecognizer(feature_net, stn, g)
    assert apply_quantize_option(rec, OmegaConf.create({"quantize": "none"}), lambda: 1 / 0) == {
        "quantize": "none", "quantize_fallback": None}
    assert rec.quantized is None
    applied = apply_quantize_option(rec, OmegaConf.create({"quantize": "int8"}),
                                    lambda: calibration_images(g.images, 32))
    assert applied == {"quantize": "int8", "quantize_fallback": None} and rec.quantized is not None
    with pytest.raises(MatlError, match="applies to MATL's recognizer"):
        apply_quantize_option(object(), OmegaConf.create({"quantize": "int8"}), lambda: None)


@pytest.mark.parametrize("name", ["eval", "predict", "bench"])
def test_configs_default_to_float(name: str, tmp_path: Path) -> None:
    assert compose_config(name, [], tmp_path).quantize == "none"
    assert compose_config(name, ["quantize=int8"], tmp_path).quantize == "int8"


def test_quick_bench_int8_entry(tmp_path: Path, cache_dir: Path) -> None:
    overrides = [*QUICK, f"paths.cache_dir={cache_dir}", "quantize=int8", "bench.refine=false", "bench.faiss=false",
                 "bench.render=false", "bench.query_threads=1"]
    run_bench(compose_config("bench", overrides, tmp_path))
    saved = json.loads((tmp_path / "bench.json").read_text())
    q, timing = saved["query_ms"], saved["query_timing"]
    assert q["matl"] > 0 and q["matl_int8"] > 0 and q["sift_ransac"] > 0  # the float number is kept beside it
    assert saved["speedup_int8_vs_sift"] == pytest.approx(q["sift_ransac"] / q["matl_int8"])
    assert saved["speedup_vs_sift"] == pytest.approx(q["sift_ransac"] / q["matl"])
    assert timing["matl_int8_ms_by_threads"] == {"1": q["matl_int8"]} and timing["matl_int8_path"].startswith("int8")
    assert saved["config"]["quantize"] == "int8"
    with pytest.raises(MatlError, match="quantize=fp16 is invalid"):
        run_bench(compose_config("bench", ["quantize=fp16"], tmp_path))
