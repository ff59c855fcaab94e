"""A large procedural catalog: many shelves of products under generated brands.

``ShelfCatalog`` concatenates ``shelves`` catalogs of one composition (``arc``: 34 objects, 152
planes each) drawn from consecutive seeds starting at ``first_seed``, and gives every product a
brand of its own, generated from the product's seed: a made-up name, a palette, a title typeface,
a logo kind and a tagline. So its products share no brand with the named brands of the
``synthetic_*`` catalogs (which are the products the unseen-products benchmark keeps out of
training), and two products of different shelves never count as "the same product printed
again" (same brand and title). Sizes: ``shelves=12`` gives 408 products and 1824 planes.

Used to train a model whose ``c()`` and ``s()`` generalise to products they never saw
(``data=shelves``, docs/datasets.md).
"""

from __future__ import annotations

import colorsys
import dataclasses
from typing import Any

import numpy as np

from matl.data.catalog import SyntheticCatalog
from matl.data.catalog.art import LOGO_KINDS
from matl.data.catalog.products import Brand, Palette, ProductSpec, sample_products, slug

SHELF_VERSION = 1

_ONSETS = ("b", "c", "d", "f", "g", "k", "l", "m", "n", "p", "r", "s", "t", "v", "z", "br", "cr", "dr", "fl",
           "gr", "kl", "pr", "st", "tr", "sh", "ch")
_VOWELS = ("a", "e", "i", "o", "u", "ai", "ea", "io", "ou", "y")
_CODAS = ("", "", "", "n", "r", "s", "l", "x", "m", "th", "nd", "sk")
_TAGLINES = ("Good every day", "Made with care", "Simply better", "Since 1958", "Taste the season",
             "For the whole family", "Naturally yours", "Quality you can see", "The original recipe",
             "Freshly packed", "Everyday essentials", "Crafted in small batches", "Trusted at home",
             "Pure and simple", "Bold by nature", "Bright mornings")
_FONTS = ("sans_bold", "sans_bold_oblique", "serif_bold", "serif_bold_italic", "mono_bold", "stix_bold",
          "stix_bold_italic", "stix_italic")


def _rgb(h: float, s: float, v: float) -> tuple[int, int, int]:
    r, g, b = colorsys.hsv_to_rgb(h % 1.0, min(max(s, 0.0), 1.0), min(max(v, 0.0), 1.0))
    return (round(r * 255), round(g * 255), round(b * 255))


def generated_brand(rng: np.random.Generator) -> Brand:
    """A made-up brand: 2-3 syllable name, a palette around a random hue, typeface, logo, tagline."""
    syllables = int(rng.integers(2, 4))
    name = "".join(str(rng.choice(_ONSETS)) + str(rng.choice(_VOWELS)) for _ in range(syllables))
    name += str(rng.choice(_CODAS))
    name = name.upper() if rng.random() < 0.4 else name.capitalize()
    hue = float(rng.random())
    main = _rgb(hue, rng.uniform(0.55, 1.0), rng.uniform(0.35, 0.85))
    second = _rgb(hue + rng.uniform(0.25, 0.6), rng.uniform(0.4, 0.9), rng.uniform(0.5, 0.95))
    accent = _rgb(hue + rng.uniform(-0.1, 0.1), rng.uniform(0.2, 0.5), rng.uniform(0.85, 1.0))
    paper = _rgb(hue, rng.uniform(0.0, 0.12), rng.uniform(0.92, 0.99))
    ink = _rgb(hue, rng.uniform(0.2, 0.6), rng.uniform(0.12, 0.3))
    return Brand(name, Palette(main, second, accent, paper, ink), str(rng.choice(_FONTS)),
                 str(rng.choice(LOGO_KINDS)), str(rng.choice(_TAGLINES)))


class ShelfCatalog(SyntheticCatalog):
    """``shelves`` procedural shelves of ``catalog``'s composition, every product under a generated brand.

    Args:
        shelves: how many shelves (each ``catalog``'s composition: arc 34 objects / 152 planes).
        first_seed: the seed of the first shelf; shelf ``i`` uses ``first_seed + i``.
        catalog, fill, supersample, texture_px: as :class:`SyntheticCatalog` (simple shapes only).
    """

    def __init__(self, shelves: int = 12, first_seed: int = 100, catalog: str = "arc", **kwargs: Any) -> None:
        if catalog not in ("arc", "ycb", "apc"):
            raise ValueError(f"data.source.catalog={catalog!r} is invalid for shelves: use arc, ycb or apc")
        if int(shelves) < 1:
            raise ValueError(f"data.source.shelves={shelves} is invalid: use an integer >= 1")
        super().__init__(catalog=catalog, seed=int(first_seed), subset="planar", **kwargs)
        self.shelves, self.first_seed = int(shelves), int(first_seed)

    def __repr__(self) -> str:
        return (f"ShelfCatalog(shelves={self.shelves}, first_seed={self.first_seed}, catalog={self.catalog!r}, "
                f"fill={self.fill}, supersample={self.supersample}, texture_px={self.texture_px})")

    @property
    def num_objects(self) -> int:
        return self.shelves * super().num_objects

    @property
    def num_planes(self) -> int:
        return self.shelves * super().num_planes

    def products(self) -> list[ProductSpec]:
        """Shelf by shelf, each shelf's products in their catalog order, rebranded and renamed."""
        specs: list[ProductSpec] = []
        names: set[str] = set()
        for shelf in range(self.shelves):
            for spec in sample_products(self.catalog, self.first_seed + shelf):
                brand = generated_brand(np.random.default_rng([SHELF_VERSION, spec.seed]))
                name = slug(f"{brand.name} {spec.title}")
                while name in names:  # two generated brands may coincide; keep names unique
                    name += "_b"
                names.add(name)
                specs.append(dataclasses.replace(spec, brand=brand, name=name))
        return specs

    def cache_key(self) -> dict[str, Any]:
        key = super().cache_key()
        key.update(type="shelf_catalog", shelves=self.shelves, first_seed=self.first_seed, shelf_version=SHELF_VERSION)
        return key
