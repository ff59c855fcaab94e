"""A large held-out catalogue with look-alike families: the products of ``python -m matl.unseen condition=catalog``.

:class:`LookalikeCatalog` is a :class:`~matl.data.canonical.CanonicalSource` of up to :data:`MAX_PRODUCTS`
products, a pure function of its seed and *prefix-stable*: the first ``n`` products of a catalogue of any
size are the same, so a gallery of ``n`` products is a subset of every larger one. Its products

- print every picture from :data:`~matl.data.catalog.drawing.CATALOG_PHOTO_FILES` (scikit-image's bundled
  photos, a pool no training catalog uses), under procedurally named brands (:func:`make_brand`: syllable
  names, never a training brand's) with their own palettes, typefaces and logos;
- come as *units*: a single product, or a look-alike *family* of :attr:`LookalikeCatalog.family_size`
  products that share brand, kind, size, layout and picture (one print seed) and differ from the family's
  first product in one thing each (:data:`CHANGES`): the flavour name, the colour band (the variant colour),
  the size text, or a small redesign (a badge printed on the front). Units are dealt so that about
  :attr:`LookalikeCatalog.lookalike_share` of every prefix's products belong to a family;
- are flat prints (the planar and box kinds of :data:`~matl.data.catalog.products.KINDS`) with ``planes``
  canonical planes each (1: the front; 2: front and back), drawn straight into the canonical frame (the
  plane's longer side at ``fill`` of the image, as the rendered catalogs frame it) without a renderer.

:func:`load_lookalikes` builds and caches the canonical images in chunks of :data:`CHUNK` products, so a
larger catalogue reuses the smaller one's cache.
"""

from __future__ import annotations

import dataclasses
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from PIL import Image, ImageDraw

from matl.data.canonical import CanonicalSet, load_canonical
from matl.data.catalog.art import LOGO_KINDS
from matl.data.catalog.drawing import CATALOG_PHOTO_FILES, INK, WHITE, draw_text, floor_ink, star_points
from matl.data.catalog.labels import compose
from matl.data.catalog.products import BRANDS, KINDS, SIZES, VARIANTS, Brand, Palette, ProductSpec, slug

GENERATOR_VERSION = 1  # bump when anything changes what a (seed, index) product looks like: caches rebuild
MAX_PRODUCTS = 20_000  # products one catalogue can hold (galleries up to 10,000 plus their left-out products)
CHUNK = 500  # products per cache file (load_lookalikes)
CHANGES = ("flavour", "colour", "size", "redesign")  # how a family member differs from the family's first product
FONTS = ("serif_bold", "sans_bold", "sans_bold_oblique", "mono_bold", "stix_bold", "stix_bold_italic",
         "serif_bold_italic")
_ONSETS = ("b", "c", "d", "f", "g", "k", "l", "m", "n", "p", "r", "s", "t", "v", "z", "br", "cr", "dr", "fl", "gr",
           "kl", "pr", "st", "tr", "sh", "ch", "th", "qu")
_VOWELS = ("a", "e", "i", "o", "u", "ai", "ea", "io", "ou", "y")
_CODAS = ("", "", "", "n", "r", "l", "s", "x", "m", "nd", "rk", "ss", "lt")
TAGLINES = ("Made with care", "Since 1958", "Simply better", "Everyday favourites", "Quality you can taste",
            "Good things inside", "The original", "Crafted daily", "Family recipe", "Pure & simple",
            "Proudly local", "Premium choice")
FLAVOURS = ("Wild Berry", "Sea Salt", "Smoky Paprika", "Honey Oat", "Double Cocoa", "Vanilla Bean", "Lemon Zest",
            "Cherry Blossom", "Forest Mint", "Toasted Almond", "Sweet Chili", "Mango Lime", "Black Pepper",
            "Blueberry", "Coconut", "Ginger Spice", "Maple Pecan", "Green Apple", "Salted Caramel", "Red Fruits",
            "Herb Garden", "Roasted Garlic", "Cinnamon", "Espresso", "Peach", "Raspberry", "Hazelnut", "Pistachio",
            "Original", "Light", "Extra Strong", "Classic", "Spicy Tomato", "Cheddar", "Onion & Chive", "Lavender",
            "Aloe Fresh", "Citrus Burst", "Dark Roast", "Fig & Walnut", "Sesame", "Barbecue", "Sour Cream",
            "Strawberry", "Pineapple", "Matcha", "Orange Blossom", "Cranberry")
BADGES = ("NEW", "NEW LOOK", "-20%", "BIO", "XL", "+25%", "BEST", "ECO")
KIND_NOUNS = {"book": "Journal", "card": "Card", "envelope": "Envelopes", "notebook": "Notebook",
              "chocolate": "Chocolate", "seeds": "Seeds", "magazine": "Magazine", "dvd": "Stories",
              "cereal": "Cereal", "tea": "Tea", "crackers": "Crackers", "toothpaste": "Toothpaste",
              "tissues": "Tissues", "pasta": "Pasta", "sugar": "Sugar", "crayons": "Crayons", "soap": "Soap",
              "pudding": "Pudding", "cookies": "Cookies"}
FLAT_KINDS = tuple(k for k in KINDS if k.shape in ("planar", "rectangular"))
_TRAINING_BRANDS = {b.name.lower() for b in BRANDS}


@dataclass(frozen=True)
class CatalogProduct:
    """One product of the catalogue: its print spec, its family (None: a single product), and how it differs
    from the family's first product (``change``: one of :data:`CHANGES`, None for the first) and the badge
    text of a ``redesign``."""

    spec: ProductSpec
    family: str | None = None
    change: str | None = None
    badge: str | None = None


def _hsv(h: float, s: float, v: float) -> tuple[int, int, int]:
    """An RGB colour of hue ``h`` in [0, 1), saturation and value in [0, 1]."""
    pixel = np.array([[[h * 180.0, s * 255.0, v * 255.0]]], dtype=np.float32)
    rgb = cv2.cvtColor(pixel.astype(np.uint8), cv2.COLOR_HSV2RGB)[0, 0]
    return int(rgb[0]), int(rgb[1]), int(rgb[2])


def make_brand(seed: int, index: int) -> Brand:
    """Brand ``index`` of a catalogue seed: a syllable name (never a training brand's), a palette of random hues,
    a typeface, a logo kind and a tagline."""
    rng = np.random.default_rng([int(seed), zlib.crc32(b"brand"), int(index)])
    while True:
        syllables = [str(rng.choice(_ONSETS)) + str(rng.choice(_VOWELS)) for _ in range(int(rng.integers(2, 4)))]
        word = "".join(syllables) + str(rng.choice(_CODAS))
        if word not in _TRAINING_BRANDS:
            break
    name = word.upper() if rng.random() < 0.4 else word.capitalize()
    hue = float(rng.random())
    main = _hsv(hue, float(rng.uniform(0.6, 1.0)), float(rng.uniform(0.35, 0.8)))
    second = _hsv((hue + float(rng.uniform(0.25, 0.75))) % 1.0, float(rng.uniform(0.4, 0.9)),
                  float(rng.uniform(0.6, 0.95)))
    accent = _hsv((hue + float(rng.uniform(-0.1, 0.1))) % 1.0, 0.35, 0.97)
    paper = _hsv(hue, float(rng.uniform(0.02, 0.1)), 0.97)
    ink = _hsv(hue, 0.6, 0.22)
    return Brand(name, Palette(main, second, accent, paper, ink), str(rng.choice(FONTS)), str(rng.choice(LOGO_KINDS)),
                 str(rng.choice(TAGLINES)))


class LookalikeCatalog:
    """``num_products`` held-out products with look-alike families (module docstring); builds products
    ``start..num_products - 1`` only (a chunk of :func:`load_lookalikes`).

    Args:
        num_products: products of the catalogue, 1 to :data:`MAX_PRODUCTS`.
        seed: selects brands, kinds, flavours, families and every detail of the prints.
        lookalike_share: share of the products that belong to a look-alike family, in [0, 1).
        family_size: ``(low, high)`` products per family, drawn uniformly, 2 <= low <= high.
        planes: canonical planes per product: 1 (front) or 2 (front and back).
        fill: the plane's longer side as a fraction of the image side.
        supersample: drawn at this multiple of the image size and area-averaged down (antialiasing).
        texture_px: the print's longer side in px before it is framed.
        start: the first product built.
    """

    def __init__(self, num_products: int, seed: int = 0, lookalike_share: float = 0.25,
                 family_size: tuple[int, int] = (2, 4), planes: int = 1, fill: float = 0.6, supersample: int = 2,
                 texture_px: int = 320, start: int = 0) -> None:
        check_lookalike_options(num_products, lookalike_share, family_size, planes)
        if not 0 <= int(start) <= int(num_products):
            raise ValueError(f"start={start} must be in [0, num_products={num_products}]")
        self.num_products, self.seed, self.start = int(num_products), int(seed), int(start)
        self.lookalike_share, self.family_size = float(lookalike_share), (int(family_size[0]), int(family_size[1]))
        self.planes, self.fill, self.supersample, self.texture_px = int(planes), float(fill), int(supersample), int(
            texture_px)

    def __repr__(self) -> str:
        return (f"LookalikeCatalog(num_products={self.num_products}, seed={self.seed}, lookalike_share="
                f"{self.lookalike_share}, family_size={list(self.family_size)}, planes={self.planes})")

    def with_range(self, start: int, stop: int) -> LookalikeCatalog:
        """The same catalogue's products ``start..stop - 1`` (a prefix of ``stop`` products, built from ``start``)."""
        return LookalikeCatalog(stop, self.seed, self.lookalike_share, self.family_size, self.planes, self.fill,
                                self.supersample, self.texture_px, start)

    # ------------------------------------------------------------------------------------ specs
    def products(self) -> list[CatalogProduct]:
        """All ``num_products`` products in catalogue order (cheap: no drawing)."""
        out: list[CatalogProduct] = []
        names: set[str] = set()
        family_products, unit = 0, 0
        while len(out) < self.num_products:
            rng = np.random.default_rng([self.seed, zlib.crc32(b"unit"), unit])
            family = family_products < self.lookalike_share * len(out)
            size = int(rng.integers(self.family_size[0], self.family_size[1] + 1)) if family else 1
            members = self._unit(rng, unit, size)
            for product in members[: self.num_products - len(out)]:
                name, k = product.spec.name, 2
                while name in names:
                    name, k = f"{product.spec.name}_{k}", k + 1
                names.add(name)
                out.append(dataclasses.replace(product, spec=dataclasses.replace(product.spec, name=name)))
            family_products += size if family else 0
            unit += 1
        return out

    def _unit(self, rng: np.random.Generator, unit: int, size: int) -> list[CatalogProduct]:
        """One single product (``size`` 1) or a family of ``size`` look-alikes."""
        brand = make_brand(self.seed, int(rng.integers(0, 8 + unit // 4)))  # brands grow with the catalogue
        kind = FLAT_KINDS[int(rng.integers(len(FLAT_KINDS)))]
        flavour = str(rng.choice(FLAVOURS))
        variant = str(rng.choice(list(VARIANTS)))
        sizes = kind.sizes or SIZES[kind.shape]
        pack = str(rng.choice(sizes))
        jitter = rng.uniform(0.85, 1.15, size=3)
        dims = tuple(float(round(d * j, 2)) for d, j in zip(kind.dims, jitter, strict=True))
        art = "photo_" + sorted(CATALOG_PHOTO_FILES)[int(rng.integers(len(CATALOG_PHOTO_FILES)))]
        seed = int(rng.integers(2**31))

        def spec(flavour: str, variant: str, pack: str, tag: str = "") -> ProductSpec:
            title = f"{flavour} {KIND_NOUNS[kind.name]}"
            name = slug(f"{brand.name} {title} {variant} {pack} {tag}")
            return ProductSpec(name=name, title=title, subtitle=pack, brand=brand, kind=kind.name, shape=kind.shape,
                               style=kind.style, dims=dims, variant=VARIANTS[variant], art=art,  # type: ignore[arg-type]
                               seed=seed)

        first = spec(flavour, variant, pack)
        if size == 1:
            return [CatalogProduct(first)]
        family = slug(f"{brand.name} {first.title} {unit}")
        members = [CatalogProduct(first, family)]
        changes = [CHANGES[int(i) % len(CHANGES)] for i in rng.permutation(max(size - 1, len(CHANGES)))][: size - 1]
        used = {"flavour": {flavour}, "colour": {variant}, "size": {pack}, "redesign": set()}  # no two twins alike
        for change in changes:
            if change == "flavour":
                other = str(rng.choice([f for f in FLAVOURS if f not in used[change]]))
                members.append(CatalogProduct(spec(other, variant, pack), family, change))
            elif change == "colour":
                other = str(rng.choice([v for v in VARIANTS if v not in used[change]]))
                members.append(CatalogProduct(spec(flavour, other, pack), family, change))
            elif change == "size":
                other = str(rng.choice([s for s in (*sizes, *SIZES[kind.shape]) if s not in used[change]]))
                members.append(CatalogProduct(spec(flavour, variant, other), family, change))
            else:
                other = str(rng.choice([b for b in BADGES if b not in used[change]]))
                members.append(CatalogProduct(spec(flavour, variant, pack, other), family, change, other))
            used[change].add(other)
        return members

    # ------------------------------------------------------------------------------------ images
    def cache_key(self) -> dict[str, Any]:
        """Everything that determines the images of products ``start..num_products - 1``."""
        from matl.data.catalog import _package_version

        return {"type": "lookalike_catalog", "generator": GENERATOR_VERSION, "seed": self.seed,
                "start": self.start, "stop": self.num_products, "lookalike_share": self.lookalike_share,
                "family_size": list(self.family_size), "planes": self.planes, "fill": self.fill,
                "supersample": self.supersample, "texture_px": self.texture_px,
                "assets": f"matplotlib-{_package_version('matplotlib')}-skimage-{_package_version('scikit-image')}"}

    def prints(self, product: CatalogProduct) -> list[tuple[str, Image.Image]]:
        """The product's planes as ``(name, RGB print)``: the front (with a redesign's badge), then the back."""
        spec = product.spec
        w, h = spec.dims[0], spec.dims[2]
        scale = self.texture_px / max(w, h)
        size = (max(round(w * scale), 16), max(round(h * scale), 16))
        front = compose(spec, "front", size)
        if product.badge:
            front = draw_badge(front, product.badge, np.random.default_rng([spec.seed, zlib.crc32(b"badge")]))
        planes = [("front", front)]
        if self.planes == 2:
            planes.append(("back", compose(spec, "back", size)))
        return planes

    def frame(self, image: Image.Image, image_size: int) -> tuple[np.ndarray, np.ndarray]:
        """A print centred in an ``image_size`` square on black, its longer side at :attr:`fill`: ``(S, S, 3)``
        uint8 and the ``(S, S)`` bool mask (pixels at least half covered)."""
        big = image_size * self.supersample
        scale = self.fill * big / max(image.size)
        w, h = max(round(image.size[0] * scale), 1), max(round(image.size[1] * scale), 1)
        x0, y0 = (big - w) // 2, (big - h) // 2
        canvas = np.zeros((big, big, 3), np.float32)
        cover = np.zeros((big, big), np.float32)
        canvas[y0:y0 + h, x0:x0 + w] = np.asarray(image.resize((w, h), Image.Resampling.LANCZOS), np.float32)
        cover[y0:y0 + h, x0:x0 + w] = 1.0
        small = cv2.resize(canvas, (image_size, image_size), interpolation=cv2.INTER_AREA)
        mask = cv2.resize(cover, (image_size, image_size), interpolation=cv2.INTER_AREA) >= 0.5
        return np.clip(np.rint(small), 0, 255).astype(np.uint8), mask

    def build(self, image_size: int) -> CanonicalSet:
        """The canonical planes of products ``start..num_products - 1`` at ``image_size`` px."""
        products = self.products()[self.start:]
        images, masks, plane_object, plane_names = [], [], [], []
        for i, product in enumerate(products):
            for name, image in self.prints(product):
                pixels, mask = self.frame(image, image_size)
                images.append(pixels)
                masks.append(mask)
                plane_object.append(i)
                plane_names.append(name)
        return CanonicalSet(images=np.stack(images), masks=np.stack(masks),
                            plane_object=np.asarray(plane_object, dtype=np.int64), plane_names=plane_names,
                            object_names=[p.spec.name for p in products],
                            object_shapes=[p.spec.shape for p in products])


def draw_badge(image: Image.Image, text: str, rng: np.random.Generator) -> Image.Image:
    """A redesign's mark: a star burst with ``text`` in a corner of the front print (a copy)."""
    out = image.copy()
    draw = ImageDraw.Draw(out)
    w, h = out.size
    r = 0.13 * min(w, h) * float(rng.uniform(0.9, 1.2))
    cx = r * 1.15 if rng.random() < 0.5 else w - r * 1.15
    cy = r * 1.15 if rng.random() < 0.5 else h - r * 1.15
    colour = ((230, 40, 40), (250, 200, 20), (40, 160, 70), (30, 90, 200))[int(rng.integers(4))]
    draw.polygon(star_points(cx, cy, r, r * 0.8, 12), fill=colour, outline=INK)
    ink = INK if colour[1] > 150 and colour[0] > 200 else WHITE
    draw_text(draw, (cx - r * 0.62, cy - r * 0.4, cx + r * 0.62, cy + r * 0.4), text, "sans_bold", ink)
    return floor_ink(out)


def check_lookalike_options(num_products: Any, lookalike_share: Any, family_size: Any, planes: Any) -> None:
    """One-line errors for options the generator cannot make (:class:`ValueError`)."""
    if not isinstance(num_products, (int, np.integer)) or isinstance(num_products, bool) or not (
            1 <= num_products <= MAX_PRODUCTS):
        raise ValueError(f"num_products={num_products} is invalid: the catalogue holds 1 to {MAX_PRODUCTS} products")
    if not isinstance(lookalike_share, (int, float)) or isinstance(lookalike_share, bool) or not (
            0.0 <= lookalike_share < 1.0):
        raise ValueError(f"lookalike_share={lookalike_share} is invalid: use a fraction in [0, 1)")
    ok = (isinstance(family_size, (list, tuple)) and len(family_size) == 2
          and all(isinstance(v, int) and not isinstance(v, bool) for v in family_size)
          and 2 <= family_size[0] <= family_size[1] <= 12)
    if not ok:
        raise ValueError(f"family_size={list(family_size) if isinstance(family_size, tuple) else family_size} is "
                         "invalid: use [low, high] with 2 <= low <= high <= 12")
    if planes not in (1, 2) or isinstance(planes, bool):
        raise ValueError(f"planes={planes} is invalid: use 1 (front) or 2 (front and back)")


def load_lookalikes(catalog: LookalikeCatalog, image_size: int, cache_dir: str | Path) -> CanonicalSet:
    """The canonical set of all of ``catalog``'s products at ``image_size`` px, built and cached in chunks of
    :data:`CHUNK` products (:func:`~matl.data.canonical.load_canonical`): a larger catalogue reuses a smaller
    one's chunks; only its last, partial chunk is its own."""
    parts = [load_canonical(catalog.with_range(start, min(start + CHUNK, catalog.num_products)), image_size, cache_dir)
             for start in range(0, catalog.num_products, CHUNK)]
    offsets = np.cumsum([0] + [p.num_objects for p in parts])
    return CanonicalSet(images=np.concatenate([p.images for p in parts]),
                        masks=np.concatenate([p.masks for p in parts]),
                        plane_object=np.concatenate([p.plane_object + o for p, o in zip(parts, offsets, strict=False)]),
                        plane_names=[n for p in parts for n in p.plane_names],
                        object_names=[n for p in parts for n in p.object_names],
                        object_shapes=[s for p in parts for s in p.object_shapes])
