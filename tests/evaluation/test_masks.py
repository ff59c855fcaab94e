"""Mask quality of a foreground step (matl/evaluation/masks.py): IoU with the truth, from files or scenes."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from matl.data.augment import CameraAugment, Photometric
from matl.data.scenes import SceneMaker
from matl.evaluation.masks import (
    compare_steps,
    condition_crops,
    mask_iou,
    mask_precision_recall,
    score_condition,
    score_masks,
    score_scenes,
)
from matl.inference.foreground import GrabCutForeground
from matl.utils.errors import MatlError
from tests.data.conftest import PatternSource


class Square:
    """A foreground step whose mask is a fixed square (and an RGBA alpha kept as given)."""

    def __init__(self, lo: int, hi: int) -> None:
        self.lo, self.hi = lo, hi

    def __call__(self, rgb: np.ndarray) -> np.ndarray:
        mask = np.zeros(rgb.shape[:2], np.float32)
        mask[self.lo:self.hi, self.lo:self.hi] = 1.0
        return mask

    def refine_alpha(self, rgb: np.ndarray, alpha: np.ndarray) -> np.ndarray:
        return alpha


def test_mask_iou() -> None:
    truth = np.zeros((10, 10), bool)
    truth[:, :5] = True
    found = np.zeros((10, 10), np.float32)
    found[:, :5] = 1.0
    assert mask_iou(found, truth) == 1.0
    found[:, 5:] = 0.8  # above 0.5: counted
    assert mask_iou(found, truth) == pytest.approx(0.5)
    assert mask_iou(np.zeros((4, 4)), np.zeros((4, 4), bool)) == 1.0
    assert mask_precision_recall(found, truth) == pytest.approx((0.5, 1.0))      # half of it over the background
    assert mask_precision_recall(found[:, :3], truth[:, :3]) == (1.0, 1.0)
    assert mask_precision_recall(np.zeros((4, 4)), np.ones((4, 4), bool)) == (1.0, 0.0)  # empty: nothing wrong taken


def write_condition(root: Path) -> None:
    """A condition folder as matl.unseen writes it: an RGB and an RGBA query, their true masks, truth.jsonl."""
    (root / "queries").mkdir(parents=True)
    (root / "masks").mkdir()
    truth = np.zeros((20, 20), np.uint8)
    truth[5:15, 5:15] = 255
    rgb = np.full((20, 20, 3), 90, np.uint8)
    cv2.imwrite(str(root / "queries" / "q0000.png"), rgb)
    alpha = np.zeros((20, 20), np.uint8)
    alpha[5:15, 5:10] = 255
    cv2.imwrite(str(root / "queries" / "q0001.png"), np.dstack([rgb, alpha]))
    records = []
    for stem in ("q0000", "q0001"):
        cv2.imwrite(str(root / "masks" / f"{stem}.png"), truth)
        records.append({"image": f"queries/{stem}.png", "object": "o", "mask_file": f"masks/{stem}.png"})
    records.append({"image": "queries/q0000.png", "object": "o"})  # no true mask: not scored
    (root / "truth.jsonl").write_text("".join(json.dumps(r) + "\n" for r in records))


def test_score_condition_reads_the_truth_and_masks_as_the_recognizer(tmp_path: Path) -> None:
    write_condition(tmp_path)
    crops = condition_crops(tmp_path)
    assert len(crops) == 2 and crops[0][0].shape == (20, 20, 3) and crops[1][0].shape == (20, 20, 4)
    result = score_condition(tmp_path, Square(5, 15))
    assert result["queries"] == 2 and result["per_query"] == [1.0, 0.5]  # the RGBA query keeps its alpha
    assert result["iou"] == pytest.approx(0.75) and result["ms_per_crop"] >= 0
    assert score_condition(tmp_path, Square(5, 15), use_alpha=False)["per_query"] == [1.0, 1.0]
    assert score_condition(tmp_path, None)["per_query"] == [0.25, 0.5]  # no step: the whole RGB crop
    assert len(condition_crops(tmp_path, limit=1)) == 1
    (tmp_path / "truth_rgb.jsonl").write_text((tmp_path / "truth.jsonl").read_text().splitlines()[0] + "\n")
    assert score_condition(tmp_path, Square(5, 15), truth="truth_rgb.jsonl")["per_query"] == [1.0]
    with pytest.raises(MatlError, match=r"no truth\.jsonl"):
        condition_crops(tmp_path / "queries")
    (tmp_path / "truth.jsonl").write_text(json.dumps({"image": "queries/q0000.png"}) + "\n")
    with pytest.raises(MatlError, match="names no mask_file"):
        condition_crops(tmp_path)


def test_scores_on_validation_scenes() -> None:
    maker = SceneMaker(augment=CameraAugment(bank=8), photometric=Photometric(p=0.0), occluded_p=0.0,
                       black_p=0.0, floor_p=0.0).setup(PatternSource().build(48))
    exact = score_masks(Square(0, 48), [(np.zeros((48, 48, 3), np.float32), np.ones((48, 48), bool))])
    assert exact["iou"] == 1.0 and exact["precision"] == 1.0 and exact["recall"] == 1.0
    result = score_scenes(maker, 3, GrabCutForeground())
    assert result["queries"] == 3 and 0.0 <= result["iou"] <= 1.0
    both = compare_steps([(maker(0).image, maker(0).visible > 0.5)], {"all": Square(0, 48), "none": Square(0, 0)})
    assert set(both) == {"all", "none"} and both["none"]["iou"] == 0.0 and "per_query" not in both["all"]
