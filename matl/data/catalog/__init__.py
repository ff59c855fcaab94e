"""Embedded procedural product catalog: the default, download-free dataset.

``SyntheticCatalog`` is a :class:`~matl.data.canonical.CanonicalSource`: it samples products
(:mod:`.products`, and the non-planar ones of :mod:`.nonplanar`), prints their faces
(:mod:`.labels`), builds textured meshes (:mod:`.models`) and renders every canonical plane
offscreen (:mod:`.rendering`). Used from Hydra as ``_target_: matl.data.catalog.SyntheticCatalog``;
see ``docs/datasets.md``.
"""

from __future__ import annotations

import dataclasses
import zlib
from collections.abc import Iterator
from importlib import metadata
from typing import TYPE_CHECKING, Any

import matplotlib
import numpy as np

from matl.data.canonical import CanonicalSet, ProgressFn
from matl.data.catalog.contact_sheet import contact_sheet
from matl.data.catalog.drawing import PHOTO_POOLS, TRAINING_PHOTO_POOL
from matl.data.catalog.models import product_model
from matl.data.catalog.nonplanar import NONPLANAR_COMPOSITION, PLANES_PER_FORM, sample_nonplanar
from matl.data.catalog.products import CATALOG_COMPOSITIONS, SHAPES, ProductSpec, sample_products
from matl.utils.config import SYNTHETIC_CATALOGS

if TYPE_CHECKING:
    from matl.data.catalog.shapes import ProductModel

# Bump when anything changes what a given (catalog, seed, ...) looks like, so caches rebuild.
GENERATOR_VERSION = 1
# Version of the non-planar generator; only in the cache key of sets that contain non-planar objects,
# so the simple catalogs' caches stay valid.
NONPLANAR_VERSION = 1

PLANES_PER_SHAPE: dict[str, int] = {"planar": 2, "rectangular": 6, "cylindrical": 10}

# Table 2 (Sec. 5.8): 11 simple ("planar" in the paper's sense) and 23 non-planar objects. The
# simple ones are the first objects of each shape of synthetic_ycb, so they look exactly alike there.
TABLE2_SIMPLE: dict[str, int] = {"planar": 2, "rectangular": 5, "cylindrical": 4}
CATALOGS = SYNTHETIC_CATALOGS
SUBSETS = ("planar", "nonplanar", "all")

__all__ = [
    "CATALOGS",
    "CATALOG_COMPOSITIONS",
    "PLANES_PER_SHAPE",
    "SHAPES",
    "SUBSETS",
    "TABLE2_SIMPLE",
    "SyntheticCatalog",
    "contact_sheet",
]


def _package_version(name: str) -> str:
    try:
        return metadata.version(name)
    except metadata.PackageNotFoundError:
        return "missing"


class SyntheticCatalog:
    """Procedural catalog shaped like the paper's ARC, YCB or APC set (Sec. 5.1), or YCB's Table 2 split.

    Args:
        catalog: "arc" (34 objects, 152 planes), "ycb" (34, 240; plus 23 non-planar objects),
            "apc" (17, 90), or "ycb_table2" (11 simple objects of "ycb" and its 23 non-planar ones).
        seed: selects the products and every detail of their prints.
        fill: fraction of the image width covered by each plane's larger extent.
        supersample: render at ``supersample * image_size`` and area-average down (antialiasing).
        texture_px: texture resolution on the long side of a face (a cylinder label gets twice).
        subset: "planar" (the simple shapes: planar, rectangular, cylindrical, as the paper's
            Sec. 5.8 calls them), "nonplanar" (bottles, mugs, ...; only "ycb" and "ycb_table2"
            have any) or "all" (simple objects first, then non-planar). The default keeps the
            catalogs of ``docs/datasets.md`` (synthetic_ycb: 34 objects, 240 planes).
        photos: the photo pool of the product art. ``"matplotlib"`` (default): the training
            catalogs, whose art mixes procedural pictures with matplotlib's sample photos.
            ``"skimage"``: the held-out benchmark variant, whose every product picture is a crop
            of one of scikit-image's bundled photos (:data:`~matl.data.catalog.drawing.HELDOUT_PHOTO_FILES`),
            dealt to the products in a seeded order; never trained on (``matl.train`` refuses it).
    """

    def __init__(
        self,
        catalog: str = "arc",
        seed: int = 0,
        fill: float = 0.6,
        supersample: int = 2,
        texture_px: int = 512,
        subset: str = "planar",
        photos: str = TRAINING_PHOTO_POOL,
    ) -> None:
        if catalog not in CATALOGS:
            raise ValueError(f"unknown catalog {catalog!r}; valid: {sorted(CATALOGS)}")
        if subset not in SUBSETS:
            raise ValueError(f"data.source.subset={subset!r} is invalid; valid: {list(SUBSETS)}")
        if subset == "nonplanar" and catalog not in ("ycb", "ycb_table2"):
            raise ValueError(f"catalog {catalog!r} has no non-planar objects (only ycb and ycb_table2 have)")
        if photos not in PHOTO_POOLS:
            raise ValueError(f"data.source.photos={photos!r} is invalid; valid: {list(PHOTO_POOLS)}")
        if not 0.0 < fill <= 1.0:
            raise ValueError(f"fill must be in (0, 1], got {fill}")
        if int(supersample) < 1:
            raise ValueError(f"supersample must be >= 1, got {supersample}")
        if int(texture_px) < 32:
            raise ValueError(f"texture_px must be >= 32, got {texture_px}")
        self.catalog = catalog
        self.seed = int(seed)
        self.fill = float(fill)
        self.supersample = int(supersample)
        self.texture_px = int(texture_px)
        self.subset = subset
        self.photos = photos

    def __repr__(self) -> str:
        sub = "" if self.subset == "planar" else f", subset={self.subset!r}"
        if self.photos != TRAINING_PHOTO_POOL:
            sub += f", photos={self.photos!r}"
        return (
            f"SyntheticCatalog(catalog={self.catalog!r}, seed={self.seed}, fill={self.fill}, "
            f"supersample={self.supersample}, texture_px={self.texture_px}{sub})"
        )

    def _composition(self) -> tuple[dict[str, int], dict[str, int]]:
        """Objects per simple shape and per non-planar form in this set."""
        simple = dict(TABLE2_SIMPLE) if self.catalog == "ycb_table2" else dict(CATALOG_COMPOSITIONS[self.catalog])
        nonplanar = dict(NONPLANAR_COMPOSITION) if self.catalog in ("ycb", "ycb_table2") else {}
        if self.subset == "planar":
            nonplanar = {}
        elif self.subset == "nonplanar":
            simple = {}
        return simple, nonplanar

    @property
    def num_objects(self) -> int:
        """Objects in the catalog, known without rendering."""
        simple, nonplanar = self._composition()
        return sum(simple.values()) + sum(nonplanar.values())

    @property
    def num_planes(self) -> int:
        """Canonical planes in the catalog, known without rendering."""
        simple, nonplanar = self._composition()
        return sum(n * PLANES_PER_SHAPE[s] for s, n in simple.items()) + sum(
            n * PLANES_PER_FORM[f] for f, n in nonplanar.items()
        )

    def products(self) -> list[ProductSpec]:
        """The sampled product specifications, in object order: simple shapes grouped by shape,
        then the non-planar products grouped by form."""
        simple, nonplanar = self._composition()
        specs: list[ProductSpec] = []
        if simple:
            base = sample_products("ycb" if self.catalog == "ycb_table2" else self.catalog, self.seed)
            for shape in SHAPES:
                specs += [s for s in base if s.shape == shape][: simple.get(shape, 0)]
        if nonplanar:
            specs += sample_nonplanar(self.seed)
        if self.photos != TRAINING_PHOTO_POOL:
            specs = self._photo_art(specs)
        return specs

    def _photo_art(self, specs: list[ProductSpec]) -> list[ProductSpec]:
        """Every product's picture becomes a photo of :attr:`photos`' pool, dealt round-robin in a seeded
        order (each photo printed by about as many products; each product crops it its own way)."""
        names = sorted(PHOTO_POOLS[self.photos])
        order = np.random.default_rng([self.seed, zlib.crc32(f"photos/{self.photos}".encode())]).permutation(len(specs))
        return [dataclasses.replace(s, art=f"photo_{names[int(order[i]) % len(names)]}") for i, s in enumerate(specs)]

    def models(self) -> Iterator[ProductModel]:
        """The textured model of every object, in object order (for rendered views, which need the
        3D objects and not only their canonical images)."""
        for spec in self.products():
            yield product_model(spec, self.texture_px)

    def cache_key(self) -> dict[str, Any]:
        """Everything that determines the images (fonts and photos come from matplotlib, so its
        version is part of the key)."""
        key: dict[str, Any] = {
            "type": "synthetic_catalog",
            "generator": GENERATOR_VERSION,
            "catalog": self.catalog,
            "seed": self.seed,
            "fill": self.fill,
            "supersample": self.supersample,
            "texture_px": self.texture_px,
            "assets": f"matplotlib-{matplotlib.__version__}",
        }
        # Added only off the default, so the caches of the original catalogs keep their keys.
        if self.subset != "planar" or self.catalog == "ycb_table2":
            key["subset"] = self.subset
        if self._composition()[1]:
            key["nonplanar"] = NONPLANAR_VERSION
        if self.photos != TRAINING_PHOTO_POOL:  # the held-out pool's files come from scikit-image
            key["photos"] = f"{self.photos}-{_package_version('scikit-image')}"
        return key

    def build(self, image_size: int, progress: ProgressFn | None = None) -> CanonicalSet:
        """Render all canonical planes at ``image_size`` px.

        ``progress(planes_done, planes_total)`` is called after each object's planes are rendered.
        """
        # Imported here: pyrender sets up OpenGL at import, which spec-only users never need.
        from matl.data.catalog.rendering import CanonicalRenderer

        specs = self.products()
        images: list[np.ndarray] = []
        masks: list[np.ndarray] = []
        plane_object: list[int] = []
        plane_names: list[str] = []
        total = self.num_planes
        with CanonicalRenderer(image_size, self.supersample, self.fill) as renderer:
            for i, model in enumerate(self.models()):  # models() builds from the same specs, in order
                imgs, msks = renderer.render(model)
                images.append(imgs)
                masks.append(msks)
                plane_object += [i] * len(model.planes)
                plane_names += [p.name for p in model.planes]
                if progress is not None:
                    progress(len(plane_names), total)
        return CanonicalSet(
            images=np.concatenate(images),
            masks=np.concatenate(masks),
            plane_object=np.asarray(plane_object, dtype=np.int64),
            plane_names=plane_names,
            object_names=[s.name for s in specs],
            object_shapes=[s.shape for s in specs],
        )
