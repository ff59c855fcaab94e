"""The speed x accuracy plane of matl.unseen's methods (matl/reporting/speed_accuracy.py)."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
from PIL import Image

from matl.reporting.speed_accuracy import METHOD_LABELS, methods_table, plot_speed_accuracy, timed_methods
from matl.utils.errors import MatlError

TABLE = {
    "matl": {"rec_acc": 0.9, "corner_err_px_median": 8.1, "pose_acc_5px": 0.02, "query_ms": 2.5},
    "matl_refine": {"rec_acc": 0.9, "corner_err_px_median": 0.3, "pose_acc_5px": 0.8, "query_ms": 25.0},
    "sift": {"rec_acc": 0.97, "corner_err_px_median": 1.8, "pose_acc_5px": 0.79, "query_ms": 50.0},
    "xfeat_lighterglue": {"rec_acc": 0.9, "corner_err_px_median": None, "pose_acc_5px": 0.7, "query_ms": 1600.0},
    "xfeat": {"rec_acc": 0.8, "corner_err_px_median": 2.0, "pose_acc_5px": 0.7, "query_ms": None},
}


def test_plot_writes_a_png_of_the_timed_methods(tmp_path: Path) -> None:
    path = plot_speed_accuracy(TABLE, tmp_path / "sub" / "plane.png", "test queries")
    assert path == tmp_path / "sub" / "plane.png"
    with Image.open(path) as image:
        assert image.format == "PNG" and image.size[0] > image.size[1] > 300  # two panels side by side
    assert timed_methods(TABLE) == ["matl", "matl_refine", "sift", "xfeat_lighterglue"]


def test_plot_needs_timings(tmp_path: Path) -> None:
    untimed = {m: {**row, "query_ms": None} for m, row in TABLE.items()}
    untimed["sift"]["query_ms"] = math.nan
    with pytest.raises(MatlError, match=r"timing\.queries > 0"):
        plot_speed_accuracy(untimed, tmp_path / "plane.png", "untimed")
    assert not (tmp_path / "plane.png").exists()


def test_methods_table_fastest_first_with_labels() -> None:
    lines = methods_table(TABLE, queries=100).splitlines()
    assert lines[0] == "| method | rec_acc | corner_err_px median | pose_acc_5px | query_ms |"
    rows = [line for line in lines[2:] if line.startswith("| ")]
    assert [r.split(" (`")[0][2:] for r in rows] == [METHOD_LABELS[m] for m in
                                                    ("matl", "matl_refine", "sift", "xfeat_lighterglue", "xfeat")]
    assert rows[0] == "| MATL (`matl`) | 0.900 | 8.10 | 0.020 | 2.5 |"
    assert rows[3] == "| XFeat+LighterGlue (`xfeat_lighterglue`) | 0.900 | - | 0.700 | 1600.0 |"
    assert rows[4].endswith("| 0.700 | - |") and lines[-1] == "100 queries, every method on the same files."
