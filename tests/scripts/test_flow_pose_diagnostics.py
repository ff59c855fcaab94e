"""scripts/flow_pose_diagnostics.py on a tiny condition folder: every mode runs and reports its shares."""

from __future__ import annotations

import json
import re
import shutil
import sys
from pathlib import Path

import pytest

from tests.predict_helpers import COLOURS, make_files, true_query_H_gallery
from tests.scripts.conftest import load_script


@pytest.fixture(scope="module")
def diagnostics():
    return load_script("flow_pose_diagnostics")


@pytest.fixture()
def folder(tmp_path: Path) -> Path:
    """A ``matl.unseen``-like folder: the first two products enrolled (``truth.jsonl``), the third left out."""
    make_files(tmp_path)
    names = list(COLOURS)
    shutil.move(str(tmp_path / "gallery" / names[2]), str(tmp_path / "left_out" / names[2]))
    H = true_query_H_gallery().tolist()
    for file, chosen, where in (("truth.jsonl", names[:2], "gallery"), ("truth_left_out.jsonl", names[2:], "left_out")):
        lines = [json.dumps({"image": f"queries/{name}.png", "object": name, "plane": "front",
                             "gallery_image": f"{where}/{name}/front.png", "H": H}) for name in chosen]
        (tmp_path / file).write_text("\n".join(lines) + "\n")
    return tmp_path


def shares(text: str) -> list[float]:
    return [float(x) for x in re.findall(r"\b[01]\.\d{3}\b", text)]


def test_every_mode_reports_shares(diagnostics, folder: Path, capsys: pytest.CaptureFixture, monkeypatch) -> None:
    monkeypatch.setattr(sys, "argv", ["flow_pose_diagnostics.py", str(folder)])
    diagnostics.main()
    out = capsys.readouterr().out
    assert out.startswith("right product and plane: ") and "not verified: " in out
    diagnostics.sweep_above(folder, "pretrained", [0.0])
    out = capsys.readouterr().out
    assert out.startswith("above=0.0: rec_acc ") and "(2 RGB queries)" in out
    assert all(0.0 <= x <= 1.0 for x in shares(out)) and len(shares(out)) == 2
    diagnostics.sweep_verifies(folder, "pretrained", ["none"])
    out = capsys.readouterr().out
    assert out.startswith("verifies=none: ") and "(2 / 1 queries)" in out and len(shares(out)) == 2
