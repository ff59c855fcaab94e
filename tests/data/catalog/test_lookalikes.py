"""The catalogue benchmark's products (matl.data.catalog.lookalikes): prefix-stable, unique, held-out, with
look-alike families that differ in one thing each, framed like the rendered catalogs, cached in chunks."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from matl.data.catalog import lookalikes
from matl.data.catalog.drawing import CATALOG_PHOTO_FILES, HELDOUT_PHOTO_FILES, PHOTO_FILES
from matl.data.catalog.lookalikes import CHANGES, LookalikeCatalog, load_lookalikes, make_brand
from matl.data.catalog.products import BRANDS


def test_products_are_prefix_stable_unique_and_deterministic() -> None:
    small, large = LookalikeCatalog(60).products(), LookalikeCatalog(300).products()
    assert small == large[:60] and LookalikeCatalog(300).products() == large
    assert len({p.spec.name for p in large}) == 300
    assert LookalikeCatalog(60, seed=1).products()[0].spec.name != small[0].spec.name
    # brands are procedural, never a training brand; pictures only from the held-out photo pool
    training = {b.name.lower() for b in BRANDS}
    assert not {p.spec.brand.name.lower() for p in large} & training
    assert {p.spec.art.removeprefix("photo_") for p in large} <= set(CATALOG_PHOTO_FILES)
    assert not set(CATALOG_PHOTO_FILES) & set(PHOTO_FILES) and set(HELDOUT_PHOTO_FILES) <= set(CATALOG_PHOTO_FILES)
    assert make_brand(0, 3) == make_brand(0, 3) and make_brand(0, 3) != make_brand(0, 4)


@pytest.mark.parametrize("share", [0.25, 0.5])
def test_a_share_of_every_prefix_is_in_lookalike_families(share: float) -> None:
    products = LookalikeCatalog(2000, lookalike_share=share).products()
    for n in (200, 2000):
        assert abs(sum(p.family is not None for p in products[:n]) / n - share) < 0.03
    assert not any(p.family for p in LookalikeCatalog(100, lookalike_share=0.0).products())


def test_family_members_share_brand_layout_and_picture_and_differ_in_one_thing() -> None:
    products = LookalikeCatalog(400).products()
    families: dict[str, list] = {}
    for p in products:
        if p.family is not None:
            families.setdefault(p.family, []).append(p)
    assert families and all(2 <= len(m) <= 4 for m in families.values())
    seen = set()
    for members in families.values():
        first = members[0]
        assert first.change is None and all(m.change in CHANGES for m in members[1:])
        for m in members[1:]:
            a, b = first.spec, m.spec
            assert (a.brand, a.kind, a.dims, a.art, a.seed) == (b.brand, b.kind, b.dims, b.art, b.seed)
            differs = {"flavour": a.title != b.title, "colour": a.variant != b.variant,
                       "size": a.subtitle != b.subtitle, "redesign": m.badge is not None}
            assert [k for k, v in differs.items() if v] == [m.change]
            seen.add(m.change)
    assert seen == set(CHANGES)


def test_prints_are_framed_like_the_rendered_catalogs() -> None:
    catalog = LookalikeCatalog(40, planes=2)
    cs = catalog.build(64)
    assert cs.images.shape == (80, 64, 64, 3) and cs.masks.shape == (80, 64, 64)
    assert cs.plane_names[:2] == ["front", "back"] and list(cs.plane_object[:4]) == [0, 0, 1, 1]
    for p in range(cs.num_planes):
        rows, cols = np.flatnonzero(cs.masks[p].any(1)), np.flatnonzero(cs.masks[p].any(0))
        assert max(len(rows), len(cols)) == pytest.approx(0.6 * 64, abs=1.5)  # longer side at fill
        assert abs((rows[0] + rows[-1]) / 2 - 31.5) <= 1 and abs((cols[0] + cols[-1]) / 2 - 31.5) <= 1
        assert cs.images[p][cs.masks[p]].min() > 0  # the print never reaches the background's 0
        outside = np.ones((64, 64), bool)
        outside[rows[0] - 1:rows[-1] + 2, cols[0] - 1:cols[-1] + 2] = False
        assert (cs.images[p][outside] == 0).all()  # black around the plane
    # a redesign prints a badge: its front differs from the family's first product's, its back does not
    products = catalog.products()
    i = next(k for k, p in enumerate(products) if p.change == "redesign")
    first = next(k for k, p in enumerate(products) if p.family == products[i].family)
    assert (np.abs(cs.images[2 * i].astype(int) - cs.images[2 * first]) > 40).sum() >= 10
    assert np.array_equal(cs.images[2 * i + 1], cs.images[2 * first + 1])


def test_chunks_are_cached_and_a_larger_catalogue_reuses_them(tmp_path: Path, monkeypatch: pytest.MonkeyPatch
                                                               ) -> None:
    monkeypatch.setattr(lookalikes, "CHUNK", 7)
    built: list[tuple[int, int]] = []
    build = LookalikeCatalog.build

    def counting(self: LookalikeCatalog, image_size: int):
        built.append((self.start, self.num_products))
        return build(self, image_size)

    monkeypatch.setattr(LookalikeCatalog, "build", counting)
    small = load_lookalikes(LookalikeCatalog(10), 32, tmp_path)
    large = load_lookalikes(LookalikeCatalog(16), 32, tmp_path)
    assert built == [(0, 7), (7, 10), (7, 14), (14, 16)]  # the first chunk came from the cache
    assert large.object_names == LookalikeCatalog(16).build(32).object_names
    assert np.array_equal(large.images[:7], small.images[:7]) and list(large.plane_object) == list(range(16))


@pytest.mark.parametrize("kwargs,match", [
    ({"num_products": 0}, "num_products=0"), ({"num_products": 20_001}, "1 to 20000"),
    ({"lookalike_share": 1.0}, "lookalike_share"), ({"family_size": (1, 3)}, "family_size"),
    ({"family_size": (4, 3)}, "family_size"), ({"planes": 3}, "planes=3")])
def test_options_the_generator_cannot_make_are_refused(kwargs: dict, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        LookalikeCatalog(**{"num_products": 10, **kwargs})


def test_no_two_members_of_a_large_family_are_alike() -> None:
    """Families larger than the four kinds of change repeat a kind, never a value: no two twins print alike."""
    families: dict[str, list] = {}
    for p in LookalikeCatalog(600, family_size=(8, 12)).products():
        if p.family is not None:
            families.setdefault(p.family, []).append(p)
    assert families and max(len(m) for m in families.values()) >= 8
    for members in families.values():
        looks = [(m.spec.title, m.spec.variant, m.spec.subtitle, m.badge) for m in members]
        assert len(set(looks)) == len(looks)
