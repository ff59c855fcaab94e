"""The inverse-compositional refiner (matl.inference.fast_refine, refiner=fast, the default of refine=true)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from matl.data.gallery import Gallery
from matl.geometry import HomographySampler, corner_error_px, warp_image
from matl.inference.fast_refine import FastRefiner
from matl.inference.refine import RefinedRecognizer
from matl.models.prediction import Prediction
from matl.utils.errors import MatlError
from tests.inference.test_refine import FixedRecognizer, plane_gallery
from tests.speed_helpers import textured_planes

S, B = 64, 6


def scene(seed: int = 2) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Anchors, queries = exact warps of them by ``query_H_anchor`` (object kept inside), those
    homographies, and starts ``~2-3 px`` (mean corner error) away from them."""
    g = torch.Generator().manual_seed(seed)
    anchors = textured_planes(B, S, seed)
    true = HomographySampler(translation=(-0.08, 0.08), rotation_deg=(-20, 20), scale=(0.9, 1.1),
                             tilt=(-0.2, 0.2)).sample(B, (S, S), g)
    queries = warp_image(anchors, true.float())
    perturbation = HomographySampler(translation=(-0.04, 0.04), rotation_deg=(-3, 3), scale=(0.97, 1.03),
                                     tilt=(-0.03, 0.03), keep_inside=False).sample(B, (S, S), g)
    return anchors, queries, true, true @ perturbation


def test_round_trip_converges_to_the_true_pose() -> None:
    anchors, queries, true, start = scene()
    before = corner_error_px(start, true, (S, S))
    assert float(before.mean()) > 1.5  # the premise: a few pixels off
    result = FastRefiner().refine_images(queries, anchors, start)
    after = corner_error_px(result.query_H_anchor, true, (S, S))
    assert float(after.max()) < 0.6, after
    assert bool(result.accepted.all()) and bool((result.loss_after < result.loss_before).all())


def test_an_exact_start_stays_and_a_hopeless_query_keeps_its_start() -> None:
    anchors = textured_planes(2, S, 3)
    shift = torch.eye(3, dtype=torch.float64).repeat(2, 1, 1)
    shift[:, 0, 2], shift[:, 1, 2] = 3.0, -2.0  # an integer shift: the warped query equals the anchor
    queries = warp_image(anchors, shift.float())
    result = FastRefiner().refine_images(queries, anchors, shift)
    assert float(corner_error_px(result.query_H_anchor, shift, (S, S)).max()) < 1e-3
    # the wrong object and a flat image: nothing explains them, the start comes back untouched
    anchors, queries, _, start = scene()
    hopeless = torch.cat([queries.roll(1, dims=0)[:3], torch.full_like(queries[:3], 0.5)])
    result = FastRefiner().refine_images(hopeless, anchors, start)
    kept = ~result.accepted
    assert bool(kept[3:].all())
    assert torch.equal(result.query_H_anchor[kept], start[kept].double())
    assert bool((result.loss_after <= result.loss_before).all())
    bad = torch.zeros(2, 3, 3, dtype=torch.float64)
    bad[:, 2, 2] = 1.0  # a degenerate start (a broken STN) is returned unchanged
    result = FastRefiner().refine_images(queries[:2], anchors[:2], bad)
    assert not bool(result.accepted.any()) and torch.equal(result.query_H_anchor, bad)


def test_lighting_does_not_move_the_pose_and_the_foreground_region_ignores_a_background() -> None:
    anchors, queries, true, start = scene()
    clean = FastRefiner().refine_images(queries, anchors, start).query_H_anchor
    relit = queries * 0.6 + 0.05 * (queries > 0)               # gain and bias of the object, background still 0
    moved = FastRefiner().refine_images(relit, anchors, start).query_H_anchor
    assert float(corner_error_px(moved, clean, (S, S)).max()) < 0.3
    # a full-frame texture behind each object and a gain / bias change of the whole query
    clutter = textured_planes(B, S, 11).flip(-1) * 0.8 + 0.1
    inside = warp_image(torch.ones_like(anchors[:, :1]), true.float()) > 0.999
    cluttered = torch.where(inside, queries, clutter) * 0.6 + 0.15
    foreground = FastRefiner(region="foreground").refine_images(cluttered, anchors, start)
    assert float(corner_error_px(foreground.query_H_anchor, true, (S, S)).max()) < 0.8


def test_region_auto_keeps_the_frame_on_segmented_queries_and_takes_the_foreground_beside_clutter() -> None:
    anchors, queries, true, start = scene()
    frame = FastRefiner(region="frame").refine_images(queries, anchors, start)
    auto = FastRefiner(region="auto")
    segmented = auto.refine_images(queries, anchors, start)
    assert torch.equal(segmented.query_H_anchor, frame.query_H_anchor)  # nothing beside the objects: the frame
    templates = auto.anchor_templates(anchors)
    assert templates.foreground is not None and templates.outside is not None
    assert templates.nbytes > FastRefiner(region="frame").anchor_templates(anchors).nbytes
    clutter = textured_planes(B, S, 11).flip(-1) * 0.8 + 0.1
    on_object = warp_image((anchors.amax(1, keepdim=True) > 0).float(), true.float()) > 0.5
    cluttered = torch.where(on_object, queries, clutter)  # a texture right up to each object's outline
    leaks = []
    for i in range(B):
        level = templates.anchors[i][0]
        H = level.norm_H_pixel @ true[i].numpy() @ level.pixel_H_norm
        gray = (cluttered[i] * torch.tensor([0.299, 0.587, 0.114])[:, None, None]).sum(0).numpy()
        leaks.append(auto.leak(gray, level, templates.outside[i], H / H[2, 2]))
    assert min(leaks) > auto.auto_leak  # at the true pose: a textured background beside every object
    result = auto.refine_images(cluttered, anchors, start)
    whole = FastRefiner(region="frame").refine_images(cluttered, anchors, start)
    after = corner_error_px(result.query_H_anchor, true, (S, S))
    frame_error = corner_error_px(whole.query_H_anchor, true, (S, S))
    assert float(frame_error.min()) > 5.0  # the whole frame is pulled off by the background
    # most queries show the background beside the object after the whole-frame pass and go to the foreground pass
    assert int((after < 0.5).sum()) >= 4 and float(after.median()) < 0.5


def test_precomputed_anchors_equal_per_query_templates_and_batches_equal_single_queries() -> None:
    anchors, queries, _, start = scene()
    gallery_images = torch.cat([textured_planes(3, S, 7), anchors])        # the anchors are entries 3..8
    index = torch.arange(3, 3 + B)
    refiner = FastRefiner().prepare(gallery_images)
    assert refiner._templates is not None and refiner._templates.nbytes > 0
    batched = refiner(queries, index, start)
    per_query = refiner.refine_images(queries, anchors, start)
    assert torch.equal(batched.query_H_anchor, per_query.query_H_anchor)
    assert torch.equal(batched.accepted, per_query.accepted)
    for i in range(B):  # a batch is a loop over its queries: the same numbers
        one = refiner(queries[i:i + 1], index[i:i + 1], start[i:i + 1])
        assert torch.equal(one.query_H_anchor, batched.query_H_anchor[i:i + 1])
        assert len(refiner.last_level_ms) == 3  # a single query's time per level, finest first


def test_a_large_gallery_computes_each_anchor_at_its_first_need_and_keeps_the_latest() -> None:
    anchors, queries, _, start = scene()
    gallery_images = torch.cat([textured_planes(3, S, 7), anchors])        # the anchors are entries 3..8
    index = torch.arange(3, 3 + B)
    eager = FastRefiner().prepare(gallery_images)
    lazy = FastRefiner(precompute=4).prepare(gallery_images)              # 9 anchors > 4: none computed yet
    templates = lazy._templates
    assert templates is not None and templates.keep == 4 and templates.nbytes == 0
    assert all(a is None for a in templates.anchors) and len(templates) == 9
    assert torch.equal(lazy(queries, index, start).query_H_anchor, eager(queries, index, start).query_H_anchor)
    # the 6 queries' anchors were computed in turn; the last 4 are kept
    assert list(templates.computed) == [5, 6, 7, 8]
    assert [a is not None for a in templates.anchors] == [False] * 5 + [True] * 4
    assert all((f is None) == (a is None) for a, f in zip(templates.anchors, templates.foreground, strict=True))
    assert 0 < templates.nbytes < eager._templates.nbytes
    again = lazy(queries[:1], index[:1], start[:1])                       # anchor 3 again: computed anew
    assert torch.equal(again.query_H_anchor, eager(queries[:1], index[:1], start[:1]).query_H_anchor)
    assert list(templates.computed) == [6, 7, 8, 3]


def test_iterations_per_level_and_zero_iterations_keep_the_start() -> None:
    anchors, queries, true, start = scene()
    none = FastRefiner(iterations=0).refine_images(queries, anchors, start)
    assert not bool(none.accepted.any()) and torch.equal(none.query_H_anchor, start.double())
    coarse_only = FastRefiner(iterations=[0, 0, 6]).refine_images(queries, anchors, start)
    fine = FastRefiner(iterations=[6, 6, 6]).refine_images(queries, anchors, start)
    before = corner_error_px(start, true, (S, S))
    mid = corner_error_px(coarse_only.query_H_anchor, true, (S, S))
    after = corner_error_px(fine.query_H_anchor, true, (S, S))
    assert float(mid.mean()) < float(before.mean()) and float(after.mean()) < float(mid.mean())


class AlignedRecognizer(FixedRecognizer):
    """A recognizer with an alignment stage that spoils the pose (so skipping it shows)."""

    def __init__(self, gallery: Gallery, index: torch.Tensor, H: torch.Tensor) -> None:
        super().__init__(gallery, index, H)
        self.align = "stage"
        self.seen: list[object] = []

    def __call__(self, queries: torch.Tensor) -> Prediction:
        self.seen.append(self.align)
        pred = super().__call__(queries)
        if self.align is None:
            return pred
        shift = torch.eye(3, dtype=torch.float64)
        shift[0, 2] = 40.0  # far outside the refinement's basin
        return dataclasses.replace(pred, query_H_anchor=shift @ pred.query_H_anchor.double())


def test_refined_recognizer_precomputes_the_gallery_once_and_start_stn_skips_the_alignment_stage() -> None:
    anchors, queries, true, start = scene(seed=6)
    n = len(anchors)
    gallery = plane_gallery(anchors.flip(0))
    index = torch.arange(n).flip(0)
    index[0] = -1
    recognizer = AlignedRecognizer(gallery, index, start)
    refined = RefinedRecognizer(recognizer, FastRefiner())
    assert refined.templates is not None and len(refined.templates) == n and refined.skips_align
    out = refined(queries)
    assert recognizer.seen == [None] and recognizer.align == "stage"  # skipped for the call, restored after
    error = corner_error_px(out.query_H_canon, true, (S, S))
    assert float(error[1:].max()) < 0.6
    assert torch.equal(out.query_H_anchor[0], start[0].double())
    # start=align refines the stage's (here spoilt) pose; the same templates can be shared
    kept = RefinedRecognizer(recognizer, FastRefiner(start="align"), templates=refined.templates)
    assert kept.templates is refined.templates and not kept.skips_align
    far = corner_error_px(kept(queries).query_H_canon, true, (S, S))
    assert recognizer.seen[-1] == "stage" and float(far[1:].min()) > 10.0


def test_fast_refiner_options_are_one_line_errors() -> None:
    for kwargs in ({"loss": "l1"}, {"levels": 0}, {"iterations": -1}, {"iterations": [2, -1]}, {"delta": 0.0},
                   {"region": "all"}, {"start": "none"}, {"erode": -1}, {"threads": 0}, {"blur": -1.0},
                   {"auto_band": -1}, {"auto_leak": -0.1}, {"auto_level": -1.0}, {"auto_from": "stn"},
                   {"compare_align": "yes"}, {"match_upscale": 0.5}, {"match_upscale": True}, {"cache": -1},
                   {"visibility": 1}, {"precompute": 0}, {"precompute": 2.5}):
        with pytest.raises(MatlError, match="refiner"):
            FastRefiner(**kwargs)
    with pytest.raises(MatlError, match="prepare"):
        FastRefiner()(torch.zeros(1, 3, S, S), torch.zeros(1, dtype=torch.long), torch.eye(3)[None])


def test_refine_true_is_the_fast_refiner_with_the_config_defaults() -> None:
    from matl.inference.recognizer_options import _refiner
    from matl.utils.errors import CONF_DIR

    default = _refiner(True)
    assert isinstance(default, FastRefiner)
    configured = FastRefiner(**{k: v for k, v in OmegaConf.to_container(
        OmegaConf.load(CONF_DIR / "refiner" / "fast.yaml")).items() if k != "_target_"})
    assert default.options() == configured.options()


class _OneMissing:
    """A search whose first query finds nothing (an approximate index can come back empty: -1)."""

    def __init__(self, search) -> None:
        self.inner = search

    def search(self, queries: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        index, distance = self.inner.search(queries)
        index = index.clone()
        index[0] = -1
        return index, distance


def test_refined_matl_recognizer_composes_the_pose_once_and_an_unmatched_query_keeps_its_answer() -> None:
    from matl.geometry import compose_query_H_canon
    from matl.models.recognizer import TensorRecognizer
    from tests.models.test_recognizer import gallery, networks

    feature_net, stn = networks()
    g = gallery(feature_net)
    recognizer = TensorRecognizer(feature_net, stn, g)
    queries = g.images[[1, 6, 11]]
    assert recognizer(queries, pose=False).query_H_canon is None
    plain = recognizer(queries)
    refined = RefinedRecognizer(recognizer, FastRefiner(min_size=4))
    out = refined(queries)
    assert torch.equal(out.gallery_index, plain.gallery_index)
    expected = compose_query_H_canon(out.query_H_anchor.double(), g.anchor_H_canon[out.gallery_index].double())
    assert torch.allclose(out.query_H_canon.double(), expected, atol=1e-9)
    # a query the search leaves without an anchor keeps the recognizer's own pose
    recognizer.search = _OneMissing(recognizer.search)
    missing = refined(queries)
    assert int(missing.gallery_index[0]) == -1
    assert torch.allclose(missing.query_H_anchor[0].double(), plain.query_H_anchor[0].double(), atol=1e-6)
    assert torch.allclose(missing.query_H_canon[0].double(), compose_query_H_canon(
        plain.query_H_anchor[:1].double(), g.anchor_H_canon[:1].double())[0], atol=1e-6)
    assert torch.allclose(missing.query_H_canon[1:], out.query_H_canon[1:])


def hidden_bar(queries: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``queries`` with a 10 px vertical bar cut out by their masks (0 there, as the foreground step leaves it), and
    those masks ``(B, 1, S, S)``."""
    visibility = torch.ones(len(queries), 1, S, S)
    visibility[..., :, 24:34] = 0.0
    return queries * visibility, visibility


def test_what_the_mask_hides_costs_nothing() -> None:
    anchors, queries, true, start = scene()
    masked, visibility = hidden_bar(queries)
    # region=auto's foreground pass can take extreme poses of a cut query: the whole frame here
    refiner = FastRefiner(region="frame", visibility=True)
    templates = refiner.anchor_templates(anchors)
    index = torch.arange(B)
    seen = refiner(masked, index, start, templates, visibility=visibility)
    assert float(corner_error_px(seen.query_H_anchor, true, (S, S)).max()) < 0.6
    # every pixel counted as it is: the cut-out print pulls the pose off
    blind = refiner(masked, index, start, templates)
    assert float(corner_error_px(blind.query_H_anchor, true, (S, S)).max()) > 10.0
    off = FastRefiner(region="frame", visibility=False)(masked, index, start, templates, visibility=visibility)
    assert torch.equal(off.query_H_anchor, blind.query_H_anchor)
    # a visibility of ones is the unweighted refinement
    ones = refiner(queries, index, start, templates, visibility=torch.ones(B, 1, S, S))
    assert torch.equal(ones.query_H_anchor, refiner(queries, index, start, templates).query_H_anchor)
    with pytest.raises(MatlError, match="visibility"):
        refiner(masked, index, start, templates, visibility=visibility[:, :, :-1])


def test_never_worse_keeps_the_unrefined_pose_of_lowest_loss() -> None:
    anchors, queries, true, start = scene()
    refiner = FastRefiner()
    templates = refiner.anchor_templates(anchors)
    index = torch.arange(B)
    # a start that is already optimal stays: nothing lowers its loss (0 at an integer shift), it comes back as it was
    shift = torch.eye(3, dtype=torch.float64).repeat(B, 1, 1)
    shift[:, 0, 2], shift[:, 1, 2] = 3.0, -2.0
    shifted = warp_image(anchors, shift.float())
    exact = refiner(shifted, index, shift, templates, alternatives=start[:, None])
    assert torch.equal(exact.query_H_anchor, shift) and exact.source.tolist() == [1] * B
    frozen = FastRefiner(iterations=0)(queries, index, true, templates, alternatives=start[:, None])
    assert torch.equal(frozen.query_H_anchor, true.double()) and frozen.source.tolist() == [1] * B
    assert not bool(frozen.accepted.any())
    # a start far off, one step from it: it loses to a better unrefined pose given beside it
    far = true.clone()
    far[:, 0, 2] += 14.0
    one = FastRefiner(iterations=1, region="frame", visibility=True)  # the whole frame: a step from far stays sane
    frame = one.anchor_templates(anchors)
    kept = one(queries, index, far, frame, alternatives=torch.stack([far, true], 1))
    assert kept.source.tolist() == [3] * B and torch.equal(kept.query_H_anchor, true.double())
    assert bool((kept.loss_after < kept.loss_before).all())
    # refined from the far start it may not come back, but never ends above the best pose it was given
    refined = refiner(queries, index, start, templates, alternatives=far[:, None])
    assert bool((refined.loss_after <= refined.loss_before).all()) and 2 not in refined.source.tolist()
    # the same with the queries' visibility: every pose is judged on the pixels all of them show
    masked, visibility = hidden_bar(queries)
    kept = one(masked, index, far, frame, visibility=visibility, alternatives=true[:, None])
    assert kept.source.tolist() == [2] * B and torch.equal(kept.query_H_anchor, true.double())


def test_small_queries_are_refined_against_their_anchor_at_their_resolution() -> None:
    from matl.inference.refine import at_resolution

    anchors, queries, true, start = scene()
    small = at_resolution(queries, 25)  # a 25 px file enlarged to the model's 64 px
    upscale = torch.full((B,), S / 25)
    refiner = FastRefiner()
    templates = refiner.anchor_templates(anchors)
    index = torch.arange(B)
    matched = refiner(small, index, start, templates, upscale=upscale)
    assert float(corner_error_px(matched.query_H_anchor, true, (S, S)).max()) < 0.6
    assert len(templates.resampled) == B and all(side == 25 for _, side in templates.resampled)
    # against the sharp anchor the blurred query is pulled inwards
    sharp = refiner(small, index, start, templates)
    assert float(corner_error_px(sharp.query_H_anchor, true, (S, S)).min()) > 1.5
    assert torch.equal(FastRefiner(match_upscale=None)(small, index, start, templates, upscale=upscale).query_H_anchor,
                       sharp.query_H_anchor)
    # at or below match_upscale the precomputed anchors serve; the kept ones are reused, the oldest dropped
    below = FastRefiner(match_upscale=3.0)(small, index, start, templates, upscale=upscale)
    assert torch.equal(below.query_H_anchor, sharp.query_H_anchor)
    again = refiner(small, index, start, templates, upscale=upscale)
    assert torch.equal(again.query_H_anchor, matched.query_H_anchor)
    FastRefiner(cache=2)(small, index, start, templates, upscale=torch.full((B,), S / 30))
    assert len(templates.resampled) == 2 and list(templates.resampled) == [(B - 2, 30), (B - 1, 30)]


class StubAlign:
    """An alignment stage whose pose is a given one per query."""

    def __init__(self, H: torch.Tensor) -> None:
        self.H, self.calls = H, 0

    def infer(self, queries, anchors, query_H_anchor, warped=None):
        self.calls += 1
        return type("Out", (), {"query_H_anchor": self.H[: len(queries)].to(query_H_anchor.dtype)})()


def test_compare_align_keeps_the_stage_pose_when_the_refinement_does_worse() -> None:
    anchors, queries, true, _ = scene(seed=6)
    n = len(anchors)
    gallery = plane_gallery(anchors)
    far = true.clone()
    far[:, 1, 2] += 15.0  # s()'s pose: beyond the refinement's basin
    recognizer = FixedRecognizer(gallery, torch.arange(n), far)
    recognizer.align = StubAlign(true)  # the stage: right
    plain = RefinedRecognizer(recognizer, FastRefiner(iterations=1))
    compared = RefinedRecognizer(recognizer, FastRefiner(iterations=1, compare_align=True), templates=plain.templates)
    assert plain.skips_align and compared.skips_align
    without = plain(queries)
    assert recognizer.align.calls == 0 and float(corner_error_px(without.query_H_anchor, true, (S, S)).min()) > 5.0
    with_stage = compared(queries)
    assert recognizer.align.calls == 1 and compared.last.source.tolist() == [2] * n
    assert float(corner_error_px(with_stage.query_H_anchor, true, (S, S)).max()) < 1e-9


def test_a_pose_that_turns_the_plane_over_or_sends_it_beyond_infinity_is_never_kept() -> None:
    from matl.inference.fast_refine import _folds

    assert not _folds(np.eye(3)) and not _folds(np.array([[0.9, 0.1, 0.1], [-0.1, 1.1, 0.0], [0.05, 0.02, 1.0]]))
    assert _folds(np.diag([-1.0, 1.0, 1.0]))                     # mirrored: the plane seen from behind
    assert _folds(np.array([[1.0, 0, 0], [0, 1.0, 0], [1.5, 0, 1.0]]))  # a corner at or beyond infinity
    sheared = np.eye(3)
    sheared[0, 1] = 1.2  # an affine map keeps the corners convex and turning one way
    assert not _folds(sheared)
