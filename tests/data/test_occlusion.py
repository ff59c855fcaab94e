"""Partly hidden training positives and negatives: hidden print is 0, coverage shrinks, determinism, the batch."""

from __future__ import annotations

import pytest
import torch

from matl.data.occlusion import OccludeQueries
from matl.utils.errors import MatlError
from tests.data.conftest import masked_prints, pattern_datamodule


def _products(B: int = 6, S: int = 48) -> tuple[torch.Tensor, torch.Tensor]:
    return masked_prints(B, S, (10, 38), (8, 40))


def _occlude(**kwargs) -> OccludeQueries:
    images, masks = _products()
    occ = OccludeQueries(**kwargs)
    occ.setup(images, masks, torch.arange(len(images)))
    return occ


def test_hidden_print_is_zero_and_coverage_only_shrinks() -> None:
    images, masks = _products()
    occ = _occlude(p=1.0, leak_p=0.0, occluders={"kinds": {"gripper": 1.0, "edge": 1.0}, "hidden": [0.2, 0.4]})
    out, visible = occ(images, masks, torch.arange(6), torch.Generator().manual_seed(1))
    assert out.shape == images.shape and visible.shape == masks.shape
    assert (visible <= masks + 1e-6).all()
    hidden = 1 - visible.sum((1, 2, 3)) / masks.sum((1, 2, 3))
    assert (hidden > 0.1).all() and (hidden < 0.5).all()
    gone = (masks > 0.5) & (visible < 1e-6)
    assert gone.any() and out.permute(1, 0, 2, 3)[:, gone[:, 0]].abs().max() == 0  # hidden print is 0
    seen = (visible > 1 - 1e-6).expand_as(out)
    # visible print as it was, darker only where the occluder's shadow falls
    assert (out[seen] <= images[seen] + 1e-6).all() and (out[seen] >= 0.4 * images[seen] - 1e-6).all()
    assert (out[seen] - images[seen]).abs().median() < 1e-6


def test_leaking_occluders_stay_in_the_image() -> None:
    images, masks = _products()
    occ = _occlude(p=1.0, leak_p=1.0, occluders={"kinds": {"gripper": 1.0}, "hidden": [0.3, 0.4]})
    out, visible = occ(images, masks, torch.arange(6), torch.Generator().manual_seed(2))
    gone = ((masks > 0.5) & (visible < 1e-6)).expand_as(out)
    assert out[gone].abs().max() > 0.05  # the gripper's pixels, not a hole


def test_no_occluder_is_the_identity_and_a_batch_is_the_same_every_time() -> None:
    images, masks = _products()
    out, visible = _occlude(p=0.0)(images, masks, torch.arange(6), torch.Generator().manual_seed(3))
    assert torch.equal(out, images) and torch.equal(visible, masks)
    occ = _occlude(p=0.7)
    a = occ(images, masks, torch.arange(6), torch.Generator().manual_seed(4))
    b = occ(images, masks, torch.arange(6), torch.Generator().manual_seed(4))
    assert torch.equal(a[0], b[0]) and torch.equal(a[1], b[1])


def test_bad_settings_are_one_line_errors() -> None:
    with pytest.raises(MatlError, match=r"data\.occlude"):
        OccludeQueries(p=1.5)
    with pytest.raises(MatlError, match=r"data\.occlude"):
        OccludeQueries(products=0)


def test_datamodule_occludes_training_positives_and_keeps_the_whole_one(tmp_path) -> None:
    plain = pattern_datamodule(tmp_path)
    occluded = pattern_datamodule(tmp_path, occlude=OccludeQueries(p=1.0, leak_p=0.0))
    b0 = plain.materialize(next(iter(plain.train_dataloader())))
    b1 = occluded.materialize(next(iter(occluded.train_dataloader())))
    assert "positive_target" not in b0
    assert torch.equal(b1["positive_target"], b0["positive"]) and torch.equal(b1["anchors"], b0["anchors"])
    assert not torch.equal(b1["positive"], b0["positive"]) and not torch.equal(b1["negative"], b0["negative"])
    again = occluded.materialize(next(iter(occluded.train_dataloader())))
    assert torch.equal(again["positive"], b1["positive"])
    params = {k: v[:4] for k, v in occluded.test_set.params.items()}  # test queries stay whole
    assert torch.equal(occluded.materialize(params)["query"], plain.materialize(params)["query"])
