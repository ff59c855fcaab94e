"""scripts/catalog_figure.py: the rows of several catalogue runs in one figure and table, by gallery size."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

from tests.scripts.conftest import load_script


def _run(path: Path, sizes: tuple[int, ...], complete: bool = True) -> Path:
    rows = [{"products": n, "rec_acc": 0.9, "lookalike_rec_acc": 0.7, "unknown_rejected": 0.5,
             "refine_pose_acc_5px": 0.8, "query_ms": float(n), "enrol_s": 1.0, "method": "matl_refine",
             "methods": {"matl_refine": {"query_ms": float(n)}, "sift": {"query_ms": 10.0 * n, "rec_acc": None}}}
            for n in sizes]
    path.write_text(json.dumps({"command": f"python -m matl.unseen condition=catalog 'catalog_sizes={list(sizes)}'",
                                "rows": rows, "complete": complete, "catalog": {"lookalike_share": 0.25},
                                "queries": 200, "timing": {"threads": 1}}))
    return path


def test_runs_are_merged_by_size(tmp_path: Path, capsys: pytest.CaptureFixture, monkeypatch) -> None:
    large, small = _run(tmp_path / "large.json", (10000,)), _run(tmp_path / "small.json", (20, 2000))
    script = load_script("catalog_figure")
    figure = tmp_path / "img" / "catalog.png"
    monkeypatch.setattr(sys, "argv", ["catalog_figure.py", str(large), str(small), "--out", str(figure)])
    script.main()
    assert figure.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith("`python -m matl.unseen") and "10000" in lines[0] and "2000" in lines[1]
    sizes = [line.split(" | ")[0].strip("| ") for line in lines if line.startswith("| ") and "products" not in line]
    assert sizes == ["20", "2000", "10000"]  # by gallery size, whatever the order of the runs


def test_a_size_twice_or_an_unfinished_run_is_a_one_line_error(tmp_path: Path, monkeypatch) -> None:
    script = load_script("catalog_figure")
    one, two = _run(tmp_path / "one.json", (20, 200)), _run(tmp_path / "two.json", (200,))
    monkeypatch.setattr(sys, "argv", ["catalog_figure.py", str(one), str(two), "--out", str(tmp_path / "f.png")])
    with pytest.raises(SystemExit, match="200 products come from more than one run: pass one run per size"):
        script.main()
    partial = _run(tmp_path / "partial.json", (20,), complete=False)
    monkeypatch.setattr(sys, "argv", ["catalog_figure.py", str(partial), "--out", str(tmp_path / "f.png")])
    with pytest.raises(SystemExit, match="from an unfinished run: let it finish or run it again"):
        script.main()
    missing = str(tmp_path / "none.json")
    monkeypatch.setattr(sys, "argv", ["catalog_figure.py", missing, "--out", str(tmp_path / "f.png")])
    with pytest.raises(SystemExit, match=r"cannot be read as a catalogue run's catalog\.json"):
        script.main()
