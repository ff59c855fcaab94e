"""Anchor acquisitions: fixed rotations, random warps, rendered anchors (photographed ones: test_photos.py)."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from matl.data.anchors import FixedAnchors, RandomAnchors, RenderedRandomAnchors
from matl.data.datamodule import TripletDataModule
from matl.geometry import HomographySampler
from matl.utils.errors import MatlError
from tests.data.conftest import TinyCatalog

SIZE = 32


def test_fixed_anchors_are_rotations_about_the_centre() -> None:
    H = FixedAnchors()(3, 4, (SIZE, SIZE), torch.Generator(), torch.zeros(3, 4, 2))
    assert H.shape == (3, 4, 3, 3) and H.dtype == torch.float64
    assert torch.allclose(H[:, 0], torch.eye(3, dtype=torch.float64).expand(3, 3, 3))
    c = (SIZE - 1) / 2
    point = lambda x, y: torch.tensor([x, y, 1.0], dtype=torch.float64)  # noqa: E731
    assert torch.allclose(H[0, 1] @ point(c, c), point(c, c))  # the centre stays
    # a quarter turn sends the top-left pixel to another corner of the 32 px frame
    corner = H[0, 1] @ point(0.0, 0.0)
    assert sorted(corner[:2].abs().round().tolist()) == [0.0, 31.0]


def test_random_anchors_draw_from_their_sampler() -> None:
    footprints = torch.tensor([[[8.0, 8.0], [23.0, 8.0], [23.0, 23.0], [8.0, 23.0]]], dtype=torch.float64)
    sampler = HomographySampler(translation=(0.0, 0.0))
    H = RandomAnchors(sampler)(1, 3, (SIZE, SIZE), torch.Generator().manual_seed(0), footprints)
    expected = sampler.sample(3, (SIZE, SIZE), torch.Generator().manual_seed(0), footprints.repeat(3, 1, 1))
    assert torch.equal(H, expected.view(1, 3, 3, 3))


def test_rendered_random_anchors(tiny: TinyCatalog, tmp_path: Path) -> None:
    dm = TripletDataModule(tiny, image_size=SIZE, num_anchors=4, train_triplets=40, val_queries=8, test_queries=20,
                           batch_size=8, eval_batch_size=10, seed=0, cache_dir=tmp_path,
                           anchors=RenderedRandomAnchors())  # fmt: skip
    dm.setup()
    assert dm.anchor_images.shape == (18, 4, 3, SIZE, SIZE) and dm.anchor_H_canon.shape == (18, 4, 3, 3)
    assert dm.anchor_images.flatten(2).amax(2).min() > 0
    assert not torch.allclose(dm.anchor_H_canon[:, 0], torch.eye(3, dtype=torch.float64).expand(18, 3, 3))
    assert torch.equal(dm.gallery.anchor_H_canon, dm.anchor_H_canon.reshape(-1, 3, 3))
    with pytest.raises(MatlError, match="build_anchors"):
        RenderedRandomAnchors()(18, 4, (SIZE, SIZE), torch.Generator(), torch.zeros(18, 4, 2))
    assert RenderedRandomAnchors({"_target_": "x", "tilt_deg": [0, 10]}).sampler.tilt_deg == (0.0, 10.0)
