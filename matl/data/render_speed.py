"""Render throughput of a mesh-based source on this machine: :func:`render_images_per_s`.

Used by ``python -m matl.bench`` (``render_images_per_s`` in ``bench.json``) and by
``python -m matl.render speed=true`` (``speed.json``); see ``docs/speed.md``.
"""

from __future__ import annotations

import time
from typing import TYPE_CHECKING

import numpy as np

from matl.data.canonical import ModelSource
from matl.data.view_sampler import ViewSampler, bounding_box_corners

if TYPE_CHECKING:
    from matl.data.catalog.shapes import ProductModel

RENDER_KINDS = ("canonical", "views")


def _pick_models(source: ModelSource, indices: list[int]) -> tuple[list[ProductModel], float]:
    """The models of objects ``indices`` and the seconds spent building them (for the catalog only
    those are built; other sources build every model up to the last index, but only the chosen
    ones are timed). A source with fewer objects than ``indices`` asks for gives all it has."""
    from matl.data.catalog.models import product_model

    wanted = set(indices)
    models, seconds = [], 0.0
    if hasattr(source, "products") and hasattr(source, "texture_px"):
        specs = source.products()
        for i in indices:
            start = time.perf_counter()
            models.append(product_model(specs[i], source.texture_px))
            seconds += time.perf_counter() - start
        return models, seconds
    it = iter(source.models())
    for i in range(max(indices) + 1):
        start = time.perf_counter()
        model = next(it, None)
        if model is None:  # e.g. views=K of a 2-object mesh folder: num_objects defaults to 3
            break
        if i in wanted:
            seconds += time.perf_counter() - start
            models.append(model)
    return models, seconds


def render_images_per_s(
    source: ModelSource | None = None,
    image_size: int = 100,
    kind: str = "canonical",
    num_objects: int = 4,
    views_per_plane: int = 8,
    sampler: ViewSampler | None = None,
) -> dict[str, float]:
    """Render throughput on this machine, for ``matl.bench`` and the docs.

    Renders the planes of ``num_objects`` objects spread evenly over ``source`` (default: the
    ``synthetic_arc`` catalog, so every shape is represented) and times them with
    ``time.perf_counter``. GL context creation and first-use shader compilation are excluded;
    building the models (for the catalog: composing the label textures) is timed separately.

    Args:
        kind: "canonical" (one orthographic view per plane) or "views" (``views_per_plane`` random
            perspective views per plane, as the rendered-query pool; includes computing each
            plane's offset and sampling the cameras).
    Returns:
        ``{"images", "render_seconds", "images_per_s", "model_seconds", "images_per_s_with_models"}``.
    """
    from matl.data.catalog import SyntheticCatalog
    from matl.data.catalog.rendering import ViewRenderer, plane_half_width  # pyrender sets up OpenGL on import

    if kind not in RENDER_KINDS:
        raise ValueError(f"kind must be 'canonical' or 'views', got {kind!r}")
    source = source if source is not None else SyntheticCatalog("arc")
    sampler = sampler or ViewSampler()
    total = int(getattr(source, "num_objects", 0) or num_objects)
    indices = sorted(set(np.linspace(0, total - 1, min(num_objects, total)).round().astype(int).tolist()))
    models, model_seconds = _pick_models(source, indices)
    n = 0
    with ViewRenderer(image_size, source.supersample) as views:
        views.plane_offsets(models[0], source.fill)  # warm-up: first-use shader compilation is not throughput
        start = time.perf_counter()
        for model in models:
            if kind == "canonical":
                n += len(views.canonical(model, source.fill)[0])
                continue
            offsets = views.plane_offsets(model, source.fill)
            box = bounding_box_corners(model)
            for i, (plane, offset) in enumerate(zip(model.planes, offsets, strict=True)):
                half = plane_half_width(plane, source.fill)
                cams, _ = sampler.sample(plane, float(offset), half, box, image_size, views_per_plane,
                                         np.random.default_rng(i))
                n += len(views.render(model, cams)[0])
        seconds = time.perf_counter() - start
    return {
        "images": float(n),
        "render_seconds": seconds,
        "images_per_s": n / max(seconds, 1e-9),
        "model_seconds": model_seconds,
        "images_per_s_with_models": n / max(seconds + model_seconds, 1e-9),
    }
