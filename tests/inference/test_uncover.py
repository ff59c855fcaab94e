"""``uncover``: a product lying across the one a crop was cut for is explained away and the rest answered again."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from matl import Recognizer
from matl.data.image_files import fit_geometry
from matl.geometry import corner_error_px
from matl.inference.files import record_of
from matl.inference.query_passes import QueryPasses
from matl.inference.uncover import (
    MIN_OVERLAP,
    centre_offset,
    erased_alpha,
    lies_on_top,
)
from matl.inference.verify import Verification
from matl.utils.errors import MatlError
from tests.inference.test_api import SIZE, StubModel, stub_recognizer
from tests.inference.test_keypoint_pose import GALLERY_HW, print_like
from tests.predict_helpers import write_png

#: where the product lies in the crop file (rows, columns of black around it)
MARGIN = 20
#: the card lying across the box covers its print's columns up to here (40 % of them)
CARD_COLUMNS = 64


def test_a_plane_is_erased_in_the_files_pixels() -> None:
    alpha = np.ones((20, 20), np.float32)
    plane = np.zeros((10, 10), bool)
    plane[:, :5] = True  # the left half of the model frame
    model_H_file = np.diag([0.5, 0.5, 1.0])  # the file at twice the model's size
    kept = erased_alpha(alpha, plane, model_H_file, grow=0)[:18]  # file row 19 maps past the model frame's last row
    assert kept[:, :9].max() == 0.0 and kept[:, 10:].min() == 1.0
    grown = erased_alpha(alpha, plane, model_H_file, grow=2)[:18]
    assert grown[:, :11].max() == 0.0 and grown[:, 12:].min() == 1.0


def test_how_far_a_plane_lies_from_the_crops_centre() -> None:
    plane = np.zeros((11, 11), bool)
    plane[4:7, 4:7] = True  # centred on pixel (5, 5), the frame's centre
    assert centre_offset(plane, np.eye(3), 11) == 0.0
    shift = np.array([[1.0, 0.0, 3.0], [0.0, 1.0, 4.0], [0.0, 0.0, 1.0]])
    assert centre_offset(plane, shift, 11) == pytest.approx(5.0 / 11)  # moved by (3, 4): 5 px of 11
    assert centre_offset(np.zeros((11, 11), bool), np.eye(3), 11) == float("inf")


def test_the_print_that_shows_is_on_top() -> None:
    rng = np.random.default_rng(0)
    top, under = (torch.from_numpy(rng.uniform(0, 1, (3, 12, 12)).astype(np.float32)) for _ in range(2))
    overlap = torch.zeros(12, 12, dtype=torch.bool)
    overlap[2:10, 2:10] = True
    query = torch.where(overlap, top, under)  # the first print shows where both lie
    assert lies_on_top(query, top, under, overlap) is True
    assert lies_on_top(query, under, top, overlap) is False
    few = torch.zeros_like(overlap)
    few.view(-1)[:MIN_OVERLAP - 1] = True
    assert lies_on_top(query, top, under, few) is None


def card_across_a_box(root: Path) -> tuple[Path, np.ndarray, np.ndarray, torch.Tensor]:
    """A gallery of a box (a red print) and a card (a blue print on 40 % of its frame, black elsewhere), and a crop on
    black of the box with the card lying across it, the same crop of the card alone, and the model-frame pose of both
    products at that crop."""
    box, card = print_like(0, (0.8, 0.2, 0.1)), print_like(1, (0.1, 0.2, 0.8))
    card[:, CARD_COLUMNS:] = 0.0
    write_png(root / "red_box" / "front.png", box)
    write_png(root / "blue_card" / "front.png", card)
    h, w = GALLERY_HW
    crop = np.zeros((h + 2 * MARGIN, w + 2 * MARGIN, 3), np.float32)
    alone = crop.copy()
    alone[MARGIN:MARGIN + h, MARGIN:MARGIN + CARD_COLUMNS] = card[:, :CARD_COLUMNS]
    crop[MARGIN:MARGIN + h, MARGIN:MARGIN + w] = box
    crop[MARGIN:MARGIN + h, MARGIN:MARGIN + CARD_COLUMNS] = card[:, :CARD_COLUMNS]
    shift = torch.tensor([[1.0, 0.0, MARGIN], [0.0, 1.0, MARGIN], [0.0, 0.0, 1.0]], dtype=torch.float64)
    pose = fit_geometry(*crop.shape[:2], SIZE).model_H_file @ shift @ torch.linalg.inv(
        fit_geometry(h, w, SIZE).model_H_file)
    return root, *((x * 255).round().astype(np.uint8) for x in (crop, alone)), pose


def test_a_card_lying_across_the_box_is_explained_away(tmp_path: Path) -> None:
    """``c()`` the mean colour (the card's blue makes it nearest), ``s()`` the pose both share: the card
    verifies but covers 60 % of what the crop shows, and its print shows where the two overlap; with its plane
    erased the rest is the box, which verifies on what is left and covers the whole crop."""
    gallery, crop, alone, pose = card_across_a_box(tmp_path)

    def recognizer(**options) -> Recognizer:
        rec = Recognizer(StubModel(pose), SIZE, 1, "stub-model", threshold=None, flow_pose="none", **options)
        return rec.enrol(gallery, cache=False)

    def answer(**options) -> tuple[str | None, bool, float]:
        match = recognizer(**options).predict(crop)
        return match.object, match.known, match.verification

    card, _, card_distance = answer(uncover=None)
    assert card == "blue_card" and card_distance <= 0.1  # the card lying on top: whole, it verifies
    box, known, box_distance = answer()  # uncover=0.7, the default
    assert box == "red_box" and known and box_distance <= 0.1
    # the card is not lost: the answer says what lies across it, posed in the crop's pixels (a shift by MARGIN)
    match = recognizer().predict(crop)
    top = match.covered_by
    assert top is not None and top.object == "blue_card" and top.known and top.verification <= 0.1
    true_H = np.array([[1.0, 0.0, MARGIN], [0.0, 1.0, MARGIN], [0.0, 0.0, 1.0]])
    assert float(corner_error_px(torch.from_numpy(top.H)[None], torch.from_numpy(true_H)[None], GALLERY_HW)) < 1.0
    record = record_of(Path("crop.png"), match)
    assert record["covered_by"]["object"] == "blue_card" and np.allclose(record["covered_by"]["H"], top.H)
    assert recognizer(uncover=None).predict(crop).covered_by is None
    assert record_of(Path("crop.png"), recognizer(uncover=None).predict(crop))["covered_by"] is None
    assert answer(uncover=0.5)[0] == "blue_card"  # the card covers just over half the crop: the answer stands
    # in a batch, beside crops of the card alone (which cover what they show: not answered again), each row keeps
    # its own answer
    assert [m.object for m in recognizer().predict([alone, crop, alone])] == ["blue_card", "red_box", "blue_card"]


def test_uncover_must_be_a_share() -> None:
    for bad in (0.0, 1.5, "half", float("nan")):
        with pytest.raises(MatlError, match=r"uncover=.* is invalid: use a share of the crop in \(0, 1\]"):
            stub_recognizer(uncover=bad)
    assert stub_recognizer(uncover=None).uncover is None and stub_recognizer(uncover=1).uncover == 1.0


def test_a_held_answer_that_covers_the_crop_is_its_subject() -> None:
    """An answer whose pose verifies with a margin but is held unverified (another product's keypoint pose, which
    might lie across the crop's subject) counts as verified where the crop has a mask and the answer's plane covers at
    least ``uncover`` of what the crop shows; one covering a quarter of it, one whose pose does not verify or verifies
    without the margin, and one of a crop without a mask stay as they were."""
    S = 32
    whole = torch.full((3, S, S), 200, dtype=torch.uint8)
    quarter = torch.zeros((3, S, S), dtype=torch.uint8)
    quarter[:, :, : S // 4] = 200

    class Passes(QueryPasses):
        verify_max, uncover, image_size, query_fill = 0.1, 0.7, S, 1.0
        foreground = None
        _planes = (SimpleNamespace(canon_u8=whole), SimpleNamespace(canon_u8=quarter))

    queries = torch.full((4, 3, S, S), 0.5)
    pred = SimpleNamespace(plane_index=torch.tensor([0, 1, 0, 0]),
                           query_H_canon=torch.eye(3, dtype=torch.float64).repeat(4, 1, 1))
    held = Verification(gallery_index=torch.zeros(4, dtype=torch.long), query_H_anchor=torch.eye(3).repeat(4, 1, 1),
                        feature_distance=torch.zeros(4), distance=torch.tensor([0.04, 0.04, 0.5, 0.02]),
                        verified=torch.tensor([False, False, False, True]), tried=torch.ones(4, dtype=torch.long))
    rgb = np.zeros((S, S, 3), np.float32)
    prepared = [(rgb, rgb, np.ones((S, S), np.float32))] * 4  # RGB crops masked by the foreground step
    out = Passes()._subjects_verified(prepared, pred, queries, held, None)
    assert out.verified.tolist() == [True, False, False, True]
    assert torch.equal(out.distance, held.distance) and not held.verified[0]  # the input is left as it was
    # verified with too little margin (SUBJECT_MARGIN of verify_max): held
    at_margin = dataclasses.replace(held, distance=torch.tensor([0.06, 0.04, 0.5, 0.02]))
    assert not Passes()._subjects_verified(prepared, pred, queries, at_margin, None).verified[0]
    # a crop without a mask stays the open-set statistic's to judge
    assert not Passes()._subjects_verified([(rgb, rgb, None)] * 4, pred, queries, held, None).verified[0]
    # what the crop shows is the plane's quarter alone (the rest not visible): that plane is its subject
    visibility = torch.ones(4, 1, S, S)
    visibility[1, :, :, S // 4:] = 0.0
    assert Passes()._subjects_verified(prepared, pred, queries, held, visibility).verified.tolist() == [
        True, True, False, True]


def test_the_second_look_is_for_the_crop_s_subject() -> None:
    """``verify_occluder_margin``'s second look (:meth:`QueryPasses._second_look`) is asked of the answers that do not
    verify, of crops with a mask, whose plane covers at least ``uncover`` of what the crop shows (not of a product
    lying across a part of it), within ``verify_max``, or within ``SUBJECT_MARGIN`` of it for an answer held although
    its distance is within ``verify_max``."""
    S = 32
    whole = torch.full((3, S, S), 200, dtype=torch.uint8)
    quarter = torch.zeros((3, S, S), dtype=torch.uint8)
    quarter[:, :, : S // 4] = 200
    asked = []

    class Passes(QueryPasses):
        verify_max, uncover, image_size, query_fill, verify_occluder_margin = 0.1, 0.7, S, 1.0, 3
        foreground = None
        _planes = (SimpleNamespace(canon_u8=whole), SimpleNamespace(canon_u8=quarter))

        def _verified_past_occluders(self, queries, gallery_index, query_H_anchor, verification, visibility,
                                     rows=None, within=None):
            asked.append((rows, within))
            return verification

    queries = torch.full((4, 3, S, S), 0.5)
    pred = SimpleNamespace(plane_index=torch.tensor([0, 1, 0, 0]), gallery_index=torch.zeros(4, dtype=torch.long),
                           query_H_canon=torch.eye(3, dtype=torch.float64).repeat(4, 1, 1),
                           query_H_anchor=torch.eye(3, dtype=torch.float64).repeat(4, 1, 1))
    verification = Verification(gallery_index=torch.zeros(4, dtype=torch.long),
                                query_H_anchor=torch.eye(3).repeat(4, 1, 1), feature_distance=torch.zeros(4),
                                distance=torch.tensor([0.3, 0.3, 0.08, 0.02], dtype=torch.float64),
                                verified=torch.tensor([False, False, False, True]),
                                tried=torch.ones(4, dtype=torch.long))
    rgb = np.zeros((S, S, 3), np.float32)
    prepared = [(rgb, rgb, np.ones((S, S), np.float32))] * 4  # RGB crops masked by the foreground step
    visibility = torch.ones(4, 1, S, S)
    Passes()._second_look(prepared, pred, queries, verification, visibility)
    assert asked[-1][0] == [0, 2] and asked[-1][1] == pytest.approx([0.1, 0.05])
    asked.clear()
    Passes()._second_look([(rgb, rgb, None)] * 4, pred, queries, verification, visibility)  # no mask: not asked
    Passes()._second_look(prepared, pred, queries, verification, None)  # nothing hidden: not asked
    off = Passes()
    off.verify_occluder_margin = 0
    assert off._second_look(prepared, pred, queries, verification, visibility) is verification
    assert asked == []
