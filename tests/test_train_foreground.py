"""``python -m matl.train_foreground``: a mistaken option is one line on stderr, exit 2, before any work (the
training itself: tests/training/test_foreground.py)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def test_a_mistaken_option_is_one_line_exit_2_before_any_work(tmp_path: Path) -> None:
    folder = tmp_path / "a_folder"
    folder.mkdir()
    run = subprocess.run([sys.executable, "-m", "matl.train_foreground", f"publish={folder}",
                          f"hydra.run.dir={tmp_path / 'run'}"], cwd=REPO, capture_output=True, text=True, timeout=300)
    assert run.returncode == 2, run.stderr
    lines = run.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: publish=") and "is a folder" in lines[0], run.stderr
    assert not (tmp_path / "run" / "checkpoints").exists() and list(folder.iterdir()) == []
