"""The unseen benchmark's results: headline queries, the occluded breakdown, each condition's scores, the table."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from matl.evaluation.unseen_results import (
    benchmark_table,
    bin_labels,
    breakdown_groups,
    breakdown_result,
    headline_queries,
    hidden_bin,
    score_condition,
)
from tests.evaluation.test_condition_writers import write_case
from tests.evaluation.test_unseen import write_predictions


def test_hidden_fraction_bins() -> None:
    edges = [0.2, 0.35, 0.5]
    assert bin_labels(edges) == ["<=0.20", "0.20-0.35", "0.35-0.50", ">0.50"]
    assert [hidden_bin(h, edges) for h in (0.1, 0.2, 0.2001, 0.35, 0.49, 0.5, 0.51)] == [
        "<=0.20", "<=0.20", "0.20-0.35", "0.20-0.35", "0.35-0.50", "0.35-0.50", ">0.50"]


def test_a_mixed_condition_is_scored_on_its_rgb_queries_and_broken_down(tmp_path: Path) -> None:
    """Occluded-like truth (hidden fraction, occluder, floor, rgba per query): the headline is the RGB queries,
    each bin and kind is scored on its own queries, the RGBA ones under input only."""
    _, truth = write_case(tmp_path, n=12)
    hidden = [0.12, 0.18, 0.25, 0.3, 0.34, 0.4, 0.45, 0.49, 0.15, 0.22, 0.38, 0.55]
    for i, t in enumerate(truth):
        t.update(hidden_fraction=hidden[i], occluder=("edge", "product", "gripper")[i % 3], floor="dark",
                 rgba=i >= 9)
    truth_path = tmp_path / "truth.jsonl"
    truth_path.write_text("".join(json.dumps(t) + "\n" for t in truth))
    right = {0, 2, 3, 5, 9}  # every other query answered with another product
    objects = sorted({t["object"] for t in truth})
    predictions = write_predictions(tmp_path / "p.jsonl", [
        {"image": t["image"], "object": t["object"] if i in right else objects[(objects.index(t["object"]) + 1) % 3],
         "plane": t["plane"], "H": t["H"], "gallery_image": t["gallery_image"]} for i, t in enumerate(truth)])
    headline = headline_queries(truth)
    assert headline == list(range(9)) and headline_queries([{"rgba": True}]) == [0]
    groups = breakdown_groups(truth, headline, [0.2, 0.35, 0.5])
    assert groups["hidden_fraction"] == {"<=0.20": [0, 1, 8], "0.20-0.35": [2, 3, 4], "0.35-0.50": [5, 6, 7]}
    assert groups["occluder"] == {"product": [1, 4, 7], "gripper": [2, 5, 8], "edge": [0, 3, 6]}
    assert groups["input"] == {"rgb": list(range(9)), "rgba": [9, 10, 11]}
    summary, rows, scored = score_condition(predictions, truth_path, headline, groups, 40)
    assert summary["num_queries"] == 9 and summary["rec_acc"] == pytest.approx(4 / 9) and len(rows) == 12
    assert summary["corner_err_px_median"] == pytest.approx(0.0, abs=1e-6)
    assert scored["hidden_fraction"]["<=0.20"] == {"num_queries": 3, "rec_acc": pytest.approx(1 / 3),
                                                   "corner_err_px_median": pytest.approx(0.0, abs=1e-6),
                                                   "pose_acc_5px": pytest.approx(1 / 3)}
    assert scored["hidden_fraction"]["0.35-0.50"]["rec_acc"] == pytest.approx(1 / 3)
    assert scored["occluder"]["edge"]["rec_acc"] == pytest.approx(2 / 3)
    assert scored["input"]["rgba"]["rec_acc"] == pytest.approx(1 / 3)
    assert breakdown_groups([{"image": "a"}], [0], [0.2]) == {}  # other conditions have none

    result = breakdown_result(groups, {"matl": scored}, [0.2, 0.35, 0.5], "rgb")
    assert result["occluder"]["gripper"] == {"num_queries": 3, "methods": {"matl": {
        "rec_acc": pytest.approx(2 / 3), "corner_err_px_median": pytest.approx(0.0, abs=1e-6),
        "pose_acc_5px": pytest.approx(2 / 3)}}}
    row = {"num_queries": 9, "num_objects": 3, "num_planes": 6, "image_size": 40, "checkpoint": "c", "data": {},
           "query_seed": 7, "timing": None, "headline": "rgb", "breakdown": result,
           "methods": {"matl": {"rec_acc": 4 / 9, "corner_err_px_median": 0.0, "pose_acc_5px": 4 / 9,
                                "query_ms": None}}}
    data, text = benchmark_table({"occluded": row}, ["matl"], "")
    assert "| occluded | 9 | 0.444 / 0.0 / 0.444 / - |" in text and "occluded count its RGB queries only" in text
    assert "| hidden_fraction <=0.20 | 3 | 0.333 / 0.0 / 0.333 |" in text and "| input rgba | 3 |" in text
    assert data["breakdown"]["occluded"]["hidden_fraction"]["0.20-0.35"]["num_queries"] == 3


def test_benchmark_table_has_a_row_per_condition_and_a_column_per_method() -> None:
    methods = ["matl", "sift"]
    results = {c: {"num_queries": 10, "num_objects": 3, "num_planes": 6, "image_size": 100, "checkpoint": "c.ckpt",
                   "data": {}, "query_seed": 1, "timing": None,
                   "methods": {m: {"rec_acc": 0.5 + 0.1 * j, "corner_err_px_median": 2.0, "pose_acc_5px": 0.25,
                                   "query_ms": 3.0 if m == "matl" else None} for j, m in enumerate(methods)}}
               for c in ("clean", "mask")}
    data, text = benchmark_table(results, methods, "python -m matl.unseen ckpt=c.ckpt condition=all")
    assert data["conditions"] == ["clean", "mask"] and data["methods"] == methods
    assert data["table"]["mask"]["sift"]["rec_acc"] == pytest.approx(0.6)
    lines = [line for line in text.splitlines() if line.startswith("|")]
    assert lines[0] == "| condition | queries | matl | sift |" and len(lines) == 4
    assert lines[2] == "| clean | 10 | 0.500 / 2.0 / 0.250 / 3.0 | 0.600 / 2.0 / 0.250 / - |"
    assert "python -m matl.unseen ckpt=c.ckpt condition=all" in text
    json.dumps(data)
