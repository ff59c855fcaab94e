"""Photometric verification: hand-computed ZNCC, ``1 - ZNCC`` of posed queries (over the whole plane and over the
visible part, patch by patch), candidates tried in order."""

from __future__ import annotations

import math

import pytest
import torch

from matl.data.gallery import Gallery
from matl.inference.verify import (
    DIFFERENCE_OVERLAP,
    MIN_PATCHES,
    MIN_PIXELS,
    PATCH_CELLS,
    SHORTLIST_EXTRA,
    SHORTLIST_VERIFY_MAX,
    CandidateMemo,
    aligned_queries,
    anchor_foreground,
    away_from_hidden,
    candidate_distances,
    coarse_similarity,
    covered_share,
    difference_distances,
    explained_distance,
    gaussian_blur,
    hidden_share,
    memo_poses,
    patch_distances,
    shown_pixels,
    subject_share,
    verification_distance,
    verify_candidates,
    weighted_zncc,
    zncc,
)

S = 32


def row(*values: float) -> torch.Tensor:
    """``(1, C, 1, W)`` from per-channel lists."""
    return torch.tensor(values, dtype=torch.float64)[None, :, None, :]


def textured(seed: int, size: int = S) -> torch.Tensor:
    """``(1, 3, S, S)`` a smooth random texture in [0.2, 0.8] on a zero border (an anchor's plane)."""
    g = torch.Generator().manual_seed(seed)
    coarse = torch.rand(1, 3, 6, 6, generator=g)
    image = torch.nn.functional.interpolate(coarse, size=(size, size), mode="bilinear", align_corners=True)
    image = 0.2 + 0.6 * image
    image[..., :4, :] = image[..., -4:, :] = image[..., :, :4] = image[..., :, -4:] = 0.0
    return image


def shift(dx: float, dy: float) -> torch.Tensor:
    return torch.tensor([[[1.0, 0.0, dx], [0.0, 1.0, dy], [0.0, 0.0, 1.0]]])


def test_zncc_by_hand() -> None:
    mask = torch.ones(1, 1, 1, 20, dtype=torch.bool)
    a = torch.arange(20, dtype=torch.float64)[None, None, None, :]
    assert float(zncc(a, 5.0 * a + 3.0, mask)[0]) == pytest.approx(1.0)       # gain and bias drop out
    assert float(zncc(a, -a, mask)[0]) == pytest.approx(-1.0)
    assert float(zncc(a, torch.full_like(a, 0.7), mask)[0]) == 0.0            # a flat image: no correlation
    # two channels, one flat in a: a' = [-1, 0, 1], [0, 0, 0]; b' = [-1, 0, 1], [1, 0, -1]
    # sum(a'b') = 2, sum(a'^2) = 2, sum(b'^2) = 4: 2 / sqrt(8)
    three = torch.ones(1, 1, 1, 3, dtype=torch.bool)
    a2, b2 = row([1, 2, 3], [0, 0, 0]), row([1, 2, 3], [1, 0, -1])
    small = zncc(a2, b2, three)
    assert float(small[0]) == 0.0  # 3 pixels < MIN_PIXELS: too few to compare
    wide = torch.ones(1, 1, 1, 3 * MIN_PIXELS, dtype=torch.bool)
    value = zncc(a2.repeat(1, 1, 1, MIN_PIXELS), b2.repeat(1, 1, 1, MIN_PIXELS), wide)
    assert float(value[0]) == pytest.approx(2 / math.sqrt(8))
    # only mask pixels count: outside it b is anything
    long = torch.arange(40, dtype=torch.float64)[None, None, None, :]
    half = torch.ones(1, 1, 1, 40, dtype=torch.bool)
    half[..., 20:] = False
    b = long.clone()
    b[..., 20:] = -100.0
    assert float(zncc(long, b, half)[0]) == pytest.approx(1.0)


def test_foreground_and_aligned_queries() -> None:
    anchor = textured(0)
    assert int(anchor_foreground(anchor, 0).sum()) == (S - 8) ** 2
    assert int(anchor_foreground(anchor, 1).sum()) == (S - 10) ** 2     # eroded by one pixel on each side
    warped, valid, seen = aligned_queries(anchor.float(), shift(3.0, 0.0))  # query = anchor shifted right by 3 px
    assert not bool(valid[0, 0, :, -3:].any()) and bool(valid[0, 0, :, :-3].all()) and seen is None
    assert torch.allclose(warped[0, :, :, :-3], anchor[0, :, :, 3:].float(), atol=1e-5)
    # the visibility travels with the pixels: the query's left half hidden is the anchor's columns up to S / 2 - 3
    visibility = torch.ones(1, 1, S, S)
    visibility[..., : S // 2] = 0.0
    _, _, seen = aligned_queries(anchor.float(), shift(3.0, 0.0), visibility=visibility)
    assert float(seen[0, 0, :, : S // 2 - 3].max()) == 0.0 and float(seen[0, 0, :, S // 2 - 3:-3].min()) == 1.0
    assert float(seen[0, 0, :, -3:].max()) == 0.0  # beyond the query's frame: nothing seen


def test_verification_distance_by_hand() -> None:
    anchor = textured(1).float()
    other = textured(2).float()
    # the query: the anchor under a gain and bias and shifted by (2, -1) px; query_H_anchor maps anchor -> query
    query = torch.zeros_like(anchor)
    query[..., :S - 1, 2:] = 0.6 * anchor[..., 1:, :-2] + 0.1
    exact = verification_distance(query, shift(2.0, -1.0), anchor, blur_sigma=0.0)
    assert float(exact[0]) == pytest.approx(0.0, abs=1e-6)
    blurred = verification_distance(query, shift(2.0, -1.0), anchor, blur_sigma=1.0)
    assert float(blurred[0]) < 0.01
    wrong_pose = verification_distance(query, shift(0.0, 0.0), anchor, blur_sigma=1.0)
    unrelated = verification_distance(other, torch.eye(3)[None], anchor, blur_sigma=1.0)
    assert float(wrong_pose[0]) > 0.05 and float(unrelated[0]) > 0.5
    assert verification_distance(query[:0], shift(0, 0)[:0], anchor[:0]).shape == (0,)


class StubRecognizer:
    """A gallery recognizer whose pose is the identity and whose features are given per query."""

    def __init__(self, anchors: torch.Tensor, objects: list[int], gallery_features: torch.Tensor,
                 query_features: torch.Tensor) -> None:
        n = len(anchors)
        self.gallery = Gallery(anchors, torch.tensor(objects), torch.arange(n), torch.zeros(n, dtype=torch.long),
                               torch.eye(3).repeat(n, 1, 1), [str(o) for o in sorted(set(objects))],
                               [str(i) for i in range(n)])
        self.gallery_features, self.query_features, self.align = gallery_features, query_features, None

    def gallery_distances(self, features: torch.Tensor) -> torch.Tensor:
        return torch.cdist(features.double(), self.gallery_features.double())

    def embed_queries(self, queries: torch.Tensor):
        n = len(queries)
        index = [int(i) for i in queries[:, 0, 0, 0]]  # the query's own number, stamped in a corner pixel
        return self.query_features[index], torch.eye(3).repeat(n, 1, 1), torch.zeros(n, dtype=torch.bool), queries


def test_candidates_are_tried_nearest_first_until_one_verifies() -> None:
    a, b, c = textured(10), textured(11), textured(12)
    anchors = torch.cat([a, b, c])
    # query 0 is c (its features nearest a, then b, then c); query 1 is unlike any anchor
    queries = torch.cat([c.clone(), textured(13)])
    queries[0, 0, 0, 0], queries[1, 0, 0, 0] = 0.0, 1.0  # stamps (outside the anchors' planes)
    gallery_features = torch.tensor([[0.0], [1.0], [2.0]])
    rec = StubRecognizer(anchors, [0, 1, 2], gallery_features, torch.tensor([[0.1], [0.2]]))
    v = verify_candidates(rec, queries, top_k=3, verify_max=0.1, blur_sigma=1.0)
    assert v.gallery_index.tolist() == [2, 0]            # query 0: c verifies (third); query 1: keeps its nearest
    assert v.verified.tolist() == [True, False] and v.tried.tolist() == [3, 3]
    assert float(v.feature_distance[0]) == pytest.approx(1.9)
    # two candidates only: c is never tried, nothing verifies
    assert verify_candidates(rec, queries, top_k=2, verify_max=0.1).verified.tolist() == [False, False]
    # c's own product excluded (the calibration's impostors): query 0 cannot verify
    v = verify_candidates(rec, queries, 3, 0.1, exclude_object=torch.tensor([2, 2]))
    assert v.verified.tolist() == [False, False] and v.tried.tolist() == [2, 2]
    # an answer given first that verifies ends the search for that query
    first = (torch.tensor([2, 1]), torch.eye(3).repeat(2, 1, 1), torch.tensor([5.0, 5.0]))
    v = verify_candidates(rec, queries, 3, 0.1, first=first)
    assert v.tried.tolist() == [1, 3] and v.gallery_index.tolist() == [2, 1] and v.verified.tolist() == [True, False]


def test_coarse_similarity_of_a_query_with_its_shortlisted_anchors() -> None:
    anchors = torch.cat([textured(seed) for seed in range(20, 26)])                 # (6, 3, S, S)
    pooled = torch.nn.functional.avg_pool2d(anchors, 4)[None]                        # (1, 6, 3, S/4, S/4)
    plane = torch.nn.functional.avg_pool2d((anchors.amax(1, keepdim=True) > 0).float(), 4)[None] > 0.99
    query = 1.7 * anchors[3:4] + 0.05                                               # a gain and a bias: the same print
    score = coarse_similarity(query, pooled, plane, 4)
    assert score.shape == (1, 6) and int(score.argmax()) == 3 and float(score[0, 3]) == pytest.approx(1.0, abs=1e-5)
    assert float(score[0].sort().values[-2]) < 0.9                                   # the others' prints differ
    empty = coarse_similarity(torch.zeros_like(query), pooled, plane, 4)             # no data: nothing compared
    assert torch.equal(empty, torch.full((1, 6), -1.0))
    gallery = Gallery(anchors, torch.arange(6), torch.arange(6), torch.zeros(6, dtype=torch.long),
                      torch.eye(3).repeat(6, 1, 1), list("abcdef"), list("abcdef"))
    held, share = gallery.coarse_images(4)
    assert torch.allclose(held, pooled[0]) and torch.equal(share, plane[0])
    assert gallery.coarse_images(4)[0] is held                                       # pooled once


def test_the_shortlist_meets_an_anchor_the_features_rank_far_by_its_pixels() -> None:
    anchors = torch.cat([textured(seed) for seed in range(30, 42)])                 # 12 products, one anchor each
    gallery_features = torch.arange(12, dtype=torch.float64)[:, None]
    queries = torch.cat([anchors[10:11].clone(), textured(50)])                      # product 10; one unlike any
    queries[0, 0, 0, 0], queries[1, 0, 0, 0] = 0.0, 1.0                             # stamps (outside the planes)
    rec = StubRecognizer(anchors, list(range(12)), gallery_features, torch.tensor([[0.0], [0.0]]))
    near = verify_candidates(rec, queries, top_k=3, verify_max=0.1)                 # product 10 is 11th nearest
    assert near.verified.tolist() == [False, False] and near.tried.tolist() == [3, 3]
    wide = verify_candidates(rec, queries, top_k=3, verify_max=0.1, shortlist=12)
    assert wide.gallery_index.tolist()[0] == 10 and wide.verified.tolist() == [True, False]
    assert wide.tried.tolist() == [3 + SHORTLIST_EXTRA] * 2 and float(wide.feature_distance[0]) == pytest.approx(10.0)
    assert verify_candidates(rec, queries, 3, 0.1, shortlist=3).tried.tolist() == [3, 3]  # at most top_k: none
    # a candidate found by its pixels verifies within the stricter bar only
    shifted = queries.clone()
    inner = anchors[10, :, 4:-4, 4:-4]
    shifted[0, :, 4:-4, 4:-4] = 0.5 * (inner.roll(1, dims=-1) + inner.roll(2, dims=-1))  # about 1.5 px off
    off = verification_distance(shifted[:1], torch.eye(3)[None], anchors[10:11], blur_sigma=1.0, skip_empty=True)
    assert SHORTLIST_VERIFY_MAX < float(off[0]) <= 0.1
    assert verify_candidates(rec, shifted, 3, 0.1, shortlist=12).verified.tolist() == [False, False]
    rec.query_features = torch.tensor([[9.0], [0.0]])                               # among the features' 3 nearest
    assert verify_candidates(rec, shifted, 3, 0.1, shortlist=12).gallery_index.tolist()[0] == 10


def test_the_share_of_a_crop_its_subject_covers() -> None:
    anchor = textured(60)                                                            # its plane: the inner 24 x 24
    query = anchor.clone()
    assert float(subject_share(query, torch.eye(3)[None], anchor)[0]) == pytest.approx(1.0)
    query[..., :4, :] = 0.5                                                          # a neighbour's 4 x 32 px beside it
    share = float(subject_share(query, torch.eye(3)[None], anchor)[0])
    assert share == pytest.approx(24 * 24 / (24 * 24 + 4 * 32), abs=0.01)
    assert float(subject_share(query, shift(12.0, 0.0), anchor)[0]) < 0.5           # posed half off the subject
    hidden = torch.ones(1, 1, S, S)
    hidden[..., :4, :] = 0.0                                                         # the neighbour masked out
    assert float(subject_share(query, torch.eye(3)[None], anchor, hidden)[0]) == pytest.approx(1.0)
    assert float(subject_share(torch.zeros_like(query), torch.eye(3)[None], anchor)[0]) == 0.0  # nothing shown


def test_shown_pixels_and_the_share_a_plane_covers() -> None:
    queries = torch.zeros(1, 3, 4, 4)
    queries[0, 0, :, :3] = 0.5  # three columns bright, the last one black
    visibility = torch.ones(1, 1, 4, 4)
    visibility[0, 0, 0] = 0.0  # the first row not shown by the mask
    shown = shown_pixels(queries, visibility)
    assert shown.sum() == 9 and not shown[0, 0].any() and not shown[0, :, 3].any()
    assert shown_pixels(queries, None).sum() == 12
    plane = torch.zeros(1, 4, 4, dtype=torch.bool)
    plane[0, :, :1] = True  # one column: 3 of the 9 shown pixels
    assert covered_share(plane, shown).tolist() == pytest.approx([3 / 9])
    assert covered_share(plane, torch.zeros_like(shown)).tolist() == [0.0]

def test_of_several_candidates_that_verify_the_shortlist_keeps_the_closest() -> None:
    anchors = torch.cat([textured(seed) for seed in range(30, 42)])
    anchors[2] = anchors[7]
    anchors[2, :, 4:-4, 4:-4] = anchors[7, :, 4:-4, 4:-4].roll(1, dims=-1)        # product 2: near 7's print
    queries = anchors[7:8].clone()
    queries[0, 0, 0, 0] = 0.0
    rec = StubRecognizer(anchors, list(range(12)), torch.arange(12, dtype=torch.float64)[:, None],
                         torch.tensor([[0.0]]))
    first = verify_candidates(rec, queries, top_k=9, verify_max=0.1)                 # the first that verifies: 2
    closest = verify_candidates(rec, queries, top_k=9, verify_max=0.1, shortlist=12)
    assert first.gallery_index.tolist() == [2] and closest.gallery_index.tolist() == [7]
    assert float(closest.distance[0]) < float(first.distance[0]) <= 0.1


def test_a_given_answer_is_not_changed_in_place_and_candidate_poses_are_used() -> None:
    a, b, c = textured(10), textured(11), textured(12)
    anchors = torch.cat([a, b, c])
    queries = c.clone()
    queries[0, 0, 0, 0] = 0.0
    rec = StubRecognizer(anchors, [0, 1, 2], torch.tensor([[0.0], [1.0], [2.0]]), torch.tensor([[0.1]]))
    first = (torch.tensor([0]), torch.eye(3)[None], torch.tensor([0.1]))
    kept = tuple(t.clone() for t in first)
    v = verify_candidates(rec, queries, 3, 0.1, first=first)
    assert v.gallery_index.tolist() == [2]  # re-ranked to c ...
    assert all(torch.equal(x, y) for x, y in zip(first, kept, strict=True))  # ... the given answer untouched

    # a candidate pose: verified with the first matrix, the answer carries the second
    carried = torch.diag(torch.tensor([1.0, 1.0, 1.0]))
    carried[0, 2] = 5.0
    seen: list[list[int]] = []

    def pose(x: torch.Tensor, index: torch.Tensor, stn_H: torch.Tensor, warped: torch.Tensor,
             visibility: torch.Tensor | None, upscale: torch.Tensor | None):
        seen.append(index.tolist())
        assert visibility is None and upscale is not None and upscale.tolist() == [2.0] * len(index)
        return stn_H, carried.expand_as(stn_H)

    twice = torch.tensor([2.0])  # each query's file enlargement goes to the candidates' poses
    v = verify_candidates(rec, queries, 3, 0.1, first=first, candidate_pose=pose, first_refined=False, upscale=twice)
    assert seen == [[0, 1, 2]]  # the nearest is posed again with the others
    assert v.gallery_index.tolist() == [2] and torch.equal(v.query_H_anchor[0], carried.double())
    seen.clear()
    verify_candidates(rec, queries, 3, 0.1, first=first, candidate_pose=pose, first_refined=True, upscale=twice)
    assert seen == [[1, 2]]


def test_candidates_posed_once_are_taken_from_the_memo() -> None:
    anchors = torch.cat([textured(seed) for seed in range(30, 36)])                 # 6 products, one anchor each
    queries = torch.cat([anchors[4:5].clone(), textured(50)])                        # product 4; one unlike any
    queries[0, 0, 0, 0], queries[1, 0, 0, 0] = 0.0, 1.0
    rec = StubRecognizer(anchors, list(range(6)), torch.arange(6, dtype=torch.float64)[:, None],
                         torch.tensor([[0.0], [0.0]]))
    posed: list[list[int]] = []

    def pose(x: torch.Tensor, index: torch.Tensor, stn_H: torch.Tensor, warped: torch.Tensor,
             visibility: torch.Tensor | None, upscale: torch.Tensor | None):
        posed.append(index.tolist())
        return stn_H, stn_H

    first = (torch.tensor([0, 0]), torch.eye(3).repeat(2, 1, 1), torch.tensor([0.0, 0.0]))
    plain = verify_candidates(rec, queries, 5, 0.1, first=first, candidate_pose=pose)
    assert posed == [[1, 2, 3, 4, 1, 2, 3, 4]]
    memo = CandidateMemo()
    keys = [7, 9]                                                                   # the queries' rows elsewhere
    posed.clear()
    once = verify_candidates(rec, queries, 5, 0.1, first=first, candidate_pose=pose, memo=memo, keys=keys)
    assert posed == [[1, 2, 3, 4, 1, 2, 3, 4]] and len(memo) == 8
    posed.clear()
    again = verify_candidates(rec, queries, 5, 0.1, first=first, candidate_pose=pose, memo=memo, keys=keys)
    assert posed == []                                                               # every pair from the memo
    # a rival's search without product 4 meets the same anchors but 4, and one more: only that one is posed
    posed.clear()
    without = verify_candidates(rec, queries, 6, 0.1, first=first, candidate_pose=pose,
                                exclude_object=torch.tensor([4, 4]), memo=memo, keys=keys)
    assert posed == [[5, 5]] and without.verified.tolist() == [False, False]
    for v in (once, again):
        for name in ("gallery_index", "query_H_anchor", "distance", "verified", "tried"):
            assert torch.equal(getattr(v, name), getattr(plain, name))
    assert plain.gallery_index.tolist() == [4, 0] and plain.verified.tolist() == [True, False]
    # the STN poses, warps and distances given (computed once by the caller) answer as computed here
    _, stn_H, warped, d = candidate_distances(rec, queries, None)
    given = verify_candidates(rec, queries, 5, 0.1, first=first, candidate_pose=pose, embedded=(stn_H, warped, d))
    assert torch.equal(given.gallery_index, plain.gallery_index) and torch.equal(given.distance, plain.distance)
    excluded = verify_candidates(rec, queries, 5, 0.1, exclude_object=torch.tensor([4, 4]), embedded=(stn_H, warped, d))
    assert excluded.verified.tolist() == [False, False]
    with pytest.raises(ValueError, match="one key per query"):
        verify_candidates(rec, queries, 5, 0.1, first=first, memo=CandidateMemo(), keys=[1])
    # the verified poses of pairs: from the memo where it has them, the rest posed and added
    fresh = CandidateMemo()
    fresh.put(3, 1, 2 * torch.eye(3), torch.eye(3))
    got = memo_poses(fresh, [3, 3], torch.tensor([1, 2]), torch.zeros(2, 3, 3),
                     lambda pairs: (torch.eye(3).repeat(len(pairs), 1, 1), torch.eye(3).repeat(len(pairs), 1, 1)))
    assert torch.equal(got[0], 2 * torch.eye(3)) and torch.equal(got[1], torch.eye(3)) and len(fresh) == 2


def test_a_pose_that_puts_the_plane_over_no_query_data_is_not_compared() -> None:
    anchor = textured(1).float()
    query = anchor.clone()
    query[..., :, S // 3:] = 0.0  # RGBA query whose alpha keeps a third of the plane: the rest is no data
    full = verification_distance(query, torch.eye(3)[None], anchor, blur_sigma=0.0, skip_empty=True, min_coverage=0.0)
    assert float(full[0]) == pytest.approx(0.0, abs=1e-6)  # the third that is there matches exactly ...
    covered = verification_distance(query, torch.eye(3)[None], anchor, blur_sigma=0.0, skip_empty=True)
    assert float(covered[0]) == 1.0  # ... but covers less than half the plane: not a verification


def test_patch_distances_by_hand() -> None:
    """A 2 x 2 grid of 4 x 4 px patches: each patch is ZNCC'd on its own, flat or hidden patches are not usable."""
    g = torch.Generator().manual_seed(0)
    a = torch.rand(1, 2, 8, 8, generator=g, dtype=torch.float64)
    b = 3.0 * a + 0.5                                      # top left: b explains a up to gain and bias
    b[..., :4, 4:] = torch.rand(1, 2, 4, 4, generator=g, dtype=torch.float64)  # top right: unrelated
    a[..., 4:, :4] = 0.4                                   # bottom left: the anchor is flat there
    weight = torch.ones(1, 1, 8, 8, dtype=torch.float64)
    weight[..., 4:, 4:] = 0.0
    weight[..., 4:, 4:6] = 1.0                             # bottom right: half of it visible (8 of 16 pixels)
    d = patch_distances(a, b, weight, cells=2, fill=0.6, texture=0.02)
    assert float(d[0, 0]) == pytest.approx(0.0, abs=1e-12)
    expected = 1.0 - float(zncc(a[..., :4, 4:], b[..., :4, 4:], torch.ones(1, 1, 4, 4, dtype=torch.bool))[0])
    assert float(d[0, 1]) == pytest.approx(expected, abs=1e-12)
    assert math.isnan(float(d[0, 2])) and math.isnan(float(d[0, 3]))  # flat anchor; too little visible (0.5 < 0.6)
    assert float(patch_distances(a, b, weight, cells=2, fill=0.5)[0, 3]) == pytest.approx(0.0, abs=1e-12)
    # a flat query patch over a textured anchor explains nothing: 1 - 0
    flat = b.clone()
    flat[..., :4, :4] = 0.3
    assert float(patch_distances(a, flat, weight, cells=2)[0, 0]) == 1.0
    # a soft weight is the weighted correlation: sum w a' b' / sqrt(sum w a'^2 sum w b'^2), means weighted per channel
    soft = torch.rand(1, 1, 8, 8, generator=g, dtype=torch.float64) * 0.5 + 0.5
    w = soft.numpy()[0, 0]
    da = [x - (w * x).sum() / w.sum() for x in a.numpy()[0]]
    db = [x - (w * x).sum() / w.sum() for x in b.numpy()[0]]
    num = sum((w * x * y).sum() for x, y in zip(da, db, strict=True))
    den = math.sqrt(sum((w * x * x).sum() for x in da) * sum((w * y * y).sum() for y in db))
    assert float(patch_distances(a, b, soft, cells=1)[0, 0]) == pytest.approx(1.0 - num / den, abs=1e-12)


def occluded(anchor: torch.Tensor, start: int, stop: int, fill: torch.Tensor | float) -> torch.Tensor:
    """``anchor`` with the columns ``start:stop`` replaced by ``fill`` (a bar across the plane)."""
    query = anchor.clone()
    query[..., :, start:stop] = fill if isinstance(fill, float) else fill[..., :, start:stop]
    return query


def test_an_occluded_query_whose_visible_part_matches_verifies_and_a_wrong_product_does_not() -> None:
    anchor = textured(1, 64).float()
    other = textured(5, 64).float()
    pose = torch.eye(3)[None]
    # another product's print across a third of the plane, left in the query (a mask that missed the occluder)
    query = occluded(anchor, 24, 40, other)
    whole = verification_distance(query, pose, anchor, statistic="global")
    visible = verification_distance(query, pose, anchor, statistic="patches")
    assert float(whole[0]) > 0.1 >= float(visible[0])  # the whole plane fails, the visible part verifies
    assert float(visible[0]) < 0.5 * float(whole[0])
    # the bar cut out by the mask (0 there and out of the visibility): verifies too
    cut = occluded(anchor, 24, 40, 0.0)
    mask = torch.ones(1, 1, 64, 64)
    mask[..., :, 24:40] = 0.0
    assert float(verification_distance(cut, pose, anchor, visibility=mask, statistic="patches", skip_empty=True)[0]) \
        < 0.02
    # another product under a third one's bar verifies neither way
    wrong = occluded(other, 24, 40, textured(7, 64).float())
    assert float(verification_distance(wrong, pose, anchor, statistic="patches")[0]) > 0.5
    assert float(verification_distance(other, pose, anchor, statistic="patches")[0]) > 0.5
    assert float(verification_distance(query[:0], pose[:0], anchor[:0], statistic="patches").shape[0]) == 0
    with pytest.raises(ValueError, match="statistic"):
        verification_distance(query, pose, anchor, statistic="median")


def test_too_little_visible_is_not_a_verification() -> None:
    anchor = textured(1, 64).float()
    pose = torch.eye(3)[None]
    plane = anchor_foreground(anchor, 1)
    mask = torch.zeros(1, 1, 64, 64)
    mask[..., :, :23] = 1.0  # 18 of the (eroded) plane's 54 columns (5 to 58) visible: a third
    share = float((plane.float() * mask).sum() / plane.sum())
    assert 0.3 < share < 0.35
    query = anchor * mask
    args = {"visibility": mask, "statistic": "patches", "skip_empty": True}
    assert float(verification_distance(query, pose, anchor, min_visible=0.3, **args)[0]) < 0.02
    assert float(verification_distance(query, pose, anchor, min_visible=0.4, **args)[0]) == 1.0
    # a soft visibility counts by its value: half of everything visible is a share of a half
    half = torch.full((1, 1, 64, 64), 0.5)
    assert float(verification_distance(anchor, pose, anchor, visibility=half, statistic="patches",
                                       min_visible=0.45)[0]) < 0.02
    assert float(verification_distance(anchor, pose, anchor, visibility=half, statistic="patches",
                                       min_visible=0.55)[0]) == 1.0
    # too few usable patches (a narrow strip shows two of an 8 x 8 grid of 8 px): the visible plane's ZNCC alone
    strip = torch.zeros(1, 1, 64, 64)
    strip[..., 24:32, 16:32] = 1.0
    assert PATCH_CELLS == 8 and MIN_PATCHES > 2
    other = textured(5, 64).float()
    mixed = other.clone()
    mixed[..., 20:36, 12:36] = anchor[..., 20:36, 12:36]  # the anchor's print under the strip and 4 px around it
    args = {"visibility": strip, "statistic": "patches", "min_visible": 0.0}
    assert float(verification_distance(mixed, pose, anchor, **args)[0]) < 0.02
    seen = anchor_foreground(anchor, 1).float() * strip
    whole = 1.0 - float(weighted_zncc(gaussian_blur(other, 1.0), gaussian_blur(anchor, 1.0), seen)[0])
    assert float(verification_distance(other, pose, anchor, **args)[0]) == pytest.approx(whole, abs=1e-6)
    # a strip of MIN_PATCHES usable patches is judged by them: the anchor's print under half of it, another's under
    # the rest (an occluder the mask missed) fails the strip's whole ZNCC and passes the patches' best half
    assert MIN_PATCHES == 4
    strip = torch.zeros(1, 1, 64, 64)
    strip[..., 24:32, 16:48] = 1.0
    half_hidden = other.clone()
    half_hidden[..., 20:36, 12:35] = anchor[..., 20:36, 12:35]  # 3 px past the patch: the blur
    seen = anchor_foreground(anchor, 1).float() * strip
    whole = 1.0 - float(weighted_zncc(gaussian_blur(half_hidden, 1.0), gaussian_blur(anchor, 1.0), seen)[0])
    four = {**args, "visibility": strip}
    assert whole > 0.1 > 0.02 > float(verification_distance(half_hidden, pose, anchor, **four)[0])


def test_weighted_zncc_is_zncc_with_a_binary_weight() -> None:
    g = torch.Generator().manual_seed(3)
    a, b = torch.rand(2, 3, 20, 20, generator=g), torch.rand(2, 3, 20, 20, generator=g)
    b[1] = 0.5 * a[1] + 0.2 * b[1]
    mask = torch.rand(2, 1, 20, 20, generator=g) > 0.4
    assert torch.allclose(weighted_zncc(a, b, mask.float()), zncc(a, b, mask), atol=1e-9)
    few = torch.zeros(2, 1, 20, 20)
    few[..., 0, :MIN_PIXELS - 1] = 1.0
    assert weighted_zncc(a, b, few).tolist() == [0.0, 0.0]  # fewer than MIN_PIXELS: not compared


def test_the_cpu_fast_path_equals_the_torch_reference() -> None:
    """The CPU path (OpenCV blur and erosion, one compiled pass for the patches' and the whole plane's sums) gives
    the torch path's answers (the GPU's) up to float rounding."""
    from matl.inference.verify import (
        PATCH_KEEP,
        PATCH_STRICTNESS,
        _anchor_foreground_torch,
        _cell_sums,
        _correlations,
        _gaussian_blur_torch,
        _patch_distances,
        _trimmed,
        _weighted_zncc,
    )

    def reference(queries: torch.Tensor, pose: torch.Tensor, anchors: torch.Tensor, visibility: torch.Tensor
                  ) -> torch.Tensor:  # verification_distance's "patches" in torch alone
        warped, valid, seen = aligned_queries(queries, pose, True, visibility)
        plane = _anchor_foreground_torch(anchors, 1)
        weight = (plane & valid).float() * seen
        enough = weight.sum((1, 2, 3)) >= 0.3 * plane.sum((1, 2, 3)).clamp_min(1)
        warped, anchors = _gaussian_blur_torch(torch.cat([warped, anchors]), 1.0).split(len(anchors))
        whole = 1.0 - _weighted_zncc(*_correlations(*_cell_sums(warped, anchors, weight, 1, torch_only=True)[:2]))
        count, sums, area = _cell_sums(anchors, warped, weight, PATCH_CELLS, torch_only=True)
        robust = _trimmed(_patch_distances(*_correlations(count, sums), area, 3), PATCH_KEEP, MIN_PATCHES)
        return torch.where(enough, torch.minimum(whole, robust * PATCH_STRICTNESS), torch.ones_like(whole))

    g = torch.Generator().manual_seed(7)
    anchors = torch.cat([textured(seed, 60).float() for seed in range(4)])
    queries = (0.8 * anchors.roll(1, 0).clone() + 0.2 * anchors).clamp(0, 1)
    queries[0] = anchors[0] * 1.1 + 0.05
    queries[1, :, 10:25, 5:30] = 0.0  # empty query pixels
    visibility = torch.nn.functional.interpolate(torch.rand(4, 1, 4, 4, generator=g), size=(60, 60), mode="bilinear")
    pose = torch.cat([shift(float(dx), float(dy)) for dx, dy in torch.randn(4, 2, generator=g)])
    pose[:, 2, :2] = 1e-4 * torch.randn(4, 2, generator=g)
    args = {"skip_empty": True, "visibility": visibility, "statistic": "patches"}
    assert torch.allclose(verification_distance(queries, pose, anchors, **args),
                          reference(queries, pose, anchors, visibility), rtol=0.0, atol=1e-6)
    images = torch.rand(3, 3, 40, 30, generator=g)
    for sigma in (0.7, 1.0, 2.0):
        assert torch.allclose(gaussian_blur(images, sigma), _gaussian_blur_torch(images, sigma), rtol=0.0, atol=1e-6)
    holes = anchors * (torch.rand(4, 1, 60, 60, generator=g) > 0.05)
    for erode in (0, 1, 2):
        assert torch.equal(anchor_foreground(holes, erode), _anchor_foreground_torch(holes, erode))
    weight = visibility * (torch.rand(4, 1, 60, 60, generator=g) > 0.2)
    for cells in (1, 3, PATCH_CELLS):
        fast, slow = _cell_sums(queries, anchors, weight, cells), _cell_sums(queries, anchors, weight, cells, True)
        assert fast[2] == slow[2]
        assert torch.allclose(fast[0], slow[0], rtol=1e-12, atol=1e-12)
        assert torch.allclose(fast[1], slow[1], rtol=1e-12, atol=1e-12)


def test_look_alikes_are_told_apart_where_they_differ() -> None:
    """Two anchors alike but for a band (another flavour's text): the query, one of them under a gain and bias and
    noise all over its plane, is explained better by its own anchor, whichever of the pair comes first; a pair that
    does not differ where the crop shows is NaN (nothing to tell them apart by)."""
    anchor = textured(1, 64).float()
    twin = anchor.clone()
    twin[..., 28:36, 8:56] = twin[..., 28:36, 8:56].flip(-1)  # the band mirrored
    noise = 0.03 * torch.randn(1, 3, 64, 64, generator=torch.Generator().manual_seed(0))
    query = torch.where(anchor > 0, 0.7 * anchor + 0.05 + noise, torch.zeros_like(anchor)).clamp(0, 1)
    pose = shift(0.0, 0.0)
    pair, overlap = difference_distances(query, torch.stack([pose, pose], 1), torch.stack([anchor, twin], 1))
    swapped, _ = difference_distances(query, torch.stack([pose, pose], 1), torch.stack([twin, anchor], 1))
    assert float(overlap[0]) == 1.0
    assert float(pair[0, 0]) < 0.2 * float(pair[0, 1])
    assert pair.flip(1)[0].tolist() == pytest.approx(swapped[0].tolist())
    # the whole plane's ZNCC tells the two apart far less: the band is an eighth of the plane, under the noise
    whole = verification_distance(query.repeat(2, 1, 1, 1), pose.repeat(2, 1, 1), torch.cat([anchor, twin]))
    assert float(whole[0] / whole[1]) > 5 * float(pair[0, 0] / pair[0, 1])
    # each anchor under its own pose: the same anchor 2 px off explains the query worse (the pixels where the two
    # poses differ are its edges)
    slid, overlap = difference_distances(query, torch.stack([pose, shift(2.0, 0.0)], 1),
                                         torch.stack([anchor, anchor], 1))
    assert float(slid[0, 0]) < 0.2 * float(slid[0, 1])
    # the planes' overlap in the crop says whether the two lie on one place (look-alikes) or elsewhere: the planes
    # (54 px wide once eroded) 2 px apart overlap by 52 / 56; 12 px apart by 42 / 59 (the shifted one leaves the crop
    # by 7 px), below DIFFERENCE_OVERLAP
    assert float(overlap[0]) == pytest.approx(52 / 56, abs=0.01) and float(overlap[0]) >= DIFFERENCE_OVERLAP
    _, far = difference_distances(query, torch.stack([pose, shift(12.0, 0.0)], 1), torch.stack([anchor, twin], 1))
    assert float(far[0]) == pytest.approx(42 / 59, abs=0.01) and float(far[0]) < DIFFERENCE_OVERLAP
    # the band hidden (the visibility leaves it out): the two do not differ on what the crop shows
    seen = torch.ones(1, 1, 64, 64)
    seen[..., 24:40, :] = 0.0
    hidden, _ = difference_distances(query, torch.stack([pose, pose], 1), torch.stack([anchor, twin], 1), seen)
    assert bool(hidden.isnan().all())
    empty = difference_distances(query[:0], torch.zeros(0, 2, 3, 3), torch.zeros(0, 2, 3, 64, 64))
    assert empty[0].shape == (0, 2) and empty[1].shape == (0,)
    with pytest.raises(ValueError, match="two poses and two anchors"):
        difference_distances(query, pose, torch.stack([anchor, twin], 1))


def test_explained_distance_judges_poses_over_the_query_s_own_pixels() -> None:
    anchor = textured(1, 64).float()
    # the query: the anchor's plane under a gain and bias, shifted by (2, -1) px; query_H_anchor maps anchor -> query
    query = torch.zeros_like(anchor)
    query[..., :63, 2:] = torch.where(anchor > 0, 0.6 * anchor + 0.1, anchor)[..., 1:, :-2]
    true, off = shift(2.0, -1.0), shift(0.0, 0.0)
    assert float(explained_distance(query, true, anchor)[0]) == pytest.approx(0.0, abs=1e-6)
    assert float(explained_distance(query, off, anchor)[0]) > 0.05
    # a pose that slides the plane half out of the query leaves half of the query's foreground unexplained: those
    # cells cost 1 each, where the anchor frame's comparison only sees the half that still overlaps
    half = shift(34.0, -1.0)
    assert float(explained_distance(query, half, anchor)[0]) > 0.4
    # an occluder the mask marks hidden is no pixel of the judge: the true pose stays exact
    hidden = occluded(query, 24, 40, textured(5, 64).float())
    mask = (query.amax(1, keepdim=True) > 0).float()  # the query's product ...
    mask[..., :, 24:40] = 0.0                         # ... less the bar
    assert float(explained_distance(hidden, true, anchor, mask)[0]) == pytest.approx(0.0, abs=1e-6)
    # kept in the visibility it costs both poses, and the true one still explains the query better
    kept = explained_distance(hidden.repeat(2, 1, 1, 1), torch.cat([true, off]), anchor.repeat(2, 1, 1, 1))
    assert 0.05 < float(kept[0]) < float(kept[1])
    # nothing visible: no cell counts; no query: nothing to judge
    assert float(explained_distance(query, true, anchor, torch.zeros(1, 1, 64, 64))[0]) == 1.0
    assert explained_distance(query[:0], true[:0], anchor[:0]).shape == (0,)


def test_the_print_beside_what_hides_it_is_left_out_in_the_second_look() -> None:
    """An occluder's drop shadow darkens the visible print along its edge, deeper nearer it (no gain per patch explains
    it), and the blur mixes the hidden side into that edge: ``occluder_margin`` px along the edges of what hides the
    plane are left out; the plane's own edge is not one. 0 (the default): everything visible counts."""
    anchor = textured(1, 64).float()
    pose = torch.eye(3)[None]
    mask = torch.zeros(1, 1, 64, 64)
    mask[..., :, 16:40] = 1.0  # hidden left of column 16 and from column 40 on
    query = anchor * mask
    shadowed = query.clone()
    shadowed[..., :, 34:40] *= torch.linspace(1.0, 0.4, 6)
    args = {"visibility": mask, "statistic": "patches", "skip_empty": True}
    assert float(verification_distance(shadowed, pose, anchor, **args)[0]) > 0.3
    assert float(verification_distance(shadowed, pose, anchor, occluder_margin=3, **args)[0]) < 0.01
    assert float(verification_distance(query, pose, anchor, **args)[0]) > 0.05  # the blur alone
    assert float(verification_distance(query, pose, anchor, occluder_margin=3, **args)[0]) < 0.01
    # the erosion: from the hidden columns inward, not from the plane's own edge (rows 5-58 of the eroded plane)
    plane = anchor_foreground(anchor, 1)
    kept = away_from_hidden(mask, plane, 3)
    assert torch.equal(kept[0, 0, 32, 16:40] > 0, torch.arange(16, 40).ge(19) & torch.arange(16, 40).lt(37))
    assert bool((kept[0, 0, 5:59, 19:37] == 1.0).all())
    whole = torch.ones(1, 1, 64, 64)
    assert torch.equal(away_from_hidden(whole, plane, 3), whole)


def test_the_hidden_share_of_a_plane() -> None:
    """What the query does not show of the anchor's plane: under its mask's hidden part, outside the query, on its
    empty pixels; nothing of a whole plane."""
    anchor = textured(1, 64).float()
    pose = torch.eye(3)[None]
    plane = anchor_foreground(anchor, 1)
    assert float(hidden_share(anchor, pose, anchor)[0]) == 0.0
    mask = torch.ones(1, 1, 64, 64)
    mask[..., :, 40:] = 0.0
    expected = float((plane[..., :, 40:]).sum() / plane.sum())
    assert float(hidden_share(anchor, pose, anchor, mask)[0]) == pytest.approx(expected)
    empty = anchor.clone()
    empty[..., :, 40:] = 0.0  # transparent: no data
    assert float(hidden_share(empty, pose, anchor)[0]) == pytest.approx(expected)
    shifted = torch.tensor([[[1.0, 0.0, 24.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]])  # anchor x -> query x + 24
    grey = torch.full_like(anchor, 0.5)  # shows something everywhere: what falls outside it is hidden
    assert float(hidden_share(grey, shifted, anchor)[0]) == pytest.approx(expected, abs=0.02)
