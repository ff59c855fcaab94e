"""The textured 3D model of any catalog product: :func:`product_model`.

Simple shapes (planar, rectangular, cylindrical) are built by :mod:`.shapes`; non-planar ones
(bottles, mugs, pouches, ...) by :mod:`.nonplanar`, which builds on the simple shapes' parts.
"""

from __future__ import annotations

from collections.abc import Callable

from matl.data.catalog.nonplanar import nonplanar_model
from matl.data.catalog.products import ProductSpec
from matl.data.catalog.shapes import ProductModel, box_model, cylinder_model

_BUILDERS: dict[str, Callable[[ProductSpec, int], ProductModel]] = {
    "planar": box_model,
    "rectangular": box_model,
    "cylindrical": cylinder_model,
    "nonplanar": nonplanar_model,
}


def product_model(spec: ProductSpec, texture_px: int = 512) -> ProductModel:
    """Textured mesh parts and canonical planes of ``spec``; textures have ``texture_px`` on the
    long side of each face (twice that for a cylinder's wrap-around label)."""
    if spec.shape not in _BUILDERS:
        raise ValueError(f"unknown product shape {spec.shape!r}; valid: {sorted(_BUILDERS)}")
    model = _BUILDERS[spec.shape](spec, texture_px)
    return ProductModel(model.parts, model.planes, spec.name)
