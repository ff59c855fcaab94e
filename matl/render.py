"""``python -m matl.render data=<dataset>``: build the canonical images of any dataset.

Datasets: ``synthetic_arc``, ``synthetic_ycb``, ``synthetic_ycb_table2``, ``synthetic_apc``, and the
user's ``ycb``, ``apc``, ``arc``, ``meshes`` (set ``data.source.root=...``) and ``images``.
Instantiates ``data.source``, builds (or loads) its canonical-image cache at ``data.image_size``
under ``paths.cache_dir`` with a progress bar, prints object and plane counts per shape, and saves
a contact sheet of every plane as ``gallery.png`` in the run folder. With ``views=K`` (mesh-based
datasets) it also renders K random views of every plane, as ``data.queries=rendered`` would, into
``views.png`` (a sample of objects), with the measured render throughput. With ``speed=true`` it
measures the canonical and view render throughput (``speed_objects`` objects, ``speed_views``
views per plane) and writes it to ``speed.json``. The work is :mod:`matl.data.prepare`'s.

A missing or corrupt mesh, texture or image, an unset ``data.source.root`` or an invalid option is
reported as one line, ``error: <message naming the file or key>``, with exit status 2.
"""

from __future__ import annotations

import json
from pathlib import Path

from omegaconf import DictConfig

from matl.utils.cli import command


@command("render")
def main(cfg: DictConfig) -> None:
    from rich.console import Console

    from matl.data.prepare import build_canonical, instantiate_source, render_speed, render_views
    from matl.utils.config import validate_config
    from matl.utils.io import write_json

    validate_config(cfg)
    source = instantiate_source(cfg)
    console = Console()
    size, out_dir = int(cfg.data.image_size), Path(cfg.paths.output_dir)
    build_canonical(source, size, cfg.paths.cache_dir, out_dir, console)
    if int(cfg.get("views") or 0) > 0:
        render_views(source, size, int(cfg.views), out_dir, console)
    if cfg.get("speed"):
        speed = render_speed(source, size, int(cfg.speed_objects), int(cfg.speed_views))
        write_json(out_dir / "speed.json", speed)
        console.print(json.dumps(speed, indent=2))
        console.print(f"render throughput -> {out_dir / 'speed.json'}")


if __name__ == "__main__":
    main()
