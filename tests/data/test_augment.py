"""Camera-like positives and negatives: framings, imperfect masks, photometric changes, determinism."""

from __future__ import annotations

import pytest
import torch

from matl.data.augment import CameraAugment, Photometric, imperfect_masks, jpeg_round_trip
from matl.utils.errors import MatlError
from tests.data.conftest import masked_prints, pattern_datamodule


def _square(B: int = 4, S: int = 32) -> tuple[torch.Tensor, torch.Tensor]:
    return masked_prints(B, S, (8, 24), (8, 24))


def _augment(**kwargs) -> CameraAugment:
    images, masks = _square(6)
    aug = CameraAugment(bank=8, **kwargs)
    aug.setup(images, masks)
    return aug


def test_imperfect_masks_dilate_erode_and_stay_near_the_truth() -> None:
    masks = torch.zeros(64, 1, 64, 64)
    masks[:, :, 12:52, 12:52] = 1.0  # a 40 px product, as at the model's 100 px
    out = imperfect_masks(masks, 3, 1.5, torch.Generator().manual_seed(0))
    assert out.shape == masks.shape and set(out.unique().tolist()) <= {0.0, 1.0}
    differs = (out != masks).flatten(1).any(1)
    assert differs.float().mean() > 0.8  # nearly every mask is imperfect
    iou = (out * masks).sum((1, 2, 3)) / ((out + masks) > 0).float().sum((1, 2, 3))
    assert iou.min() > 0.5  # but it is still the product's segmentation
    grown = out.sum((1, 2, 3)) > masks.sum((1, 2, 3))
    assert grown.any() and (~grown).any()  # some dilated, some eroded
    assert torch.equal(imperfect_masks(masks, 0, 0.0, torch.Generator()), masks)


def test_clean_framing_without_photometric_is_the_identity() -> None:
    images, masks = _square()
    aug = _augment(modes={"clean": 1.0}, photometric=Photometric(p=0.0))
    assert torch.allclose(aug(images, masks, torch.Generator().manual_seed(1)), images)


def test_clutter_fills_the_background_and_keeps_the_product() -> None:
    images, masks = _square()
    aug = _augment(modes={"clutter": 1.0}, photometric=Photometric(p=0.0), neighbour_p=1.0)
    out = aug(images, masks, torch.Generator().manual_seed(2))
    inside = masks.bool().expand_as(out)
    assert torch.allclose(out[inside], images[inside])
    assert (out[~inside] > 0).float().mean() > 0.5  # background is no longer black


def test_masked_framing_is_black_outside_its_imperfect_mask() -> None:
    images, masks = _square(16)
    aug = _augment(modes={"masked": 1.0}, photometric=Photometric(p=0.0), mask_error_px=2, ragged=0.0)
    out = aug(images, masks, torch.Generator().manual_seed(3))
    far = torch.ones_like(masks)
    far[:, :, 5:27, 5:27] = 0  # beyond the largest dilation
    assert out[far.bool().expand_as(out)].abs().max() == 0


def test_photometric_changes_images_and_stays_in_range() -> None:
    images, _ = _square(16)
    out = Photometric(p=1.0, jpeg_p=1.0, blur_p=1.0)(images, torch.Generator().manual_seed(4))
    assert out.shape == images.shape and out.min() >= 0 and out.max() <= 1
    assert (out - images).abs().flatten(1).mean(1).min() > 1e-3


def test_jpeg_round_trip_is_close_at_high_quality() -> None:
    image = torch.linspace(0, 1, 3 * 32 * 32).reshape(3, 32, 32)
    assert (jpeg_round_trip(image, 95) - image).abs().mean() < 0.02


def test_same_generator_state_same_images() -> None:
    images, masks = _square()
    aug = _augment()
    a = aug(images, masks, torch.Generator().manual_seed(5))
    b = aug(images, masks, torch.Generator().manual_seed(5))
    assert torch.equal(a, b)


def test_the_bank_takes_its_share_of_textures_and_greys_what_grey_p_says() -> None:
    plain, textured = _augment(), _augment(textures=0.5)
    assert plain._bank.shape == textured._bank.shape == (8, 3, 32, 32)
    assert torch.equal(plain._bank[:2], _augment()._bank[:2])  # seeded: the same bank every time
    textures = textured._bank[4:]  # the last half: fractal noise, stones, strokes, bent bands
    assert textures.min() >= 0.0 and textures.max() <= 1.0
    assert all(float(t.std()) > 0.01 for t in textures)  # each has a texture, none is flat
    grey = _augment(textures=0.5, grey_p=1.0)._bank
    assert torch.equal(grey[:, 0], grey[:, 1]) and torch.equal(grey[:, 1], grey[:, 2])
    assert not torch.equal(plain._bank[:, 0], plain._bank[:, 1])  # grey_p=0: the colours kept


def test_bad_settings_are_one_line_errors() -> None:
    for bad in ({"textures": 1.0}, {"textures": -0.1}, {"grey_p": 1.5}):
        with pytest.raises(MatlError, match=r"textures=.*grey_p="):
            CameraAugment(**bad)
    with pytest.raises(MatlError, match="modes"):
        CameraAugment(modes={"blurry": 1.0})
    with pytest.raises(MatlError, match="neighbour_p"):
        CameraAugment(neighbour_p=2.0)
    with pytest.raises(ValueError, match=r"\(B, 1, S, S\)"):
        _augment()(torch.zeros(2, 3, 32, 32), torch.zeros(2, 32, 32), torch.Generator())


def test_datamodule_augments_positives_and_negatives_only(tmp_path) -> None:
    plain = pattern_datamodule(tmp_path)
    camera = pattern_datamodule(tmp_path, augment=CameraAugment(bank=8, modes={"clutter": 1.0}))
    b0 = plain.materialize(next(iter(plain.train_dataloader())))
    b1 = camera.materialize(next(iter(camera.train_dataloader())))
    assert torch.equal(b0["anchors"], b1["anchors"]) and torch.equal(b0["plane"], b1["plane"])
    assert not torch.allclose(b0["positive"], b1["positive"])
    assert b1["anchor_masks"].shape == (8, 2, 1, 32, 32)
    assert torch.equal(b1["anchor_masks"].bool(), b1["anchors"].amax(2, keepdim=True) > 0)
    # the same batch is augmented alike whenever it is made; queries stay clean
    again = camera.materialize(next(iter(camera.train_dataloader())))
    assert torch.equal(again["positive"], b1["positive"])
    params = {k: v[:4] for k, v in camera.test_set.params.items()}
    assert torch.equal(camera.materialize(params)["query"], plain.materialize(params)["query"])
