"""Photometric verification: hand-computed ZNCC, ``1 - ZNCC`` of posed queries, candidates tried in order."""

from __future__ import annotations

import math
from types import SimpleNamespace

import pytest
import torch

from matl.inference.verify import (
    MIN_PIXELS,
    aligned_queries,
    anchor_foreground,
    verification_distance,
    verify_candidates,
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
    warped, valid = aligned_queries(anchor.float(), shift(3.0, 0.0))  # query = anchor shifted right by 3 px
    assert not bool(valid[0, 0, :, -3:].any()) and bool(valid[0, 0, :, :-3].all())
    assert torch.allclose(warped[0, :, :, :-3], anchor[0, :, :, 3:].float(), atol=1e-5)


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
        self.gallery = SimpleNamespace(images=anchors, object_index=torch.tensor(objects))
        self.gallery_features, self.query_features, self.align = gallery_features, query_features, None

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

    def pose(x: torch.Tensor, index: torch.Tensor, stn_H: torch.Tensor, warped: torch.Tensor):
        seen.append(index.tolist())
        return stn_H, carried.expand_as(stn_H)

    v = verify_candidates(rec, queries, 3, 0.1, first=first, candidate_pose=pose, first_refined=False)
    assert seen == [[0, 1, 2]]  # the nearest is posed again with the others
    assert v.gallery_index.tolist() == [2] and torch.equal(v.query_H_anchor[0], carried.double())
    seen.clear()
    verify_candidates(rec, queries, 3, 0.1, first=first, candidate_pose=pose, first_refined=True)
    assert seen == [[1, 2]]


def test_a_pose_that_puts_the_plane_over_no_query_data_is_not_compared() -> None:
    anchor = textured(1).float()
    query = anchor.clone()
    query[..., :, S // 3:] = 0.0  # RGBA query whose alpha keeps a third of the plane: the rest is no data
    full = verification_distance(query, torch.eye(3)[None], anchor, blur_sigma=0.0, skip_empty=True, min_coverage=0.0)
    assert float(full[0]) == pytest.approx(0.0, abs=1e-6)  # the third that is there matches exactly ...
    covered = verification_distance(query, torch.eye(3)[None], anchor, blur_sigma=0.0, skip_empty=True)
    assert float(covered[0]) == 1.0  # ... but covers less than half the plane: not a verification
