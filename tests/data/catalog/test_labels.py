"""Product prints (matl.data.catalog.labels and its panels, planar styles and cylinder prints): every role of
every kind drawn at its size, a pure function of ``(spec, role, size)``, tall faces turned."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from matl.data.catalog import SyntheticCatalog
from matl.data.catalog.drawing import INK_FLOOR
from matl.data.catalog.labels import ROLES, compose
from matl.data.catalog.panels import turned_when_tall
from matl.data.catalog.planar_prints import PLANAR_STYLES
from matl.data.catalog.products import KINDS


def test_the_planar_styles_are_styles_of_planar_kinds() -> None:
    """Each of the planar styles' fronts and backs is printed on a planar kind (others, ``packet``, print as boxes)."""
    planar = {k.style for k in KINDS if k.shape == "planar"}
    assert set(PLANAR_STYLES) < planar and all(len(faces) == 2 for faces in PLANAR_STYLES.values())


@pytest.mark.parametrize("role", ROLES)
def test_every_role_is_a_pure_function_of_spec_role_and_size(role: str) -> None:
    specs = {p.style: p for p in SyntheticCatalog("ycb", 0).products()}  # one product per print style
    for spec in specs.values():
        size = (48, 48) if role.startswith("lid") else (64, 40)
        first = np.asarray(compose(spec, role, size))
        assert first.shape == (size[1], size[0], 3) and first.min() >= INK_FLOOR  # never the background's 0
        assert np.array_equal(first, np.asarray(compose(spec, role, size)))
    with pytest.raises(ValueError, match="unknown role"):
        compose(next(iter(specs.values())), "inside", (32, 32))


def test_a_tall_face_is_laid_out_lying_and_turned() -> None:
    calls = []

    @turned_when_tall(1.6)
    def layout(spec, w: int, h: int, rng) -> Image.Image:
        calls.append((w, h))
        return Image.new("RGB", (w, h))

    assert layout(None, 30, 40, None).size == (30, 40) and calls[-1] == (30, 40)  # not tall enough: as asked
    assert layout(None, 20, 40, None).size == (20, 40) and calls[-1] == (40, 20)  # drawn 40 x 20, turned
