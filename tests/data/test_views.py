"""Rendered views: plane-induced homographies, the cached view pool, rendered queries and anchors."""

from __future__ import annotations

import math
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from matl.data.canonical import CanonicalSet
from matl.data.catalog import SyntheticCatalog
from matl.data.catalog.shapes import PlaneView, ProductModel, product_model
from matl.data.datamodule import TripletDataModule
from matl.data.views import (
    RenderedQueries,
    RenderedRandomAnchors,
    ViewSampler,
    bounding_box_corners,
    load_view_pool,
    render_images_per_s,
    require_models,
    view_pool_path,
)
from matl.geometry import warp_image
from matl.utils.errors import MatlError

SIZE = 32


class TinyCatalog:
    """Three products of the APC catalog (planar, rectangular, cylindrical): 18 planes, fast."""

    fill = 0.6
    supersample = 2

    def __init__(self, texture_px: int = 96) -> None:
        specs = SyntheticCatalog("apc", texture_px=texture_px).products()
        self.specs = [next(s for s in specs if s.shape == shape) for shape in ("planar", "rectangular", "cylindrical")]
        self.texture_px = texture_px
        self.num_planes = 18

    def cache_key(self) -> dict[str, Any]:
        return {"type": "tiny-test-catalog", "texture_px": self.texture_px}

    def models(self) -> Iterator[ProductModel]:
        for spec in self.specs:
            yield product_model(spec, self.texture_px)

    def build(self, image_size: int) -> CanonicalSet:
        from matl.data.catalog.rendering import CanonicalRenderer

        images, masks, plane_object, names = [], [], [], []
        with CanonicalRenderer(image_size, self.supersample, self.fill) as r:
            for o, model in enumerate(self.models()):
                im, m = r.render(model)
                images.append(im)
                masks.append(m)
                plane_object += [o] * len(model.planes)
                names += [p.name for p in model.planes]
        return CanonicalSet(np.concatenate(images), np.concatenate(masks), np.asarray(plane_object, np.int64), names,
                            [s.name for s in self.specs], [s.shape for s in self.specs])  # fmt: skip


@pytest.fixture(scope="module")
def tiny() -> TinyCatalog:
    return TinyCatalog()


def test_frontal_view_has_identity_homography() -> None:
    from matl.data.catalog.rendering import ViewCamera

    plane = PlaneView("front", np.array([0.0, -1.0, 0.0]), np.array([0.0, 0.0, 1.0]), (4.0, 6.0))
    half, offset, size = 5.0, 1.5, 64
    sampler = ViewSampler(tilt_deg=(0.0, 0.0), rotation_deg=(0.0, 0.0), scale=(1.0, 1.0), translation=(0.0, 0.0))
    cams, H = sampler.sample(plane, offset, half, np.zeros((8, 3)) + 0.1, size, 1, np.random.default_rng(0))
    assert isinstance(cams[0], ViewCamera)
    assert np.allclose(H[0], np.eye(3), atol=1e-9)
    # A rolled camera gives a pure rotation about the image centre; scale 1.2 enlarges by 1.2.
    rolled = ViewSampler(tilt_deg=(0.0, 0.0), rotation_deg=(90.0, 90.0), scale=(1.2, 1.2), translation=(0.0, 0.0))
    _, H = rolled.sample(plane, offset, half, np.zeros((8, 3)), size, 1, np.random.default_rng(0))
    A = H[0][:2, :2]
    assert np.allclose(A @ A.T, 1.44 * np.eye(2), atol=1e-9) and np.allclose(H[0][2, :2], 0, atol=1e-12)
    c = (size - 1) / 2
    assert np.allclose(H[0] @ [c, c, 1.0], [c, c, 1.0])


def test_tilted_view_is_projective_and_stays_inside() -> None:
    plane = PlaneView("front", np.array([0.0, -1.0, 0.0]), np.array([0.0, 0.0, 1.0]), (4.0, 6.0))
    box = np.array([[x, y, z] for x in (-2, 2) for y in (-1, 1) for z in (-3, 3)], float)
    sampler = ViewSampler(tilt_deg=(30.0, 30.0))
    cams, H = sampler.sample(plane, 1.0, 5.0, box, 64, 8, np.random.default_rng(1))
    assert (np.abs(H[:, 2, :2]).sum(1) > 1e-4).all()  # a 30 deg tilt is not affine
    assert np.allclose(H[:, 2, 2], 1.0)
    # the tilt is exactly 30 deg: the optical axis (camera +z) makes that angle with the normal
    for cam in cams:
        assert math.isclose(float(cam.pose[:3, 2] @ plane.normal), math.cos(math.radians(30.0)), abs_tol=1e-9)


def test_rendered_view_matches_the_warped_canonical_on_a_box_face(tiny: TinyCatalog) -> None:
    """For a planar face the homography is exact: the canonical image warped by it lands on the render."""
    from matl.data.catalog.rendering import ViewRenderer, plane_half_width

    model = list(tiny.models())[1]  # the box
    size = 64
    sampler = ViewSampler(ambient=(0.72, 0.72), direct=(0.28, 0.28), light_cone_deg=0.0, tint=0.0)
    with ViewRenderer(size, 2) as renderer:
        canon, masks, offsets = renderer.canonical(model, tiny.fill)
        for p in (0, 4):  # front and top
            plane = model.planes[p]
            cams, H = sampler.sample(plane, float(offsets[p]), plane_half_width(plane, tiny.fill),
                                     bounding_box_corners(model), size, 4, np.random.default_rng(p))  # fmt: skip
            views, _ = renderer.render(model, cams)
            src = torch.from_numpy(canon[p]).permute(2, 0, 1)[None].float().div(255).repeat(4, 1, 1, 1)
            warped = warp_image(src, torch.from_numpy(H).float())
            inside = warp_image(torch.from_numpy(masks[p])[None, None].float().repeat(4, 1, 1, 1),
                                torch.from_numpy(H).float())[:, 0] > 0.999  # fmt: skip
            rendered = torch.from_numpy(views).permute(0, 3, 1, 2).float().div(255)
            err = (warped - rendered).abs().mean(1)[inside].mean()
            assert inside.sum() > 200 and err < 0.06, (plane.name, float(err))
            # a wrong pose would not match: shift the homography by 3 px
            shift = torch.tensor([[1.0, 0, 3], [0, 1, 0], [0, 0, 1]])
            wrong = warp_image(src, shift @ torch.from_numpy(H).float())
            assert (wrong - rendered).abs().mean(1)[inside].mean() > 1.5 * err


def test_plane_offset_is_the_face_for_boxes_and_inside_for_cylinders(tiny: TinyCatalog) -> None:
    from matl.data.catalog.rendering import ViewRenderer

    models = list(tiny.models())
    with ViewRenderer(SIZE, 2) as renderer:
        box_offsets = renderer.plane_offsets(models[1], tiny.fill)
        cyl_offsets = renderer.plane_offsets(models[2], tiny.fill)
    dims = np.asarray(tiny.specs[1].dims)
    expected = [dims[1] / 2, dims[1] / 2, dims[0] / 2, dims[0] / 2, dims[2] / 2, dims[2] / 2]
    assert np.allclose(box_offsets, expected, rtol=0.02)
    radius = tiny.specs[2].dims[0] / 2
    assert np.allclose(cyl_offsets[2:], math.pi / 4 * radius, rtol=0.05)  # mean height of a half cylinder


def test_view_pool_is_cached_and_reused(tiny: TinyCatalog, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    sampler = ViewSampler()
    pool = load_view_pool(tiny, SIZE, 3, sampler, 0, tmp_path)
    assert pool.images.shape == (18, 3, SIZE, SIZE, 3) and pool.query_H_canon.shape == (18, 3, 3, 3)
    assert pool.images.reshape(18 * 3, -1).max(1).min() > 0  # every view shows the object
    path, _ = view_pool_path(tiny, SIZE, 3, sampler, 0, tmp_path)
    assert path.exists() and not list(tmp_path.glob(".*.tmp"))

    def fail(*args: Any, **kwargs: Any) -> None:
        raise AssertionError("should have loaded from the cache")

    monkeypatch.setattr("matl.data.views.render_view_pool", fail)
    again = load_view_pool(tiny, SIZE, 3, sampler, 0, tmp_path)
    assert np.array_equal(again.images, pool.images) and np.array_equal(again.query_H_canon, pool.query_H_canon)
    assert view_pool_path(tiny, SIZE, 3, ViewSampler(tilt_deg=(0, 10)), 0, tmp_path)[0] != path


def make_dm(tiny: TinyCatalog, cache: Path, **kw: Any) -> TripletDataModule:
    dm = TripletDataModule(tiny, image_size=SIZE, num_anchors=4, train_triplets=40, val_queries=8, test_queries=20,
                           batch_size=8, eval_batch_size=10, seed=0, cache_dir=cache, **kw)  # fmt: skip
    dm.setup()
    return dm


def test_datamodule_with_rendered_queries(tiny: TinyCatalog, tmp_path: Path) -> None:
    views = RenderedQueries(views_per_plane=6, val_fraction=0.2, test_fraction=0.34)
    dm = make_dm(tiny, tmp_path, queries="rendered", views=views)
    assert views.split_sizes() == (3, 1, 2)
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
    assert warped.query_source is None and "view" not in warped.test_set.params


def test_rendered_random_anchors(tiny: TinyCatalog, tmp_path: Path) -> None:
    dm = make_dm(tiny, tmp_path, anchors=RenderedRandomAnchors())
    assert dm.anchor_images.shape == (18, 4, 3, SIZE, SIZE) and dm.anchor_H_canon.shape == (18, 4, 3, 3)
    assert dm.anchor_images.flatten(2).amax(2).min() > 0
    assert not torch.allclose(dm.anchor_H_canon[:, 0], torch.eye(3, dtype=torch.float64).expand(18, 3, 3))
    assert torch.equal(dm.gallery.anchor_H_canon, dm.anchor_H_canon.reshape(-1, 3, 3))
    with pytest.raises(MatlError, match="build_anchors"):
        RenderedRandomAnchors()(18, 4, (SIZE, SIZE), torch.Generator(), torch.zeros(18, 4, 2))


def test_image_only_sources_are_refused_clearly() -> None:
    class Photos:
        def cache_key(self) -> dict:
            return {}

        def build(self, image_size: int) -> CanonicalSet:
            raise AssertionError

    with pytest.raises(MatlError, match=r"data.queries=rendered needs 3D models.*Photos"):
        require_models(Photos(), "data.queries=rendered")


def test_render_throughput_function(tiny: TinyCatalog) -> None:
    canon = render_images_per_s(tiny, SIZE, "canonical", num_objects=2)
    views = render_images_per_s(tiny, SIZE, "views", num_objects=1, views_per_plane=2)
    assert canon["images"] == 8 and views["images"] == 4
    assert canon["images_per_s"] > 0 and views["images_per_s"] > 0


def test_render_views_sheet(tiny: TinyCatalog, tmp_path: Path) -> None:
    """``python -m matl.render ... views=K`` writes views.png: per plane its canonical image and K views."""
    from PIL import Image
    from rich.console import Console

    from matl.render import render_views

    speed = render_views(tiny, 24, 2, tmp_path, Console(quiet=True), max_objects=1)
    sheet = Image.open(tmp_path / "views.png")
    assert sheet.size == (3 * 24 + 3 * 4, 2 * (24 + 4))  # the planar object: 2 planes, canonical + 2 views each
    assert speed["images_per_s"] > 0
