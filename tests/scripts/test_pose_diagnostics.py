"""scripts/pose_diagnostics.py: the affine floor shrinks with the focal length; exact poses have no residual."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest

from tests.scripts.conftest import load_script


@pytest.fixture(scope="module")
def diagnostics():
    return load_script("pose_diagnostics")


def test_affine_floor_shrinks_with_focal_and_vanishes_without_tilt(diagnostics) -> None:
    medians = [float(np.median(diagnostics.affine_floor(f, 200))) for f in (1.0, 3.0, 10.0)]
    assert medians[0] > medians[1] > medians[2] > 0
    assert medians[0] > 2 * medians[1]  # perspective falls roughly as 1 / focal


def test_residuals_of_exact_poses_are_zero(diagnostics, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    rng = np.random.default_rng(0)
    path = tmp_path / "per_query.csv"
    keys = [f"{i}{j}" for i in range(3) for j in range(3)]
    with path.open("w", newline="") as f:
        writer = csv.DictWriter(f, ["correct", *[f"true_H_{k}" for k in keys], *[f"est_H_{k}" for k in keys]])
        writer.writeheader()
        for _ in range(20):
            H = np.eye(3) + rng.normal(scale=[[0.1, 0.1, 5], [0.1, 0.1, 5], [1e-3, 1e-3, 0]])
            entries = dict(zip(keys, H.flatten(), strict=True))
            writer.writerow({"correct": "1", **{f"true_H_{k}": v for k, v in entries.items()},
                             **{f"est_H_{k}": v for k, v in entries.items()}})
    diagnostics.residuals(path)
    out = capsys.readouterr().out
    assert "20 correctly recognised queries" in out
    assert "rotation (deg)           median   0.000" in out and "correlation 1.000" in out
