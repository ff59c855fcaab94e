"""scripts/mask_errors.py on a tiny condition folder: every way of masking answers and reports its shares."""

from __future__ import annotations

import json
import re
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from tests.predict_helpers import COLOURS, make_files
from tests.scripts.conftest import load_script


@pytest.fixture()
def folder(tmp_path: Path) -> Path:
    """A ``matl.unseen leave_out=...``-like folder with true masks: two products enrolled, the third left out."""
    make_files(tmp_path)
    names = list(COLOURS)
    shutil.move(str(tmp_path / "gallery" / names[2]), str(tmp_path / "left_out" / names[2]))
    (tmp_path / "masks").mkdir()
    for name in names:
        rgb = np.asarray(Image.open(tmp_path / "queries" / f"{name}.png").convert("RGB"))
        Image.fromarray(((rgb.max(-1) > 0) * 255).astype(np.uint8)).save(tmp_path / "masks" / f"{name}.png")
    for file, chosen in (("truth.jsonl", names[:2]), ("truth_left_out.jsonl", names[2:])):
        lines = [json.dumps({"image": f"queries/{name}.png", "object": name, "plane": "front",
                             "mask_file": f"masks/{name}.png"}) for name in chosen]
        (tmp_path / file).write_text("\n".join(lines) + "\n")
    return tmp_path


def test_every_mask_is_answered(folder: Path, capsys: pytest.CaptureFixture, monkeypatch) -> None:
    script = load_script("mask_errors")
    monkeypatch.setattr(sys, "argv", ["mask_errors.py", str(folder)])
    script.main()
    out = capsys.readouterr().out
    assert "2 enrolled / 1 left-out RGB queries" in out
    for name in script.VARIANTS:
        line = next(row for row in out.splitlines() if row.strip().startswith(f"{name}:"))
        shares = [float(x) for x in re.findall(r"\b[01]\.\d{3}\b", line)]
        assert len(shares) == 2 and all(0.0 <= x <= 1.0 for x in shares)
