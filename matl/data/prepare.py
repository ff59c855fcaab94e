"""Preparing a dataset before training: what ``python -m matl.render`` does, as library functions.

* :func:`instantiate_source`: ``data.source`` of a composed config, user mistakes as one line.
* :func:`build_canonical`: build (or load) the canonical-image cache with a progress bar, print
  the object and plane counts per shape, write a contact sheet of every plane (``gallery.png``).
* :func:`render_views`: a preview of rendered views, as ``data.queries=rendered`` makes them
  (``views.png``), with the view render throughput.
* :func:`render_speed`: canonical and view render throughput of a source (``speed.json``).
"""

from __future__ import annotations

import logging
import time
from collections import Counter
from pathlib import Path
from typing import Any

import hydra
import numpy as np
from hydra.errors import InstantiationException
from omegaconf import DictConfig
from omegaconf.errors import MissingMandatoryValue
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from matl.data.canonical import CanonicalSet, CanonicalSource, cache_path, load_canonical, require_models
from matl.data.catalog.contact_sheet import contact_sheet
from matl.data.render_speed import RENDER_KINDS, render_images_per_s
from matl.data.view_sampler import ViewSampler, bounding_box_corners
from matl.utils.errors import MatlError

log = logging.getLogger(__name__)


def instantiate_source(cfg: DictConfig) -> CanonicalSource:
    """``data.source`` instantiated, user mistakes turned into one-line :class:`MatlError` s."""
    try:
        return hydra.utils.instantiate(cfg.data.source)
    except MissingMandatoryValue as e:
        key = f"data.source.{getattr(e, 'key', None) or 'root'}"
        raise MatlError(f"{key} is not set: pass {key}=<path> (see docs/datasets.md)") from None
    except InstantiationException as e:
        cause = e.__cause__
        if isinstance(cause, (MatlError, ValueError, TypeError, FileNotFoundError)):
            raise MatlError(" ".join(str(cause).split())) from None
        raise


def shape_counts(cs: CanonicalSet) -> dict[str, tuple[int, int]]:
    """``{shape: (objects, planes)}`` of a canonical set, shapes in order of first appearance."""
    objects = Counter(cs.object_shapes)
    planes = Counter(cs.object_shapes[int(o)] for o in cs.plane_object)
    return {s: (objects[s], planes[s]) for s in dict.fromkeys(cs.object_shapes)}


def build_canonical(
    source: CanonicalSource, image_size: int, cache_dir: str | Path, out_dir: str | Path, console: Console | None = None
) -> CanonicalSet:
    """Build or load the canonical set of ``source``; print its counts; write ``gallery.png``
    into ``out_dir``. Returns the set."""
    console = console or Console()
    path = cache_path(source, image_size, cache_dir)
    cached = path.exists()
    start = time.perf_counter()
    columns = (
        TextColumn("[bold]rendering"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("planes"),
        TimeElapsedColumn(),
    )
    with Progress(*columns, console=console, transient=False, disable=cached) as progress:
        task = progress.add_task("render", total=None)

        def on_progress(done: int, total: int) -> None:
            progress.update(task, completed=done, total=total)

        cs = load_canonical(source, image_size, cache_dir, progress=on_progress)
    seconds = time.perf_counter() - start
    verb = "loaded from cache" if cached else f"built in {seconds:.1f} s"
    console.print(f"{source!r}: {verb} -> {path}")

    table = Table(title=f"{cs.image_size} px canonical images")
    for col in ("shape", "objects", "planes"):
        table.add_column(col, justify="left" if col == "shape" else "right")
    for shape, (n_obj, n_planes) in shape_counts(cs).items():
        table.add_row(shape, str(n_obj), str(n_planes))
    table.add_row("[bold]total", f"[bold]{cs.num_objects}", f"[bold]{cs.num_planes}")
    console.print(table)

    sheet = Path(out_dir) / "gallery.png"
    contact_sheet(cs, sheet)
    console.print(f"contact sheet -> {sheet}")
    log.info("render: %d objects, %d planes, %s; sheet %s", cs.num_objects, cs.num_planes, verb, sheet)
    return cs


def render_views(source: CanonicalSource, image_size: int, views: int, out_dir: str | Path, console: Console,
                 max_objects: int = 6) -> dict[str, float]:
    """Render ``views`` random views (the ``data.views`` sampler's defaults) of every plane of the
    first ``max_objects`` objects, save them as ``views.png`` (one row per plane: the canonical
    image, then its views), return the throughput from :func:`render_images_per_s`."""
    from PIL import Image

    from matl.data.catalog.rendering import ViewRenderer, plane_half_width  # pyrender sets up OpenGL on import

    source = require_models(source, "views=K")
    sampler = ViewSampler()
    rows = []
    with ViewRenderer(image_size, source.supersample) as renderer:
        for o, model in enumerate(source.models()):
            if o >= max_objects:
                break
            canon, _, offsets = renderer.canonical(model, source.fill)
            for p, plane in enumerate(model.planes):
                cams, _ = sampler.sample(plane, float(offsets[p]), plane_half_width(plane, source.fill),
                                         bounding_box_corners(model), image_size, views,
                                         np.random.default_rng([o, p]))  # fmt: skip
                imgs, _ = renderer.render(model, cams)
                gap = np.full((image_size, 4, 3), 60, np.uint8)
                rows.append(np.concatenate([canon[p], gap, *[np.concatenate([v, gap], 1) for v in imgs]], 1))
    sheet = Path(out_dir) / "views.png"
    Image.fromarray(np.concatenate([np.pad(r, ((0, 4), (0, 0), (0, 0)), constant_values=60) for r in rows])).save(sheet)
    speed = render_images_per_s(source, image_size, "views", num_objects=min(max_objects, 3), views_per_plane=views)
    console.print(f"rendered views (canonical first, then {views} views per plane) -> {sheet}")
    console.print(f"view render throughput: {speed['images_per_s']:.1f} images/s "
                  f"({speed['images_per_s_with_models']:.1f} including building the models)")
    return speed


def render_speed(source: CanonicalSource, image_size: int, num_objects: int = 8,
                 views_per_plane: int = 8) -> dict[str, Any]:
    """Canonical and view render throughput of ``num_objects`` objects spread over ``source``
    (:func:`render_images_per_s` of each kind), with what was measured."""
    source = require_models(source, "speed=true")
    if num_objects < 1 or views_per_plane < 1:
        raise MatlError(f"speed_objects={num_objects} and speed_views={views_per_plane} must be >= 1")
    out: dict[str, Any] = {"source": repr(source), "image_size": int(image_size), "objects": int(num_objects),
                           "views_per_plane": int(views_per_plane)}  # fmt: skip
    for kind in RENDER_KINDS:
        out[kind] = render_images_per_s(source, image_size, kind, num_objects, views_per_plane)
    return out
