"""runtime=onnxruntime (matl/inference/runtime.py): the query networks in onnxruntime, s()'s warps in OpenCV,
the same answers as the torch path up to float rounding and OpenCV's 1/32 px sample positions."""

from __future__ import annotations

import pytest
import torch
from omegaconf import OmegaConf

from matl.geometry import warp_image
from matl.inference import runtime as runtime_module
from matl.inference.runtime import OnnxRuntimeQueryPath, apply_runtime, apply_runtime_option, runtime_option
from matl.models.recognizer import TensorRecognizer
from matl.models.search import ExactSearch, nearest
from matl.utils.errors import MatlError
from tests.models.test_recognizer import gallery, networks, random_homographies
from tests.speed_helpers import textured_planes

pytest.importorskip("onnxruntime")
S = 32


def queries_of(gal, seed: int = 9) -> torch.Tensor:
    return warp_image(gal.images[[1, 6, 11, 17, 2]], random_homographies(5, seed, 0.03))


@pytest.mark.parametrize("input_norm", ["none", "channel"])
def test_onnxruntime_path_agrees_with_torch(input_norm: str) -> None:
    feature_net, stn = networks(1, input_norm=input_norm)
    gal = gallery(feature_net)
    queries = queries_of(gal)
    reference = TensorRecognizer(feature_net, stn, gal)
    onnx = TensorRecognizer(feature_net, stn, gal)
    assert apply_runtime(onnx, "onnxruntime") is None and isinstance(onnx.onnx, OnnxRuntimeQueryPath)
    for batch in (queries, *queries.split(1)):  # a batch, and one query at a time
        ref, out = reference(batch), onnx(batch)
        assert torch.equal(out.gallery_index, ref.gallery_index)
        assert torch.equal(out.degenerate, ref.degenerate)
        assert torch.allclose(out.distance, ref.distance, atol=1e-3)
        assert torch.allclose(out.features, ref.features, atol=1e-3)
        assert torch.allclose(out.query_H_canon, ref.query_H_canon, atol=1e-3)  # pixels
        assert torch.allclose(out.warped, ref.warped, atol=0.05)  # bilinear at 1/32 px positions
        assert out.warped.shape == ref.warped.shape and out.query_H_anchor.dtype == torch.float32
    assert not torch.allclose(ref.query_H_anchor, torch.eye(3).expand_as(ref.query_H_anchor), atol=1e-3)


def test_onnxruntime_path_keeps_the_degeneracy_guard() -> None:
    feature_net, stn = networks(2)
    with torch.no_grad():
        stn.regressor.fc2.bias.copy_(torch.tensor([-1.0, 0, 0, 0, -1.0, 0, 0, 0]))  # the zero matrix: degenerate
    gal = gallery(feature_net)
    rec = TensorRecognizer(feature_net, stn, gal)
    apply_runtime(rec, "onnxruntime")
    out = rec(queries_of(gal))
    ref = TensorRecognizer(feature_net, stn, gal)(queries_of(gal))
    assert out.degenerate.all() and ref.degenerate.all()
    assert torch.allclose(out.query_H_anchor, torch.eye(3).expand(5, 3, 3))


def test_onnxruntime_path_follows_weight_changes_and_thread_counts() -> None:
    feature_net, stn = networks(3)
    gal = gallery(feature_net)
    rec = TensorRecognizer(feature_net, stn, gal)
    apply_runtime(rec, "onnxruntime")
    query = textured_planes(1, S, 3)
    before = rec(query).query_H_anchor
    with torch.no_grad():
        stn.regressor.fc2.bias.add_(0.05)  # in place, as an optimiser step
    after = rec(query).query_H_anchor
    rec.onnx, path = None, rec.onnx
    torch_after = rec(query).query_H_anchor
    rec.onnx = path
    assert not torch.allclose(before, after, atol=1e-3) and torch.allclose(after, torch_after, atol=1e-3)
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        one = rec(query).query_H_anchor
    finally:
        torch.set_num_threads(threads)
    assert torch.allclose(one, after, atol=1e-4) and 1 in path._sessions


def test_without_onnxruntime_torch_answers(monkeypatch: pytest.MonkeyPatch) -> None:
    import matl.inference.export as export

    def missing() -> None:
        raise MatlError("format=onnx needs onnx and onnxruntime (onnxruntime is not installed): pip install ...")

    monkeypatch.setattr(export, "require_onnxruntime", missing)
    feature_net, stn = networks(4)
    gal = gallery(feature_net)
    rec = TensorRecognizer(feature_net, stn, gal)
    record = apply_runtime_option(rec, OmegaConf.create({"runtime": "onnxruntime"}))
    assert record["runtime"] == "torch" and "onnxruntime is not installed" in record["runtime_fallback"]
    assert rec.onnx is None and rec(queries_of(gal)).gallery_index.shape == (5,)


def test_runtime_option_and_unsupported_recognizers() -> None:
    assert runtime_option(OmegaConf.create({})) == "torch"
    assert runtime_option(OmegaConf.create({"runtime": "onnxruntime"})) == "onnxruntime"
    with pytest.raises(MatlError, match="runtime=tensorrt is invalid: use torch or onnxruntime"):
        runtime_option(OmegaConf.create({"runtime": "tensorrt"}))
    feature_net, stn = networks(5)
    gal = gallery(feature_net)
    no_stn = TensorRecognizer(feature_net, None, gal)
    assert "not an STN" in apply_runtime(no_stn, "onnxruntime") and no_stn.onnx is None
    assert "applies to MATL's recognizer" in apply_runtime(object(), "onnxruntime")
    stn.regressor.train()  # no batch norm here: training mode changes nothing, and the path still applies
    assert runtime_module.unsupported(feature_net, stn) is None


def test_numpy_search_equals_torch_search() -> None:
    g = torch.Generator().manual_seed(4)
    features = torch.randn(50, 16, generator=g)
    features[7] = features[3]  # a tie: the lower index wins on both paths
    queries = torch.randn(6, 16, generator=g)
    queries[1] = features[3]
    queries[2] = float("nan")
    search = ExactSearch(features)
    for q in (queries, *queries.split(1)):
        index, distance = search.search(q)
        ref_index, ref_distance = nearest(q, features)
        assert torch.equal(index, ref_index) and index.dtype == torch.int64
        # the same |q|^2 + |g|^2 - 2 q.g summed in another order: an exact match is 0 within sqrt(float32 rounding)
        assert torch.allclose(distance, ref_distance, atol=5e-3, equal_nan=True)
    assert int(search.search(queries)[0][1]) == 3 and int(search.search(queries)[0][2]) == 0
    assert search.search(queries[2:3])[1].item() == float("inf")
    # a gallery entry with a NaN leaves every query without an answer, one query at a time or in a batch
    features[9] = float("nan")
    broken = ExactSearch(features)
    for q in (queries[:3], *queries[:3].split(1)):
        index, distance = broken.search(q)
        assert index.tolist() == [0] * len(q) and distance.isinf().all()


def test_single_query_search_beyond_one_chunk_equals_the_chunked_search() -> None:
    g = torch.Generator().manual_seed(5)
    features = torch.randn(50, 16, generator=g)
    features[41] = features[3]  # a tie across chunks: the lower index wins
    queries = torch.randn(4, 16, generator=g)
    queries[0] = features[3]
    search = ExactSearch(features, chunk=16)  # 4 chunks: one query compiled, a batch through torch's chunks
    for q in (queries, *queries.split(1)):
        index, distance = search.search(q)
        ref_index, ref_distance = nearest(q, features, chunk=16)
        assert torch.equal(index, ref_index) and index.dtype == torch.int64
        assert torch.allclose(distance, ref_distance, atol=5e-3)
    assert int(search.search(queries[:1])[0]) == 3
