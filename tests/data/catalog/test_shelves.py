"""The large catalog: shelves of products under generated brands."""

from __future__ import annotations

import numpy as np
import pytest

from matl.data.catalog import SyntheticCatalog
from matl.data.catalog.products import BRANDS
from matl.data.catalog.shelves import ShelfCatalog, generated_brand


def test_sizes_names_and_brands() -> None:
    cat = ShelfCatalog(shelves=3)
    specs = cat.products()
    assert cat.num_objects == len(specs) == 3 * SyntheticCatalog("arc").num_objects
    assert cat.num_planes == 3 * SyntheticCatalog("arc").num_planes
    assert len({s.name for s in specs}) == len(specs)
    named = {b.name for b in BRANDS}
    assert not named & {s.brand.name for s in specs}  # no brand of the synthetic_* catalogs
    assert len({s.brand.name for s in specs}) > 0.9 * len(specs)  # a brand per product


def test_deterministic_and_keyed() -> None:
    assert [s.name for s in ShelfCatalog(shelves=2).products()] == [s.name for s in ShelfCatalog(shelves=2).products()]
    keys = [ShelfCatalog(shelves=2).cache_key(), ShelfCatalog(shelves=3).cache_key(),
            ShelfCatalog(shelves=2, first_seed=7).cache_key(), SyntheticCatalog("arc", seed=100).cache_key()]
    assert len({str(sorted(k.items())) for k in keys}) == 4
    # the first shelf has the shapes and titles of the arc catalog of its seed
    first = ShelfCatalog(shelves=1, first_seed=5).products()
    assert [s.title for s in first] == [s.title for s in SyntheticCatalog("arc", seed=5).products()]


def test_generated_brand_is_valid() -> None:
    brand = generated_brand(np.random.default_rng(0))
    assert brand.name.isalpha() and len(brand.name) >= 4
    assert all(0 <= c <= 255 for colour in vars(brand.palette).values() for c in colour)


def test_bad_values() -> None:
    with pytest.raises(ValueError, match="shelves"):
        ShelfCatalog(shelves=0)
    with pytest.raises(ValueError, match="catalog"):
        ShelfCatalog(catalog="ycb_table2")
