"""Offscreen rendering: plane offsets from the canonical depth buffer."""

from __future__ import annotations

import math

import numpy as np

from matl.data.catalog.rendering import ViewRenderer
from tests.data.conftest import TinyCatalog

SIZE = 32


def test_plane_offset_is_the_face_for_boxes_and_inside_for_cylinders(tiny: TinyCatalog) -> None:
    models = list(tiny.models())
    with ViewRenderer(SIZE, 2) as renderer:
        box_offsets = renderer.plane_offsets(models[1], tiny.fill)
        cyl_offsets = renderer.plane_offsets(models[2], tiny.fill)
    dims = np.asarray(tiny.specs[1].dims)
    expected = [dims[1] / 2, dims[1] / 2, dims[0] / 2, dims[0] / 2, dims[2] / 2, dims[2] / 2]
    assert np.allclose(box_offsets, expected, rtol=0.02)
    radius = tiny.specs[2].dims[0] / 2
    assert np.allclose(cyl_offsets[2:], math.pi / 4 * radius, rtol=0.05)  # mean height of a half cylinder
