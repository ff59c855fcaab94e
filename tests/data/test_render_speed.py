"""Render throughput: the images counted per kind and a positive rate."""

from __future__ import annotations

import pytest

from matl.data.render_speed import render_images_per_s
from tests.data.conftest import TinyCatalog

SIZE = 32


def test_render_throughput_function(tiny: TinyCatalog) -> None:
    canon = render_images_per_s(tiny, SIZE, "canonical", num_objects=2)
    views = render_images_per_s(tiny, SIZE, "views", num_objects=1, views_per_plane=2)
    # TinyCatalog does not say how many objects it has: the first num_objects are used (2 + 6 planes; 2 planes x 2)
    assert canon["images"] == 8 and views["images"] == 4
    assert canon["images_per_s"] > 0 and views["images_per_s"] > 0
    assert set(canon) == {"images", "render_seconds", "images_per_s", "model_seconds", "images_per_s_with_models"}
    with pytest.raises(ValueError, match="kind must be"):
        render_images_per_s(tiny, SIZE, "photos")
