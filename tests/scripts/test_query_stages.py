"""scripts/query_stages.py on a tiny gallery folder: every timed call is reported, its stages and the rest add up."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

from tests.predict_helpers import COLOURS, make_files
from tests.scripts.conftest import load_script


def test_every_call_is_broken_down(tmp_path: Path, capsys: pytest.CaptureFixture, monkeypatch) -> None:
    make_files(tmp_path)
    lines = [json.dumps({"image": f"queries/{name}.png", "object": name, "plane": "front", "enrolled": True})
             for name in COLOURS]
    (tmp_path / "truth.jsonl").write_text("\n".join(lines) + "\n")
    script = load_script("query_stages")
    monkeypatch.setattr(sys, "argv", ["query_stages.py", str(tmp_path), "--warmup", "1", "--flow-pose", "none",
                                      "--option", "lookalike_ratio=1.1", "--option", "lookalike_statistic=global"])
    script.main()
    report = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert report["queries"] == len(COLOURS) and report["gallery_planes"] == len(COLOURS)
    assert report["options"] == {"lookalike_ratio": 1.1, "lookalike_statistic": "global"}
    assert report["median_ms"] > 0.0 and {"networks", "search", "refinement"} <= set(report["stage_mean_ms"])
    for call in report["calls"]:
        assert call["ms"] == pytest.approx(sum(call["stages"].values()) + call["other"], abs=0.05)


def test_a_folder_without_a_gallery_is_a_one_line_error(tmp_path: Path, monkeypatch) -> None:
    script = load_script("query_stages")
    monkeypatch.setattr(sys, "argv", ["query_stages.py", str(tmp_path)])
    with pytest.raises(SystemExit, match=r"gallery not found: pass a folder with gallery/ and truth.jsonl"):
        script.main()
    monkeypatch.setattr(sys, "argv", ["query_stages.py", str(tmp_path), "--option", "lookalike_ratio"])
    with pytest.raises(SystemExit, match=r"--option 'lookalike_ratio' is not NAME=VALUE"):
        script.main()
