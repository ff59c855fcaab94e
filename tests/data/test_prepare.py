"""What python -m matl.render does: sources from configs, the views preview, the speed report."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from rich.console import Console

from matl.data.canonical import CanonicalSet
from matl.data.catalog import SyntheticCatalog
from matl.data.prepare import instantiate_source, render_speed, render_views, shape_counts
from matl.utils.errors import MatlError
from tests.conftest import compose_config
from tests.data.conftest import TinyCatalog


def test_render_views_sheet(tiny: TinyCatalog, tmp_path: Path) -> None:
    """``python -m matl.render ... views=K`` writes views.png: per plane its canonical image and K views."""
    speed = render_views(tiny, 24, 2, tmp_path, Console(quiet=True), max_objects=1)
    sheet = Image.open(tmp_path / "views.png")
    assert sheet.size == (3 * 24 + 3 * 4, 2 * (24 + 4))  # the planar object: 2 planes, canonical + 2 views each
    assert speed["images_per_s"] > 0


def test_render_speed_report(tiny: TinyCatalog) -> None:
    """``python -m matl.render speed=true``: both kinds of throughput and what was measured."""
    report = render_speed(tiny, 24, num_objects=1, views_per_plane=1)
    assert report["image_size"] == 24 and report["objects"] == 1 and report["views_per_plane"] == 1
    assert report["canonical"]["images"] == 2 and report["views"]["images"] == 2  # the planar object's 2 planes
    with pytest.raises(MatlError, match="must be >= 1"):
        render_speed(tiny, 24, num_objects=0)


def test_instantiate_source_from_configs(tmp_path: Path) -> None:
    source = instantiate_source(compose_config("render", ["data=synthetic_apc"], tmp_path))
    assert isinstance(source, SyntheticCatalog) and source.catalog == "apc"
    with pytest.raises(MatlError, match=r"data.source.root is not set: pass data.source.root=<path>"):
        instantiate_source(compose_config("render", ["data=ycb"], tmp_path))
    with pytest.raises(MatlError, match=r"no such folder"):
        instantiate_source(compose_config("render", ["data=ycb", f"data.source.root={tmp_path / 'nope'}"], tmp_path))


def test_shape_counts() -> None:
    cs = CanonicalSet(np.zeros((5, 8, 8, 3), np.uint8), np.zeros((5, 8, 8), bool), np.array([0, 0, 1, 1, 1]),
                      list("abcde"), ["card", "box"], ["planar", "rectangular"])  # fmt: skip
    assert shape_counts(cs) == {"planar": (1, 2), "rectangular": (1, 3)}
