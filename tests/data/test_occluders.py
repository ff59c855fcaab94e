"""Occluders over a product crop: realised hidden fractions, coverage, determinism, shapes, bad settings."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from matl.data.occluders import OCCLUDER_KINDS, Occluders, capsule_alpha, halfplane_alpha
from matl.utils.errors import MatlError

SIZE = 140  # the frame; the product is a 100 x 70 px box turned by 20 deg in it


def _box(size: int, width: float, height: float, angle: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """A textured box: ``(size, size, 3)`` RGB (0 outside) and its soft ``(size, size)`` coverage."""
    mask = np.zeros((size, size))
    corners = cv2.boxPoints(((size / 2, size / 2), (width, height), angle))
    cv2.fillPoly(mask, [np.round(corners * 16).astype(np.int32)], 1.0, lineType=cv2.LINE_AA, shift=4)
    texture = cv2.GaussianBlur(np.random.default_rng(seed).uniform(0.0, 1.0, (size, size, 3)), (0, 0), 2.0)
    return texture * mask[..., None], mask


@pytest.fixture(scope="module")
def scene() -> tuple[np.ndarray, np.ndarray, list, np.ndarray]:
    rgb, mask = _box(SIZE, 100, 70, 20, 0)
    image = rgb + (1.0 - mask[..., None]) * 0.3
    others = [_box(80, 60 + 10 * k, 35, 0, 1 + k) for k in range(3)]
    floor = cv2.GaussianBlur(np.random.default_rng(9).uniform(0.0, 1.0, (SIZE, SIZE, 3)), (0, 0), 1.0)
    return image, mask, others, floor


@pytest.mark.parametrize("kind", OCCLUDER_KINDS)
def test_each_kind_hides_the_drawn_fraction(scene, kind: str) -> None:
    image, mask, others, floor = scene
    occluders = Occluders({kind: 1.0}, (0.1, 0.5))
    for seed in range(12):
        out, visible, info = occluders.apply(image, mask, np.random.default_rng(seed), others, floor)
        assert info["occluder"] == kind
        assert 0.1 <= info["target_fraction"] <= 0.5
        assert abs(info["hidden_fraction"] - info["target_fraction"]) <= 0.05
        assert info["hidden_fraction"] == pytest.approx(1.0 - visible.sum() / mask.sum())
        # the new coverage lies within the old one, soft only where the occluder's edge is
        assert (visible >= 0).all() and (visible <= mask + 1e-12).all()
        hidden = (mask > 0.99) & (visible < 0.01)
        assert hidden.sum() > 0.05 * mask.sum()  # it lies over the product
        assert np.abs(out - image)[hidden].max() > 0.02  # and what hides it is drawn there


def test_kinds_are_drawn_by_weight_and_the_range_is_honoured(scene) -> None:
    image, mask, others, floor = scene
    occluders = Occluders({"gripper": 1.0, "edge": 3.0, "suction": 0.0}, (0.3, 0.3))
    kinds = []
    for seed in range(40):
        _, _, info = occluders.apply(image, mask, np.random.default_rng(seed), others, floor)
        kinds.append(info["occluder"])
        assert info["target_fraction"] == 0.3 and abs(info["hidden_fraction"] - 0.3) <= 0.05
    assert set(kinds) == {"gripper", "edge"} and kinds.count("edge") > kinds.count("gripper")


def test_same_generator_state_same_result(scene) -> None:
    image, mask, others, floor = scene
    occluders = Occluders({k: 1.0 for k in OCCLUDER_KINDS})
    for seed in range(6):
        a = occluders.apply(image, mask, np.random.default_rng(seed), others, floor)
        b = occluders.apply(image, mask, np.random.default_rng(seed), others, floor)
        assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1]) and a[2] == b[2]
    c = occluders.apply(image, mask, np.random.default_rng(99), others, floor)
    assert not np.array_equal(a[0], c[0])


def test_shapes_dtypes_and_a_dark_wall_without_a_floor(scene) -> None:
    image, mask, _, _ = scene
    out, visible, info = Occluders({"edge": 1.0}, (0.2, 0.2)).apply(image.astype(np.float32), mask,
                                                                     np.random.default_rng(3))
    assert out.shape == (SIZE, SIZE, 3) and out.dtype == np.float64 and out.min() >= 0.0 and out.max() <= 1.0
    assert visible.shape == (SIZE, SIZE) and visible.dtype == np.float64
    assert info["variant"] == "dark"  # no floor given: the wall is dark
    gone = (mask > 0.99) & (visible < 0.01)
    assert out[gone].mean() < 0.2


def test_edge_takes_the_floor_texture(scene) -> None:
    image, mask, others, floor = scene
    variants = set()
    for seed in range(10):
        out, visible, info = Occluders({"edge": 1.0}, (0.4, 0.4)).apply(image, mask, np.random.default_rng(seed),
                                                                        others, floor)
        variants.add(info["variant"])
        if info["variant"] == "texture":
            gone = (mask > 0.99) & (visible < 0.01)
            assert np.corrcoef(out[gone].ravel(), floor[gone].ravel())[0, 1] > 0.95  # the floor, darkened
    assert variants == {"dark", "texture"}


def test_soft_shapes() -> None:
    ys, xs = np.mgrid[0:20, 0:40].astype(np.float64)
    bar = capsule_alpha(xs, ys, np.array([-100.0, 10.0]), np.array([20.0, 10.0]), 4.0, round_end=False)
    assert bar[10, 10] == 1.0 and bar[10, 30] == 0.0 and bar[2, 10] == 0.0 and 0 < bar[14, 10] <= 1.0
    finger = capsule_alpha(xs, ys, np.array([-100.0, 10.0]), np.array([20.0, 10.0]), 4.0, round_end=True)
    assert finger[10, 23] == 1.0 and finger[10, 25] == 0.0  # the round tip reaches 4 px beyond its end point
    half = halfplane_alpha(xs, ys, np.array([1.0, 0.0]), 9.5)
    assert half[:, :9].min() == 1.0 and half[:, 11:].max() == 0.0 and half[0, 9] == pytest.approx(1.0)


@pytest.mark.parametrize("kinds,hidden,match", [
    ({"hand": 1.0}, (0.1, 0.5), "occluder kind 'hand' is unknown: use product, gripper, suction or edge"),
    ({"edge": -1.0}, (0.1, 0.5), "occluder kind weight edge=-1.0 is invalid: use a number >= 0"),
    ({"edge": 0.0}, (0.1, 0.5), "occluder kinds all have weight 0"),
    ({}, (0.1, 0.5), "occluder kinds=.* is invalid"),
    ({"edge": 1.0}, (0.6, 0.2), r"occluder hidden=\[0.6, 0.2\] is invalid: use \[low, high\] with 0 <= low"),
    ({"edge": 1.0}, (0.2, 1.0), "occluder hidden=.* is invalid"),
])
def test_bad_settings_are_one_line_errors(kinds: dict, hidden: tuple, match: str) -> None:
    with pytest.raises(MatlError, match=match) as error:
        Occluders(kinds, hidden)
    assert "\n" not in str(error.value)


def test_bad_inputs_are_one_line_errors(scene) -> None:
    image, mask, others, _ = scene
    occluders = Occluders({"product": 1.0})
    with pytest.raises(MatlError, match="'product' needs other products"):
        occluders.apply(image, mask, np.random.default_rng(0), [])
    with pytest.raises(MatlError, match="no visible pixel"):
        occluders.apply(image, np.zeros_like(mask), np.random.default_rng(0), others)
    with pytest.raises(MatlError, match="visible coverage has shape"):
        occluders.apply(image, mask[:10], np.random.default_rng(0), others)
