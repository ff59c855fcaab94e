"""Test-time refinement (matl.inference.refine), gallery search backends and the inference options."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from omegaconf import open_dict

from matl.data.gallery import Gallery
from matl.geometry import HomographySampler, corner_error_px, warp_image
from matl.inference.options import configure_recognizer
from matl.inference.refine import PhotometricRefiner, RefinedRecognizer
from matl.models.feature import FeatureNet
from matl.models.prediction import Prediction
from matl.models.recognizer import TensorRecognizer
from matl.models.search import ExactSearch, FaissSearch, nearest
from matl.utils.errors import MatlError
from tests.conftest import compose_config
from tests.speed_helpers import textured_planes, write_tiny_checkpoint

S, B = 64, 8


def scene(seed: int = 1, lighting: bool = False) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Anchors, queries = anchors warped by known ``query_H_anchor``, those homographies, and a start
    ``~4 px`` (mean corner error) away from them."""
    g = torch.Generator().manual_seed(seed)
    anchors = textured_planes(B, S, seed)
    true = HomographySampler(translation=(-0.1, 0.1), rotation_deg=(-30, 30), scale=(0.9, 1.1), tilt=(-0.3, 0.3),
                             keep_inside=False).sample(B, (S, S), g)
    queries = warp_image(anchors, true.float())
    if lighting:  # darker, with a bias on the object (background stays 0)
        queries = queries * 0.7 + 0.05 * (queries > 0)
    perturbation = HomographySampler(translation=(-0.06, 0.06), rotation_deg=(-5, 5), scale=(0.95, 1.05),
                                     tilt=(-0.06, 0.06), keep_inside=False).sample(B, (S, S), g)
    return anchors, queries, true, true @ perturbation


@pytest.mark.parametrize("lighting", [False, True])
def test_refinement_recovers_a_perturbed_pose(lighting: bool) -> None:
    anchors, queries, true, start = scene(lighting=lighting)
    before = corner_error_px(start, true, (S, S))
    assert 2.5 < float(before.mean()) < 6.0  # the premise: a few pixels off
    result = PhotometricRefiner()(queries, anchors, start)
    after = corner_error_px(result.query_H_anchor, true, (S, S))
    assert float(after.max()) < 1.0, after
    assert float(after.mean()) < 0.35 * float(before.mean())
    assert bool(result.accepted.all()) and bool((result.loss_after <= result.loss_before).all())


@pytest.mark.parametrize("loss", ["l2", "cauchy"])
def test_other_robust_losses_converge(loss: str) -> None:
    anchors, queries, true, start = scene(seed=2)
    result = PhotometricRefiner(loss=loss, grayscale=loss == "l2")(queries, anchors, start)
    assert float(corner_error_px(result.query_H_anchor, true, (S, S)).max()) < 1.0


def test_refinement_is_a_noop_at_the_exact_pose() -> None:
    # an integer shift: the warped query equals the anchor exactly, nothing can improve
    anchors = textured_planes(2, S, 3)
    shift = torch.eye(3, dtype=torch.float64).repeat(2, 1, 1)
    shift[:, 0, 2], shift[:, 1, 2] = 3.0, -2.0
    queries = warp_image(anchors, shift.float())
    result = PhotometricRefiner()(queries, anchors, shift)
    assert float(corner_error_px(result.query_H_anchor, shift, (S, S)).max()) < 1e-6
    # a general homography: stays within interpolation accuracy of the truth
    anchors, queries, true, _ = scene(seed=4)
    result = PhotometricRefiner()(queries, anchors, true)
    assert float(corner_error_px(result.query_H_anchor, true, (S, S)).max()) < 0.3


def test_refinement_never_makes_the_loss_worse() -> None:
    anchors, queries, true, _ = scene(seed=5)
    g = torch.Generator().manual_seed(0)
    wild = HomographySampler(translation=(-0.3, 0.3), rotation_deg=(-180, 180), scale=(0.5, 1.5),
                             tilt=(-0.8, 0.8), keep_inside=False).sample(B, (S, S), g)
    starts = torch.cat([wild, true @ wild])[:B]
    wrong_anchors = anchors.roll(1, dims=0)  # the wrong object: no pose explains it
    refiner = PhotometricRefiner(iterations=4)
    for anchor_set in (anchors, wrong_anchors):
        result = refiner(queries, anchor_set, starts)
        assert bool((result.loss_after <= result.loss_before).all())
        kept = ~result.accepted
        assert torch.equal(result.query_H_anchor[kept], starts[kept])  # rejected: the input, untouched
        assert torch.isfinite(result.query_H_anchor).all()
    # a degenerate start (what a broken STN could give) comes back unchanged, finite or not
    bad = torch.zeros(2, 3, 3, dtype=torch.float64)
    bad[:, 2, 2] = 1.0
    result = refiner(queries[:2], anchors[:2], bad)
    assert not bool(result.accepted.any()) and torch.equal(result.query_H_anchor, bad)


def test_refinement_options_are_checked() -> None:
    for kwargs in ({"loss": "l1"}, {"levels": 0}, {"iterations": -1}, {"step": 0.0}, {"delta": 0.0},
                   {"match_upscale": 0.9}, {"visibility": "no"}):
        with pytest.raises(ValueError, match="refiner"):
            PhotometricRefiner(**kwargs)


def test_what_the_mask_hides_costs_nothing_and_the_best_unrefined_pose_is_kept() -> None:
    anchors, queries, true, start = scene(seed=2)
    visibility = torch.ones(B, 1, S, S)
    visibility[..., :, 24:34] = 0.0  # a bar cut out by each query's mask
    masked = queries * visibility
    refiner = PhotometricRefiner(visibility=True)
    seen = refiner(masked, anchors, start, visibility=visibility)
    assert float(corner_error_px(seen.query_H_anchor, true, (S, S)).max()) < 0.6
    blind = refiner(masked, anchors, start)
    assert float(corner_error_px(blind.query_H_anchor, true, (S, S)).median()) > 2.0
    off = PhotometricRefiner(visibility=False)(masked, anchors, start, visibility=visibility)
    assert torch.equal(off.query_H_anchor, blind.query_H_anchor)
    # never worse: a far start refined without a step loses to a better unrefined pose given beside it
    far = true.clone()
    far[:, 0, 2] += 14.0
    kept = PhotometricRefiner(iterations=0)(masked, anchors, far, visibility=visibility,
                                            alternatives=torch.stack([far, true], 1))
    assert kept.source.tolist() == [3] * B and torch.allclose(kept.query_H_anchor, true.double(), atol=1e-9)
    assert not bool(kept.accepted.any()) and bool((kept.loss_after < kept.loss_before).all())
    frozen = PhotometricRefiner(iterations=0)(queries, anchors, true, alternatives=far[:, None])
    assert frozen.source.tolist() == [1] * B and torch.equal(frozen.query_H_anchor, true.double())


def test_small_queries_are_compared_with_their_anchor_at_their_resolution() -> None:
    from matl.inference.refine import at_resolution

    anchors, queries, true, start = scene(seed=2)
    small = at_resolution(queries, 25)  # a 25 px file enlarged to the model's 64 px
    upscale = torch.full((B,), S / 25)
    matched = PhotometricRefiner()(small, anchors, start, upscale=upscale)
    sharp = PhotometricRefiner()(small, anchors, start)
    error = corner_error_px(matched.query_H_anchor, true, (S, S))
    assert float(error.max()) < 0.6 and float(error.mean()) < float(
        corner_error_px(sharp.query_H_anchor, true, (S, S)).mean())
    assert torch.equal(PhotometricRefiner(match_upscale=None)(small, anchors, start, upscale=upscale).query_H_anchor,
                       sharp.query_H_anchor)
    assert torch.equal(at_resolution(anchors, S), anchors)  # a file at least the model's size: nothing to do


# ------------------------------------------------------------------------------ recognizer wrapper
def plane_gallery(anchors: torch.Tensor) -> Gallery:
    """A gallery of ``(n, 3, S, S)`` anchor images, one object and plane each, anchor frames the canonical frames."""
    n = len(anchors)
    return Gallery(anchors, torch.arange(n), torch.arange(n), torch.zeros(n, dtype=torch.long),
                   torch.eye(3, dtype=torch.float64).repeat(n, 1, 1), [f"o{i}" for i in range(n)],
                   [f"p{i}" for i in range(n)])


class FixedRecognizer:
    """Returns given indices and poses (a stand-in for any recognizer)."""

    def __init__(self, gallery: Gallery, index: torch.Tensor, query_H_anchor: torch.Tensor) -> None:
        self.gallery, self.index, self.H = gallery, index, query_H_anchor

    def __call__(self, queries: torch.Tensor) -> Prediction:
        g, i = self.gallery, self.index
        safe = i.clamp_min(0)
        pose = self.H @ g.anchor_H_canon[safe]
        return Prediction(i, g.object_index[safe], g.plane_index[safe], g.anchor_index[safe],
                          torch.zeros(len(i)), self.H, pose, queries, torch.zeros(len(i), dtype=torch.bool))


def test_refined_recognizer_refines_against_the_selected_anchor() -> None:
    anchors, queries, true, start = scene(seed=6)
    n = len(anchors)
    gallery = plane_gallery(anchors.flip(0))
    index = torch.arange(n).flip(0)  # gallery entry of query i is n - 1 - i
    index[0] = -1                    # an unmatched query (a baseline's -1) keeps its prediction
    refined = RefinedRecognizer(FixedRecognizer(gallery, index, start), PhotometricRefiner())(queries)
    error = corner_error_px(refined.query_H_canon, true, (S, S))
    assert float(error[1:].max()) < 1.0
    assert torch.equal(refined.query_H_anchor[0], start[0])
    assert torch.equal(refined.gallery_index, index)


def test_refine_check_keeps_the_pose_it_judges_better() -> None:
    anchors, queries, true, start = scene(seed=6)
    n = len(anchors)
    gallery = plane_gallery(anchors)
    index = torch.arange(n)
    seen: list[tuple[int, ...]] = []

    def prefer(unrefined_rows: set[int]):  # a judge scoring the unrefined pose lower for these queries only
        def check(q: torch.Tensor, H: torch.Tensor, i: torch.Tensor, vis: torch.Tensor | None) -> torch.Tensor:
            seen.append((len(q), len(H), len(i)))
            score = torch.ones(len(H), dtype=torch.float64)
            for row in unrefined_rows:
                score[n + row] = 0.0  # the start's copy of the query
            return score
        return check

    plain = RefinedRecognizer(FixedRecognizer(gallery, index, start), PhotometricRefiner())(queries)
    kept = RefinedRecognizer(FixedRecognizer(gallery, index, start), PhotometricRefiner(), check=prefer({1}))(queries)
    assert seen == [(2 * n, 2 * n, 2 * n)]  # every query's refined and unrefined pose in one call
    assert torch.equal(kept.query_H_anchor[1], start[1].to(kept.query_H_anchor))
    others = [r for r in range(n) if r != 1]
    assert torch.equal(kept.query_H_anchor[others], plain.query_H_anchor[others])
    assert float(corner_error_px(kept.query_H_canon[others], true[others], (S, S)).max()) < 1.0
    tie = RefinedRecognizer(FixedRecognizer(gallery, index, start), PhotometricRefiner(), check=prefer(set()))(queries)
    assert torch.equal(tie.query_H_anchor, plain.query_H_anchor)  # equal scores: the refined pose


# ----------------------------------------------------------------------------------------- search
def test_exact_search_caches_norms_and_matches_cdist() -> None:
    g = torch.Generator().manual_seed(0)
    gallery, queries = torch.randn(1000, 16, generator=g), torch.randn(7, 16, generator=g)
    search = ExactSearch(gallery, chunk=128)
    idx, dist = search.search(queries)
    ref = torch.cdist(queries, gallery).min(1)
    assert torch.equal(idx, ref.indices) and torch.allclose(dist, ref.values, atol=1e-4)
    assert torch.equal(nearest(queries, gallery)[0], idx)


def test_recognizer_rebuilds_its_search_when_features_change() -> None:
    S_ = 32
    images = textured_planes(6, S_, 0)
    gallery = Gallery(images, torch.arange(6), torch.arange(6), torch.zeros(6, dtype=torch.long),
                      torch.eye(3, dtype=torch.float64).repeat(6, 1, 1), [str(i) for i in range(6)],
                      [str(i) for i in range(6)])
    rec = TensorRecognizer(FeatureNet(), None, gallery)
    rec.gallery_features = torch.eye(6, 128)[torch.tensor([5, 4, 3, 2, 1, 0])]
    assert torch.equal(rec.search.features, rec.gallery_features)
    faiss = pytest.importorskip("faiss")
    assert faiss is not None
    rec.use_search(lambda f: FaissSearch(f, index="flat"))
    assert isinstance(rec.search, FaissSearch)
    idx, _ = rec.search.search(torch.eye(6, 128)[:2])
    assert idx.tolist() == [5, 4]


def test_faiss_hnsw_finds_the_nearest_neighbours() -> None:
    pytest.importorskip("faiss")
    g = torch.Generator().manual_seed(0)
    gallery = torch.nn.functional.normalize(torch.randn(3000, 32, generator=g), dim=1)
    queries = torch.nn.functional.normalize(gallery[:50] + 0.02 * torch.randn(50, 32, generator=g), dim=1)
    for index in ("hnsw", "ivf", "flat"):
        found, _ = FaissSearch(gallery, index=index, nlist=32, nprobe=8).search(queries)
        assert float((found == torch.arange(50)).float().mean()) >= 0.95, index


# ------------------------------------------------------------------------------ inference options
def test_configure_recognizer_applies_search_and_refine(tmp_path: Path) -> None:
    images = textured_planes(4, 32, 0)
    gallery = Gallery(images, torch.arange(4), torch.arange(4), torch.zeros(4, dtype=torch.long),
                      torch.eye(3, dtype=torch.float64).repeat(4, 1, 1), list("abcd"), list("abcd"))
    cfg = compose_config("eval", ["refine=true", "refiner.iterations=2"], tmp_path)
    rec, info = configure_recognizer(TensorRecognizer(FeatureNet(), None, gallery),
                                     compose_config("eval", [], tmp_path))
    assert info == {"search": "exact", "refine": False, "refiner": None} and isinstance(rec, TensorRecognizer)
    with pytest.raises(MatlError, match="no STN"):  # TL: nothing to refine
        configure_recognizer(TensorRecognizer(FeatureNet(), None, gallery), cfg)
    fixed = FixedRecognizer(gallery, torch.arange(4), torch.eye(3, dtype=torch.float64).repeat(4, 1, 1))
    rec, info = configure_recognizer(fixed, cfg)  # any recognizer with a pose (e.g. a baseline) refines
    assert isinstance(rec, RefinedRecognizer) and info["refine"] and info["refiner"]["iterations"] == 2
    assert rec(images).query_H_canon.shape == (4, 3, 3)
    faiss_cfg = compose_config("eval", ["search=faiss"], tmp_path)
    with pytest.raises(MatlError, match="search=faiss applies to embedding models"):
        configure_recognizer(fixed, faiss_cfg)
    with open_dict(faiss_cfg):
        faiss_cfg.search.index = "lsh"
    with pytest.raises(MatlError, match=r"search\.index"):
        configure_recognizer(TensorRecognizer(FeatureNet(), None, gallery), faiss_cfg)


def test_predict_with_refinement_and_faiss(tmp_path: Path, cache_dir: Path) -> None:
    """End to end on image files with an untrained tiny checkpoint: refine=true and search=faiss run
    and say so in the summary; the records stay valid."""
    pytest.importorskip("faiss")
    from matl.inference.files import predict
    from tests.predict_helpers import make_files

    ckpt = write_tiny_checkpoint(tmp_path / "ckpt" / "tiny.ckpt", cache_dir)
    gallery, queries, _ = make_files(tmp_path)
    overrides = [f"ckpt={ckpt}", f"gallery={gallery}", f"images={queries}", f"out={tmp_path / 'p.jsonl'}",
                 "refine=true", "search=faiss", "search.index=flat", "cache=false"]
    summary = predict(compose_config("predict", overrides, tmp_path / "run"))
    assert summary["predicted"] == 3 and summary["refine"] is True and summary["search"] == "faiss"
    for line in (tmp_path / "p.jsonl").read_text().splitlines():
        record = json.loads(line)
        assert torch.isfinite(torch.tensor(record["H"])).all() and record["H"][2][2] == pytest.approx(1.0)
