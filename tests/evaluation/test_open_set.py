"""Open-set scoring: hand-computed precision / recall, and ``matl.unseen leave_out=`` end to end."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from matl.evaluation.open_set import open_set_summary, plot_open_set
from matl.evaluation.unseen import left_out_products, unseen
from tests.conftest import compose_config
from tests.evaluation.test_unseen import tiny_ckpt  # noqa: F401 - the module fixture


def record(image: str, nearest: str, known: bool, statistic: float) -> dict:
    return {"image": image, "nearest_object": nearest, "known": known, "statistic": statistic}


def test_summary_by_hand(tmp_path: Path) -> None:
    truth = [{"image": "a", "object": "x", "enrolled": True}, {"image": "b", "object": "y", "enrolled": True},
             {"image": "c", "object": "z", "enrolled": False}, {"image": "d", "object": "w", "enrolled": False}]
    predictions = {"a": record("a", "x", True, 0.2), "b": record("b", "x", False, 0.9),  # b: wrong and rejected
                   "c": record("c", "x", False, 0.8), "d": record("d", "y", True, 0.5)}
    s = open_set_summary(truth, predictions)
    assert s["rec_acc_closed"] == 0.5            # a right, b wrong (nearest x, truth y)
    assert s["rec_acc_known"] == 0.5             # a accepted and right
    assert s["unknown_recall"] == 0.5            # c rejected, d accepted
    assert s["unknown_precision"] == 0.5         # rejected: b (enrolled) and c (left out)
    assert [c["threshold"] for c in s["curve"]] == [0.2, 0.5, 0.8, 0.9]
    assert s["curve"][0] == {"threshold": 0.2, "rec_acc_known": 0.5, "unknown_recall": 1.0,
                             "unknown_precision": pytest.approx(2 / 3)}
    assert plot_open_set(s, tmp_path / "curve.png").stat().st_size > 1000
    with pytest.raises(ValueError, match="both"):
        open_set_summary(truth[:2], predictions)


def test_left_out_products_are_a_seeded_fraction() -> None:
    names = [f"p{i}" for i in range(10)]
    assert len(left_out_products(names, 0.5, 3)) == 5 and left_out_products(names, 0.5, 3) == left_out_products(
        names, 0.5, 3)
    assert left_out_products(names, 0.0, 3) == []


@pytest.mark.slow
def test_unseen_open_set_end_to_end(tiny_ckpt: Path, tmp_path: Path, cache_dir: Path) -> None:
    out = tmp_path / "open"
    result = unseen(compose_config("unseen", [f"ckpt={tiny_ckpt}", "data=synthetic_apc", "methods=[matl]",
                                              "timing.queries=0", "queries=24", f"out={out}", "leave_out=0.5",
                                              f"paths.cache_dir={cache_dir}"], tmp_path / "run"))
    left = result["open_set"]["left_out"]
    assert len(left) == 8 and not any((out / "gallery" / name).exists() for name in left)
    assert all((out / "left_out" / name).is_dir() for name in left)
    saved = json.loads((out / "open_set.json").read_text())
    for key in ("rec_acc_closed", "rec_acc_known", "unknown_recall", "unknown_precision"):
        assert 0.0 <= saved[key] <= 1.0 and saved[key] == result["open_set"][key]
    assert saved["num_enrolled_queries"] + saved["num_left_out_queries"] == 24
    assert result["num_queries"] == saved["num_enrolled_queries"]  # the usual metrics: enrolled products only
    assert (out / "open_set.png").is_file()
