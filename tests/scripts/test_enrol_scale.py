"""scripts/enrol_scale.py on a small gallery with the shipped fast model: every figure is measured and the gallery
folder is left as it was (its cache aside)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

from tests.inference.test_api import gallery_folder
from tests.scripts.conftest import load_script


@pytest.mark.slow
def test_every_figure_is_measured_and_the_gallery_is_left_alone(tmp_path: Path, monkeypatch) -> None:
    script = load_script("enrol_scale")
    gallery = gallery_folder(tmp_path / "gallery", 22)
    before = sorted(p.name for p in gallery.iterdir())
    out = tmp_path / "scale.json"
    monkeypatch.setattr(sys, "argv", ["enrol_scale.py", str(gallery), "--ckpt", "pretrained_fast", "--out", str(out),
                                      "--kill-after", "0.5"])
    script.main()
    result = json.loads(out.read_text())
    assert result["products"] == 22 and 0 <= result["kept_products"] <= 22
    for key in ("fresh_s", "resumed_s", "cached_s", "grown_s", "add_ms", "remove_ms", "query_ms",
                "first_query_after_add_ms", "first_query_after_remove_ms", "s_per_1000_products"):
        assert result[key] > 0, key
    assert 30_000 < result["cache_bytes_per_product"] < 60_000  # a 100 px plane's image and 4 anchors' features
    assert sorted(p.name for p in gallery.iterdir() if not p.name.startswith(".")) == before
