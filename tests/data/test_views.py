"""Run configs saved before the rendered-view code was split still instantiate (matl.eval run=<old run>)."""

from __future__ import annotations

import hydra
from omegaconf import OmegaConf

from matl.data.anchors import PhotoAnchors, RenderedRandomAnchors
from matl.data.queries import RenderedQueries
from matl.data.view_sampler import ViewSampler


def test_old_targets_instantiate() -> None:
    saved = OmegaConf.create({
        "views": {"_target_": "matl.data.views.RenderedQueries", "views_per_plane": 12,
                  "sampler": {"_target_": "matl.data.views.ViewSampler", "tilt_deg": [0.0, 20.0]}},
        "anchors": {"_target_": "matl.data.views.RenderedRandomAnchors",
                    "sampler": {"_target_": "matl.data.views.ViewSampler", "translation": [0.0, 0.0]}},
        "photos": {"_target_": "matl.data.photos.PhotoAnchors"},
    })  # fmt: skip
    views = hydra.utils.instantiate(saved.views)
    assert type(views) is RenderedQueries and views.views_per_plane == 12
    assert type(views.sampler) is ViewSampler and views.sampler.tilt_deg == (0.0, 20.0)
    anchors = hydra.utils.instantiate(saved.anchors)
    assert type(anchors) is RenderedRandomAnchors and anchors.sampler.translation == (0.0, 0.0)
    assert type(hydra.utils.instantiate(saved.photos)) is PhotoAnchors
