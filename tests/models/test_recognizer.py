"""The fast query path (docs/speed.md): same outputs as the training code path, up to float rounding."""

from __future__ import annotations

from pathlib import Path

import hydra
import torch
from torch import nn

from matl.data.gallery import Gallery
from matl.geometry import anchor_H_canon, sample_by_normalised, sample_by_normalised_kornia, warp_image
from matl.models.feature import FeatureNet
from matl.models.recognizer import CompiledQueryPath, QueryGraph, TensorRecognizer
from matl.models.search import distances, nearest
from matl.models.stn import HomographyRegressor, SpatialTransformer
from tests.conftest import compose_config
from tests.speed_helpers import textured_planes

S = 32


def networks(seed: int = 0, batch_norm: bool = False,
             input_norm: str = "none") -> tuple[FeatureNet, SpatialTransformer]:
    torch.manual_seed(seed)
    stn = SpatialTransformer(HomographyRegressor(image_size=S, batch_norm=batch_norm, input_norm=input_norm),
                             image_size=S, iterations=2)
    nn.init.normal_(stn.regressor.fc2.weight, std=0.02)  # a real homography, not the identity it starts at
    nn.init.normal_(stn.regressor.fc2.bias, std=0.05)
    return FeatureNet(input_norm=input_norm).eval(), stn.eval()


def gallery(feature_net: FeatureNet, planes: int = 5, N: int = 4) -> Gallery:
    canon = textured_planes(planes, S, 7)
    rot = anchor_H_canon(N, (S, S))
    anchors = torch.stack([warp_image(canon, rot[k].expand(planes, 3, 3)) for k in range(N)], 1)
    return Gallery(anchors.reshape(planes * N, 3, S, S), torch.arange(planes).repeat_interleave(N),
                   torch.arange(planes).repeat_interleave(N), torch.arange(N).repeat(planes), rot.repeat(planes, 1, 1),
                   [f"o{i}" for i in range(planes)], [f"p{i}" for i in range(planes)])


def random_homographies(batch: int, seed: int, spread: float = 0.15) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.eye(3) + spread * torch.randn(batch, 3, 3, generator=g)


def test_lean_warp_equals_kornia_warp() -> None:
    images = textured_planes(4, S, 1)
    H = random_homographies(4, 2)
    H[1] *= 0.5  # a matrix scaled away from 1: the same warp (kornia rescales it first)
    assert torch.allclose(sample_by_normalised(images, H), sample_by_normalised_kornia(images, H), atol=1e-5)


def test_lean_warp_is_differentiable() -> None:
    H = random_homographies(2, 3).requires_grad_()
    sample_by_normalised(textured_planes(2, S, 4), H).sum().backward()
    assert H.grad is not None and torch.isfinite(H.grad).all() and H.grad.abs().sum() > 0


def test_graph_takes_its_own_regressor_and_feature() -> None:
    """The int8 path's way in: another regressor and feature module, the same loop, guard and conversion."""
    feature_net, stn = networks(4)
    images = textured_planes(2, S, 6)
    doubled = nn.Sequential(stn.regressor)  # the same function, another module
    with torch.no_grad():
        ref = QueryGraph(stn, feature_net).eval()(images)
        out = QueryGraph(stn, FeatureNet(), regressor=doubled, feature=feature_net).eval()(images)
    assert all(torch.equal(a, b) for a, b in zip(ref, out, strict=True))


def test_infer_methods_equal_forward() -> None:
    feature_net, stn = networks()
    images = textured_planes(3, S, 5)
    with torch.no_grad():
        ref, fast = stn(images), stn.infer(images)
        assert torch.allclose(stn.regressor.infer(images), stn.regressor(images), atol=1e-5)
        assert torch.allclose(fast.warped, ref.warped, atol=1e-4)
        assert torch.allclose(fast.query_H_anchor, ref.query_H_anchor, rtol=1e-5, atol=1e-4)
        assert torch.equal(fast.degenerate, ref.degenerate)
        for batch in (1, 3):  # torch picks another convolution for one small image: oneDNN here
            assert torch.allclose(feature_net.infer(images[:batch]), feature_net(images[:batch]), atol=1e-5)
            assert torch.allclose(feature_net.forward_graph(images[:batch]), feature_net(images[:batch]), atol=1e-6)
    assert not torch.allclose(ref.query_H_anchor, torch.eye(3).expand_as(ref.query_H_anchor), atol=1e-2)


def test_infer_keeps_the_degeneracy_guard() -> None:
    class Constant(nn.Module):
        def __init__(self, H: torch.Tensor) -> None:
            super().__init__()
            self.register_buffer("H", H)

        def forward(self, images: torch.Tensor) -> torch.Tensor:
            return self.H[: len(images)]

    bad = torch.stack([torch.full((3, 3), float("nan")), torch.zeros(3, 3), torch.eye(3) * 1.1])
    stn = SpatialTransformer(Constant(bad), image_size=S).eval()  # type: ignore[arg-type]
    images = textured_planes(3, S, 2)
    with torch.no_grad():
        ref, fast = stn(images), stn.infer(images)
        graph = QueryGraph(stn, FeatureNet()).eval()(images)
    assert fast.degenerate.tolist() == ref.degenerate.tolist() == graph[2].tolist() == [True, True, False]
    assert torch.allclose(fast.query_H_anchor, ref.query_H_anchor, atol=1e-5)
    assert torch.allclose(graph[1], ref.query_H_anchor, atol=1e-5)


def test_recognizer_paths_agree() -> None:
    """One query at a time (compiled graph), a batch (eager infer) and the training code path."""
    feature_net, stn = networks(1)
    gal = gallery(feature_net)
    queries = warp_image(gal.images[[1, 6, 11, 17]], random_homographies(4, 9, 0.02) @ torch.eye(3))
    reference = TensorRecognizer(feature_net, stn, gal, fast=False)
    batched = TensorRecognizer(feature_net, stn, gal)
    single = TensorRecognizer(feature_net, stn, gal)
    ref, fast = reference(queries), batched(queries)  # 4 <= compiled_max_batch: compiled
    eager = TensorRecognizer(feature_net, stn, gal, compiled_max_batch=0)(queries)
    one = [single(queries[i:i + 1]) for i in range(len(queries))]
    assert single._compiled is not None and single._compiled.failure is None and single._compiled._graph is not None
    for pred in (fast, eager):
        assert torch.equal(pred.gallery_index, ref.gallery_index)
        assert torch.allclose(pred.distance, ref.distance, atol=1e-5)
        assert torch.allclose(pred.query_H_canon, ref.query_H_canon, rtol=1e-5, atol=1e-4)
        assert torch.allclose(pred.warped, ref.warped, atol=1e-4)
        assert torch.equal(pred.degenerate, ref.degenerate)
    assert torch.equal(torch.cat([p.gallery_index for p in one]), ref.gallery_index)
    assert torch.allclose(torch.cat([p.query_H_canon for p in one]), ref.query_H_canon, rtol=1e-5, atol=1e-4)
    assert torch.allclose(torch.cat([p.distance for p in one]), ref.distance, atol=1e-5)


def test_compiled_path_follows_weight_changes_and_modes() -> None:
    feature_net, stn = networks(2)
    gal = gallery(feature_net)
    rec = TensorRecognizer(feature_net, stn, gal)
    query = textured_planes(1, S, 3)
    before = rec(query).query_H_anchor
    with torch.no_grad():
        stn.regressor.fc2.bias.add_(0.05)  # in place, as an optimiser step
    after = rec(query).query_H_anchor
    ref = TensorRecognizer(feature_net, stn, gal, fast=False)(query).query_H_anchor
    assert not torch.allclose(before, after, atol=1e-3) and torch.allclose(after, ref, rtol=1e-5, atol=1e-4)
    # building the graph leaves the networks' modes alone
    stn.train()
    rec(query)
    assert stn.training and stn.regressor.training and not feature_net.training
    # batch norm in training mode (batch statistics): never compiled
    feature_bn, stn_bn = networks(3, batch_norm=True)
    stn_bn.train()
    assert not CompiledQueryPath.supports(feature_bn, stn_bn)
    assert CompiledQueryPath.supports(feature_bn, stn_bn.eval())


def test_single_chunk_search_equals_chunked() -> None:
    g = torch.Generator().manual_seed(4)
    gal, q = torch.randn(50, 16, generator=g), torch.randn(6, 16, generator=g)
    q[2] = float("nan")
    one, chunked = nearest(q, gal), nearest(q, gal, chunk=7)
    assert torch.equal(one[0], chunked[0]) and torch.allclose(one[1], chunked[1])
    assert int(one[0][2]) == 0 and one[1][2] == float("inf")


def test_matl_fast_networks_take_the_same_fast_paths(tmp_path: Path) -> None:
    """``model=matl_fast`` (coarser strides): compiled single queries and eager batches equal its training path."""
    cfg = compose_config("train", ["model=matl_fast", f"data.image_size={S}"], tmp_path)
    torch.manual_seed(3)
    feature_net, stn = hydra.utils.instantiate(cfg.model.feature_net), hydra.utils.instantiate(cfg.model.stn)
    assert stn.regressor.features[0].stride == (4, 4) and feature_net.pool.kernel_size == 4
    nn.init.normal_(stn.regressor.fc2.weight, std=0.02)
    feature_net, stn = feature_net.eval(), stn.eval()
    gal = gallery(feature_net)
    queries = warp_image(gal.images[[0, 5, 10]], random_homographies(3, 4, 0.02))
    ref = TensorRecognizer(feature_net, stn, gal, fast=False)(queries)
    single = TensorRecognizer(feature_net, stn, gal)
    one = [single(queries[i:i + 1]) for i in range(len(queries))]
    assert single._compiled is not None and single._compiled.failure is None
    assert torch.equal(torch.cat([p.gallery_index for p in one]), ref.gallery_index)
    assert torch.allclose(torch.cat([p.query_H_canon for p in one]), ref.query_H_canon, rtol=1e-5, atol=1e-4)
    assert torch.allclose(torch.cat([p.distance for p in one]), ref.distance, atol=1e-5)


def test_all_distances_are_cdist_s() -> None:
    g = torch.Generator().manual_seed(3)
    gallery, queries = torch.randn(300, 16, generator=g), torch.randn(5, 16, generator=g)
    expected = torch.cdist(queries.double(), gallery.double())
    torch.testing.assert_close(distances(queries, gallery.double()), expected, rtol=0, atol=1e-12)
    torch.testing.assert_close(distances(queries, gallery.double(), gallery.double().pow(2).sum(-1)), expected,
                               rtol=0, atol=1e-12)
    assert distances(queries[:0], gallery.double()).shape == (0, 300)
