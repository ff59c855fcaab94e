"""The paper's figures: Fig. 2's loss curve (from an image and from a catalog), Fig. 5 from two checkpoints."""

from __future__ import annotations

import csv
import math
from pathlib import Path

import hydra
import pytest
import torch
from omegaconf import OmegaConf

from matl.reporting.build import build_report
from matl.reporting.figures import appearance_vs_rotation, fig5_panels, local_minima, plot_fig5, write_fig2
from tests.conftest import TINY, compose_config


def test_fig2_curve_has_minima_at_0_and_180() -> None:
    """A label-like image (a 2:1 rectangle with an off-centre mark): rotated by 180 deg its silhouette
    matches again, so the loss has a poor local minimum there, as Fig. 2 shows for a book."""
    image = torch.zeros(3, 32, 32)
    image[:, 10:22, 4:28] = 0.6
    image[0, 12:16, 6:12] = 1.0
    angles = torch.arange(-180.0, 181.0, 5.0, dtype=torch.float64)
    values = appearance_vs_rotation(image, angles)
    assert values[angles == 0].item() == pytest.approx(0.0, abs=1e-6)
    minima = dict(local_minima(angles.tolist(), values.tolist()))
    assert 0.0 in minima and -180.0 in minima and 180.0 in minima
    assert values[angles == 180].item() < values[angles == 90].item()


def test_fig2_from_a_tiny_catalog(tmp_path: Path, cache_dir: Path) -> None:
    path, caption = write_fig2(tmp_path / "fig2.png", "synthetic_apc", None, 32, str(cache_dir))
    assert path.is_file() and path.stat().st_size > 0 and "Local minima" in caption
    with (tmp_path / "fig2.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 181 and float(rows[90]["rotation_deg"]) == 0.0
    assert float(rows[90]["appearance_loss"]) < 1e-6 < min(float(r["appearance_loss"]) for r in rows[:80])


def _fake_checkpoint(path: Path, overrides: list[str], cache_dir: Path) -> Path:
    """A matl.train-style checkpoint of a freshly initialised model (no training needed for the figure)."""
    cfg = compose_config("train", [*TINY, f"paths.cache_dir={cache_dir}", *overrides], path.parent)
    config = OmegaConf.to_container(cfg, resolve=True)
    model = hydra.utils.instantiate(cfg.model)
    torch.save({"state_dict": model.state_dict(), "matl_config": config, "matl_image_size": 32,
                "matl_num_anchors": cfg.N, "epoch": 0, "global_step": 0}, path)
    return path


def test_fig5_from_two_checkpoints(tmp_path: Path, cache_dir: Path) -> None:
    single = _fake_checkpoint(tmp_path / "single.ckpt", ["N=1"], cache_dir)
    matl = _fake_checkpoint(tmp_path / "matl.ckpt", ["N=4", "seed=1"], cache_dir)
    panels = fig5_panels(single, matl, rows=3, pool=40)
    assert panels.query.shape == panels.single.shape == panels.matl.shape == panels.anchor.shape == (3, 3, 32, 32)
    assert len(panels.labels) == 3 and all("rotation" in label for label in panels.labels)
    rotations = [abs(float(label.rsplit(" ", 1)[-1].rstrip("°"))) for label in panels.labels]
    assert rotations == sorted(rotations)  # from small to large in-plane rotation
    assert plot_fig5(panels, tmp_path / "fig5.png").is_file()
    # through the report, with the checkpoints given on the command line
    rep = build_report([], tmp_path / "rep", fig5=[single, matl])
    assert (tmp_path / "rep" / "fig5.png").is_file() and "![Fig. 5](fig5.png)" in (rep.out / "report.md").read_text()
    assert not math.isnan(float(panels.matl.mean()))
