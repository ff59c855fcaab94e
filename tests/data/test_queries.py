"""Query sources: warped (the paper's) and rendered queries, and how data.queries picks one."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
import torch

from matl.data.canonical import CanonicalSet, require_models
from matl.data.datamodule import TripletDataModule
from matl.data.queries import QuerySource, RenderedQueries, WarpedQueries, make_query_source
from matl.data.streams import stream_generator
from matl.geometry import HomographySampler, warp_image
from matl.utils.errors import MatlError
from tests.data.conftest import PatternSource, TinyCatalog

SIZE = 32


def make_dm(source: Any, cache: Path, **kw: Any) -> TripletDataModule:
    dm = TripletDataModule(source, image_size=SIZE, num_anchors=4, train_triplets=40, val_queries=8, test_queries=20,
                           batch_size=8, eval_batch_size=10, seed=0, cache_dir=cache, **kw)  # fmt: skip
    dm.setup()
    return dm


def test_make_query_source() -> None:
    homography = HomographySampler(focal=2.0)
    warped = make_query_source("warped", None, homography)
    assert isinstance(warped, WarpedQueries) and warped.homography is homography
    assert isinstance(make_query_source(None), WarpedQueries)
    views = RenderedQueries(views_per_plane=6)
    assert make_query_source("rendered", views) is views
    built = make_query_source("rendered", {"_target_": "ignored", "views_per_plane": 5, "sampler": {"focal": 2.0}})
    assert isinstance(built, RenderedQueries) and built.views_per_plane == 5 and built.sampler.focal == 2.0
    assert make_query_source(views) is views and isinstance(views, QuerySource)
    with pytest.raises(MatlError, match=r"data.queries='photos' is invalid"):
        make_query_source("photos")


def test_warped_queries_are_the_canonical_images_warped(tmp_path: Path) -> None:
    dm = make_dm(PatternSource(), tmp_path)
    assert isinstance(dm.query_source, WarpedQueries)
    # the test split, drawn by hand from its stream: a plane per query, then its homographies
    g = stream_generator(0, "test")
    plane = torch.randint(12, (20,), generator=g)
    H = dm.homography.sample(20, (SIZE, SIZE), g, dm.footprints[plane])
    assert torch.equal(dm.test_set.params["plane"], plane)
    assert torch.equal(dm.test_set.params["query_H_canon"], H.float())
    batch = dm.materialize({k: v[:5] for k, v in dm.test_set.params.items()})
    assert torch.equal(batch["query"], warp_image(dm.canon_images[plane[:5]], H[:5].float()))
    # triplets: positives and negatives both start from the train stream's state
    train = dm.train_set.params
    g = stream_generator(0, "train")
    assert torch.equal(train["plane"], torch.randint(12, (40,), generator=g))
    assert (train["object"] != train["neg_object"]).all()
    triplets = dm.materialize({k: v[:4] for k, v in train.items()})
    assert torch.equal(triplets["negative"], warp_image(dm.canon_images[train["neg_plane"][:4]],
                                                        train["neg_H_canon"][:4]))  # fmt: skip
    assert torch.equal(triplets["anchors"], dm.anchor_images[train["plane"][:4]])


def test_datamodule_with_rendered_queries(tiny: TinyCatalog, tmp_path: Path) -> None:
    views = RenderedQueries(views_per_plane=6, val_fraction=0.2, test_fraction=0.34)
    dm = make_dm(tiny, tmp_path, queries="rendered", views=views)
    assert dm.query_source is views and views.split_sizes() == (3, 1, 2)
    batch = dm.materialize(next(iter(dm.train_dataloader())))
    assert batch["positive"].shape == batch["negative"].shape == (8, 3, SIZE, SIZE)
    assert batch["anchors"].shape == (8, 4, 3, SIZE, SIZE)
    assert (batch["object"] != batch["neg_object"]).all()
    assert torch.equal(batch["positive"], views.images[batch["view"]].float() / 255)
    assert torch.equal(batch["query_H_canon"], views.query_H_canon[batch["view"]].float())
    # every view belongs to its plane, and test views are never training views
    assert torch.equal(batch["view"] // 6, batch["plane"])
    train = set(dm.train_set.params["view"].tolist()) | set(dm.train_set.params["neg_view"].tolist())
    test = set(dm.test_set.params["view"].tolist())
    assert test and not train & test
    query = dm.materialize({k: v[:5] for k, v in dm.test_set.params.items()})["query"]
    assert query.shape == (5, 3, SIZE, SIZE) and query.max() > 0
    # the warped default is untouched by the option
    warped = make_dm(tiny, tmp_path)
    assert isinstance(warped.query_source, WarpedQueries) and "view" not in warped.test_set.params


def test_image_only_sources_are_refused_clearly() -> None:
    class Photos:
        def cache_key(self) -> dict:
            return {}

        def build(self, image_size: int) -> CanonicalSet:
            raise AssertionError

    with pytest.raises(MatlError, match=r"data.queries=rendered needs 3D models.*Photos"):
        require_models(Photos(), "data.queries=rendered")
