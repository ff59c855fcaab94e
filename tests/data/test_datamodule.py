"""Triplet data: shapes, labels, disjoint seeded splits, batched materialisation."""

from __future__ import annotations

import torch

from matl.data.datamodule import TripletDataModule, footprints_from_masks
from matl.geometry import transfer_points
from tests.data.conftest import PatternSource


def make_dm(tmp_path, seed: int = 0, N: int = 4) -> TripletDataModule:
    dm = TripletDataModule(PatternSource(), image_size=32, num_anchors=N, train_triplets=40, val_queries=10,
                           test_queries=20, batch_size=8, eval_batch_size=10, seed=seed, cache_dir=tmp_path)
    dm.setup()
    return dm


def test_footprints_from_masks() -> None:
    masks = torch.zeros(1, 10, 10, dtype=torch.bool)
    masks[0, 2:5, 3:8] = True
    assert footprints_from_masks(masks)[0].tolist() == [[3, 2], [7, 2], [7, 4], [3, 4]]


def test_triplet_batch_shapes_and_labels(tmp_path) -> None:
    dm = make_dm(tmp_path)
    batch = dm.materialize(next(iter(dm.train_dataloader())))
    assert batch["anchors"].shape == (8, 4, 3, 32, 32)
    assert batch["positive"].shape == batch["negative"].shape == (8, 3, 32, 32)
    assert (batch["object"] != batch["neg_object"]).all()
    assert len(dm.gallery) == 12 * 4
    # anchor 0 is the canonical image itself
    assert torch.allclose(dm.anchor_images[:, 0], dm.canon_images, atol=1e-5)


def test_positive_is_the_canonical_warped_by_its_pose(tmp_path) -> None:
    dm = make_dm(tmp_path)
    params = {k: v[:4] for k, v in dm.test_set.params.items()}
    query = dm.materialize(params)["query"]
    # the mapped footprint centre carries the object's colour, the frame corners stay background
    corners = transfer_points(params["query_H_canon"].double(), dm.footprints[params["plane"]])
    assert corners.min() >= -1e-3 and corners.max() <= 31 + 1e-3
    assert query[:, :, 0, 0].abs().max() == 0


def test_splits_are_seeded_and_disjoint(tmp_path) -> None:
    a, b, c = make_dm(tmp_path, 0), make_dm(tmp_path, 0), make_dm(tmp_path, 1)
    assert torch.equal(a.train_set.params["query_H_canon"], b.train_set.params["query_H_canon"])
    assert not torch.equal(a.test_set.params["query_H_canon"], c.test_set.params["query_H_canon"])
    train_H = a.train_set.params["query_H_canon"].reshape(-1, 9)
    test_H = a.test_set.params["query_H_canon"].reshape(-1, 9)
    assert torch.cdist(test_H, train_H).min() > 1e-3  # no test query repeats a training one
