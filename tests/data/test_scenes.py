"""Training scenes of the visibility network (matl/data/scenes.py): the mask is the truth, scenes are seeded."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
import torch

from matl.data.augment import CameraAugment, Photometric
from matl.data.occluders import Occluders
from matl.data.scenes import SceneDataModule, SceneMaker, bin_floor, make_scene_set
from matl.geometry import sample_by_pixels
from matl.utils.errors import MatlError
from tests.data.conftest import PatternSource

SIZE = 48


def catalog() -> Any:
    return PatternSource().build(SIZE)


def maker(**kwargs: Any) -> SceneMaker:
    settings = {"augment": CameraAugment(bank=8), "photometric": Photometric(p=0.0), **kwargs}
    return SceneMaker(**settings).setup(catalog())


def target_mask(m: SceneMaker, plane: int, query_H_canon: np.ndarray) -> np.ndarray:
    """The target's whole warped mask ``(S, S)`` (nothing hidden)."""
    return sample_by_pixels(catalog().masks[plane].astype(np.float32), np.linalg.inv(query_H_canon), (SIZE, SIZE))


def test_the_visible_mask_is_the_targets_warped_mask_without_occluders() -> None:
    m = maker(neighbours=(1, 2), occluded_p=0.0)
    for i in range(6):
        scene = m(i)
        assert scene.image.shape == (SIZE, SIZE, 3) and scene.visible.shape == (SIZE, SIZE)
        assert scene.image.dtype == np.float32 and scene.image.min() >= 0.0 and scene.image.max() <= 1.0
        whole = target_mask(m, scene.plane, scene.query_H_canon)
        assert np.allclose(scene.visible, whole, atol=1e-6)
        assert scene.visible[whole == 0].max(initial=0.0) == 0.0  # outside the target's warped mask: 0
        inside = whole > 0.999  # the target is on top: its pixels are its own print
        canon = catalog().images[scene.plane].astype(np.float32) / 255.0
        own = sample_by_pixels(canon, np.linalg.inv(scene.query_H_canon), (SIZE, SIZE))
        assert np.allclose(scene.image[inside], own[inside], atol=0.5 / 255 + 1e-6)  # 8 bits


class HideLeftHalf:
    """An occluder that paints the left half of the crop white: what it covers is hidden."""

    def apply(self, image: np.ndarray, visible: np.ndarray, rng: np.random.Generator, products: Any,
              floor: Any = None) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
        assert len(products) == 3 and all(p[0].shape == (SIZE, SIZE, 3) and p[1].shape == (SIZE, SIZE)
                                          for p in products)
        image, visible = image.copy(), visible.copy()
        image[:, : SIZE // 2] = 1.0
        hidden = 1.0 - visible[:, SIZE // 2:].sum() / visible.sum()
        visible[:, : SIZE // 2] = 0.0
        return image, visible, {"hidden_fraction": float(hidden), "occluder": "test"}


def test_occluded_pixels_are_out_of_the_visible_mask() -> None:
    m = maker(occluders=HideLeftHalf(), occluded_p=1.0, occluder_products=3)
    scene = m(0)
    assert scene.visible[:, : SIZE // 2].max() == 0.0 and np.all(scene.image[:, : SIZE // 2] == 1.0)
    whole = target_mask(m, scene.plane, scene.query_H_canon)
    assert np.allclose(scene.visible[:, SIZE // 2:], whole[:, SIZE // 2:], atol=1e-6)
    assert scene.info["occluder"] == "test" and scene.info["hidden_fraction"] > 0
    assert np.allclose(scene.covered, whole, atol=1e-6)  # the coverage before the occluder: the hidden half too
    sets = make_scene_set(m, [0], 16)
    assert sets.covered[0, 0, :, :8].max() > 0 and sets.visible[0, 0, :, :8].max() == 0


def test_real_occluders_hide_part_of_the_target_and_only_of_it() -> None:
    m = maker(occluders=Occluders(kinds={"product": 1.0, "gripper": 1.0, "suction": 1.0, "edge": 1.0},
                                  hidden=(0.3, 0.3)), occluded_p=1.0)
    for i in range(4):
        scene = m(i)
        whole = target_mask(m, scene.plane, scene.query_H_canon)
        assert np.all(scene.visible <= whole + 1e-6)
        assert scene.visible[whole == 0].max(initial=0.0) == 0.0
        hidden = 1.0 - scene.visible.sum() / whole.sum()
        assert hidden == pytest.approx(scene.info["hidden_fraction"], abs=1e-4)
        assert 0.2 < hidden < 0.4


def test_photometric_changes_leave_the_mask_and_scenes_are_seeded() -> None:
    plain = maker(occluded_p=0.0)
    shot = maker(occluded_p=0.0, photometric=Photometric(p=1.0, noise_std=(0.02, 0.03)))
    a, b = plain(3), shot(3)
    assert np.array_equal(a.visible, b.visible) and not np.allclose(a.image, b.image)
    again = maker(occluded_p=0.0, photometric=Photometric(p=1.0, noise_std=(0.02, 0.03)))(3)
    assert np.array_equal(b.image, again.image) and np.array_equal(b.visible, again.visible)
    assert not np.array_equal(shot(4).image, b.image)
    assert not np.array_equal(maker(occluded_p=0.0, seed=1)(3).visible, a.visible)


def test_backgrounds_black_floor_and_bank() -> None:
    black = maker(black_p=1.0, floor_p=0.0, neighbours=(0, 0), occluded_p=0.0)(0)
    outside = target_mask(black, black.plane, black.query_H_canon) == 0
    assert black.image[outside].max() == 0.0 and black.info["background"] == "black"
    floor = maker(black_p=0.0, floor_p=1.0, occluded_p=0.0)(1)
    assert floor.info["background"] == "floor"
    bank = maker(black_p=0.0, floor_p=0.0, occluded_p=0.0)(2)
    assert bank.info["background"] == "bank"
    texture = bin_floor(64, np.random.default_rng(0))
    assert texture.shape == (64, 64, 3) and texture.dtype == np.float32 and texture.mean() < 0.5


def test_bad_settings_are_one_line() -> None:
    for kwargs in ({"black_p": 0.7, "floor_p": 0.5}, {"neighbours": (2, 1)}, {"occluded_p": 1.5},
                   {"neighbour_distance": (0.8, 0.5)}, {"occluder_products": 0}):
        with pytest.raises(MatlError, match="scenes: "):
            SceneMaker(**kwargs)
    with pytest.raises(MatlError, match="has no apply"):
        SceneMaker(occluders=object())
    with pytest.raises(RuntimeError, match="setup"):
        SceneMaker()(0)


def test_scene_sets_and_the_datamodule(tmp_path) -> None:
    m = maker(occluded_p=0.0)
    scenes = make_scene_set(m, [0, 1, 2], 16)
    assert scenes.images.shape == (3, 3, 16, 16) and scenes.images.dtype == torch.uint8
    assert scenes.visible.shape == (3, 1, 16, 16) and scenes.visible.max() == 255 and len(scenes.background) == 3
    dm = SceneDataModule(PatternSource(), PatternSource(), {"augment": {"bank": 8}, "occluded_p": 0.0},
                         image_size=SIZE, working_size=16, train_scenes=8, val_scenes=4, batch_size=4,
                         cache_dir=tmp_path)
    dm.setup()
    batch = next(iter(dm.train_dataloader()))
    assert batch["image"].shape == (4, 3, 16, 16) and batch["visible"].shape == (4, 1, 16, 16)
    assert float(batch["visible"].min()) >= 0.0 and float(batch["visible"].max()) <= 1.0
    assert torch.equal(batch["covered"], batch["visible"])  # nothing occluded: covered as visible
    assert len(dm.val_set.images) == 4 and len(dm.timing_crops(2)) == 2
    assert dm.validation_maker().seed == dm.scenes.seed + 1
    with pytest.raises(MatlError, match="train_scenes"):
        SceneDataModule(PatternSource(), PatternSource(), train_scenes=2, batch_size=4)
