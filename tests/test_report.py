"""python -m matl.report: its command line, outputs and one-line errors (the tables themselves: tests/reporting)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from matl import report
from tests.reporting.fake_runs import make_sweep


def test_cli(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    sweep = make_sweep(tmp_path)
    assert report.main([str(sweep / "multirun"), "--out", str(sweep / "cli"), "--no-fig5"]) == 0
    out = capsys.readouterr().out
    assert "## Table 1" in out and out.rstrip().endswith(f"{sweep / 'cli' / 'table.csv'}, {sweep / 'cli' / 'fig4.png'}")
    assert (sweep / "cli" / "table.csv").is_file() and (sweep / "cli" / "report.md").is_file()
    assert report.main([str(sweep / "evals"), "--no-fig5"]) == 0 and (sweep / "evals" / "report.md").is_file()


@pytest.mark.parametrize("args,message", [
    (["{empty}"], "error: no metrics.json, eval.json or run folder under {empty}"),
    (["{missing}"], "error: {missing} does not exist; pass run or multirun folders of matl.train/eval"),
    (["--fig5", "{missing}/a.ckpt", "{missing}/b.ckpt", "--out", "{empty}"], "error: checkpoint {missing}/a.ckpt"),
])
def test_user_errors_are_one_line_and_exit_2(args: list[str], message: str, tmp_path: Path,
                                             capsys: pytest.CaptureFixture) -> None:
    (tmp_path / "empty").mkdir()
    names = {"empty": tmp_path / "empty", "missing": tmp_path / "missing"}
    with pytest.raises(SystemExit) as exit_:
        report.main([a.format(**names) for a in args])
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    assert err.startswith(message.format(**names)) and err.count("\n") == 1


def test_nothing_to_do_is_a_usage_error(capsys: pytest.CaptureFixture) -> None:
    with pytest.raises(SystemExit) as exit_:
        report.main([])
    assert exit_.value.code == 2 and "give run folders, --fig2 DATA or --fig5 SINGLE MATL" in capsys.readouterr().err


def test_user_errors_come_before_torch_is_loaded(tmp_path: Path) -> None:
    code = ("import sys\nfrom matl import report\ntry:\n    report.main([sys.argv[1]])\nexcept SystemExit as e:\n"
            "    print(e.code, 'torch' in sys.modules)\n")
    done = subprocess.run([sys.executable, "-c", code, str(tmp_path)], capture_output=True, text=True, timeout=120,
                          cwd=Path(__file__).resolve().parents[1])
    assert done.stdout.strip() == "2 False", done.stderr
