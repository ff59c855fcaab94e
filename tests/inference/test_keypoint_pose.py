"""The keypoint pose of answers that do not verify (``keypoint_pose``): a partly hidden product posed by its visible
keypoints, and kept only where it verifies better."""

from __future__ import annotations

import pickle
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from matl import Recognizer
from matl.geometry import corner_error_px
from matl.inference.keypoint_pose import KeypointPose
from matl.utils.errors import MatlError
from tests.inference.test_api import StubModel
from tests.predict_helpers import write_png

SIZE = 100
GALLERY_HW = (120, 120)
QUERY_HW = (140, 150)
#: gallery image pixels -> query pixels: a turn, a scale and a little perspective
QUERY_H_GALLERY = np.array([[0.95, -0.25, 30.0], [0.22, 0.9, 12.0], [0.0004, -0.0003, 1.0]])


def print_like(seed: int, base: tuple[float, float, float]) -> np.ndarray:
    """A product print ``GALLERY_HW`` float RGB in [0, 1]: blocks, discs and strokes of many colours on ``base``."""
    rng = np.random.default_rng(seed)
    image = np.empty((*GALLERY_HW, 3), np.float32)
    image[:] = base
    for _ in range(40):
        colour = tuple(float(c) for c in rng.uniform(0, 1, 3))
        x, y = (int(v) for v in rng.integers(0, GALLERY_HW[1] - 10, 2))
        kind = rng.integers(0, 3)
        if kind == 0:
            cv2.rectangle(image, (x, y), (x + int(rng.integers(4, 18)), y + int(rng.integers(4, 18))), colour, -1)
        elif kind == 1:
            cv2.circle(image, (x, y), int(rng.integers(2, 8)), colour, -1)
        else:
            cv2.line(image, (x, y), (x + int(rng.integers(-15, 15)), y + int(rng.integers(-15, 15))), colour, 2)
    return image


def hidden_query(image: np.ndarray) -> np.ndarray:
    """``image`` seen by the camera at ``QUERY_H_GALLERY`` on a dark floor, a grey bar across a third of it."""
    query = cv2.warpPerspective(image, QUERY_H_GALLERY, (QUERY_HW[1], QUERY_HW[0]), flags=cv2.INTER_LINEAR,
                                borderValue=(0.05, 0.05, 0.05))
    query[:, 75:120] = 0.55  # the gripper
    return np.clip(query, 0, 1)


@pytest.fixture()
def gallery(tmp_path: Path) -> Path:
    for k, (name, base) in enumerate({"red_box": (0.8, 0.2, 0.1), "blue_tin": (0.1, 0.2, 0.8)}.items()):
        write_png(tmp_path / name / "front.png", print_like(k, base))
    return tmp_path


def wrong_pose_recognizer(**options) -> Recognizer:
    """One anchor, ``c()`` the mean colour, ``s()`` a fixed pose far from the truth (a shift of 20 px); the flow pose
    off (this file tests the keypoint stage alone)."""
    wrong = torch.tensor([[1.0, 0.0, 20.0], [0.0, 1.0, -20.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    options = {"threshold": None, "foreground": "none", "flow_pose": "none", **options}
    return Recognizer(StubModel(wrong), SIZE, 1, "stub-model", **options)


def error_px(H: np.ndarray) -> float:
    """The corner error of a gallery -> query pose against the truth, in query pixels."""
    return float(corner_error_px(torch.from_numpy(H)[None], torch.from_numpy(QUERY_H_GALLERY)[None], GALLERY_HW)[0])


def test_a_hidden_product_is_posed_by_its_visible_keypoints(gallery: Path) -> None:
    query = hidden_query(print_like(0, (0.8, 0.2, 0.1)))
    without = wrong_pose_recognizer(keypoint_pose="none").enrol(gallery, cache=False).predict(query)
    assert without.object == "red_box" and error_px(without.H) > 15.0 and not without.verification <= 0.1
    rec = wrong_pose_recognizer().enrol(gallery, cache=False)  # keypoint_pose=unverified: the default
    answer = rec.predict(query)
    assert answer.object == "red_box" and error_px(answer.H) < 3.0
    assert answer.verification < without.verification - 0.3
    assert rec.options()["keypoint_pose"]["mode"] == "unverified"


def test_the_planes_keypoints_are_computed_when_a_small_gallery_is_built(gallery: Path) -> None:
    query = hidden_query(print_like(0, (0.8, 0.2, 0.1)))
    ready = wrong_pose_recognizer().enrol(gallery, cache=False)  # keypoint_pose=unverified, precompute 1024 planes
    lazy = wrong_pose_recognizer(keypoint_pose=KeypointPose(mode="unverified", precompute=1)).enrol(gallery,
                                                                                                    cache=False)
    ready._build(), lazy._build()
    assert all(p.keypoints is not None for p in ready._planes)     # no query waits for them
    assert all(p.keypoints is None for p in lazy._planes)          # 2 planes > 1: each at its first need
    first, second = ready.predict(query), lazy.predict(query)
    assert first.object == second.object == "red_box" and error_px(first.H) < 3.0
    np.testing.assert_array_equal(first.H, second.H)               # the same keypoints either way
    assert {p.object for p in lazy._planes if p.keypoints is not None} == {"red_box"}  # the answered product's only
    # off: nothing computed
    off = wrong_pose_recognizer(keypoint_pose="none").enrol(gallery, cache=False)
    off._build()
    assert all(p.keypoints is None for p in off._planes)


def test_a_pose_that_verifies_is_left_alone_and_a_worse_one_never_taken(gallery: Path) -> None:
    query = hidden_query(print_like(0, (0.8, 0.2, 0.1)))
    # unverified: an answer that verifies is not matched (verify_max=2 verifies every pose, the wrong one too)
    loose = wrong_pose_recognizer(keypoint_pose="unverified", verify_max=2.0).enrol(gallery, cache=False)
    assert error_px(loose.predict(query).H) > 15.0
    # always: matched, and kept because it verifies better
    always = wrong_pose_recognizer(keypoint_pose="always", verify_max=2.0).enrol(gallery, cache=False)
    assert error_px(always.predict(query).H) < 3.0
    # a crop with no keypoint of the product (flat grey): nothing to match, the networks' answer stays
    flat = np.full((*QUERY_HW, 3), 0.5, np.float32)
    base = wrong_pose_recognizer(keypoint_pose="none").enrol(gallery, cache=False).predict(flat)
    kept = wrong_pose_recognizer(keypoint_pose="always").enrol(gallery, cache=False).predict(flat)
    np.testing.assert_array_equal(kept.H, base.H)
    assert kept.object == base.object and kept.verification == base.verification


def test_match_finds_the_plane_and_its_pose_in_model_pixels() -> None:
    settings = KeypointPose(mode="always")
    canon = [cv2.resize(print_like(k, (0.5, 0.5, 0.2)), (SIZE, SIZE), interpolation=cv2.INTER_AREA) for k in range(3)]
    planes = [settings.plane_features(torch.from_numpy((c * 255).round().astype(np.uint8)).permute(2, 0, 1))
              for c in canon]
    query_H_canon = QUERY_H_GALLERY @ np.diag([GALLERY_HW[1] / SIZE, GALLERY_HW[0] / SIZE, 1.0])
    query = cv2.warpPerspective(canon[2], query_H_canon, (QUERY_HW[1], QUERY_HW[0]), flags=cv2.INTER_LINEAR)
    index, H, inliers = settings.match(settings.query_features(query), planes, 1.0)
    assert index == 2 and inliers >= settings.min_inliers
    err = corner_error_px(torch.from_numpy(H)[None], torch.from_numpy(query_H_canon)[None], (SIZE, SIZE))
    assert float(err) < 1.0
    again = pickle.loads(pickle.dumps(settings))  # after use: the settings travel, each copy its own detector
    assert again == settings and again.match(again.query_features(query), planes, 1.0)[0] == 2


@pytest.mark.parametrize(("key", "value", "named"), [
    ("mode", "sometimes", "keypoint_pose='sometimes'"), ("size", 8, "size=8"), ("min_inliers", 3, "min_inliers=3"),
    ("ratio", 1.5, "ratio=1.5"), ("reproj_threshold", 0.0, "reproj_threshold=0.0"), ("method", "lmeds", "method"),
    ("switch_margin", -1, "switch_margin=-1"), ("precompute", -1, "precompute=-1"),
    ("precompute", True, "precompute=True")])
def test_bad_settings_are_one_line_errors(key: str, value: object, named: str) -> None:
    with pytest.raises(MatlError, match=named):
        KeypointPose(**{key: value})


def test_the_next_nearest_product_is_taken_only_where_its_pose_verifies(tmp_path: Path) -> None:
    query = hidden_query(print_like(0, (0.8, 0.2, 0.1)))
    write_png(tmp_path / "red_box" / "front.png", print_like(0, (0.8, 0.2, 0.1)))
    # a flat print of the query's own mean colour: the nearest product by c() (the mean colour), with no keypoint
    write_png(tmp_path / "decoy" / "front.png", np.broadcast_to(query.mean((0, 1)), (*GALLERY_HW, 3)).copy())
    assert wrong_pose_recognizer(keypoint_pose="none").enrol(tmp_path, cache=False).predict(query).object == "decoy"
    answer = wrong_pose_recognizer(keypoint_pose="unverified").enrol(tmp_path, cache=False).predict(query)
    assert answer.nearest_object == "red_box" and error_px(answer.H) < 3.0
    one = KeypointPose(mode="unverified", products=1)  # the answered product alone
    assert wrong_pose_recognizer(keypoint_pose=one).enrol(tmp_path, cache=False).predict(query).object == "decoy"
    # open set: another product's verified pose changes the nearest product, the statistic still decides known
    strict = wrong_pose_recognizer(keypoint_pose="unverified", threshold=0.0).enrol(tmp_path, cache=False)
    answer = strict.predict(query)
    assert answer.nearest_object == "red_box" and answer.verification <= 0.1 and not answer.known


def test_an_answer_verified_nowhere_goes_to_the_product_whose_keypoints_match_clearly_most(tmp_path: Path) -> None:
    query = hidden_query(print_like(0, (0.8, 0.2, 0.1)))
    write_png(tmp_path / "red_box" / "front.png", print_like(0, (0.8, 0.2, 0.1)))
    write_png(tmp_path / "decoy" / "front.png", np.broadcast_to(query.mean((0, 1)), (*GALLERY_HW, 3)).copy())
    # verify_max=1e-9: no pose verifies, so only the keypoint inliers can move the answer off the nearest product
    answers = {margin: wrong_pose_recognizer(keypoint_pose=KeypointPose(mode="unverified", switch_margin=margin),
                                             verify_max=1e-9).enrol(tmp_path, cache=False).predict(query)
               for margin in (None, 3, 10_000)}
    assert answers[None].nearest_object == "decoy" and answers[10_000].nearest_object == "decoy"
    switched = answers[3]
    assert switched.nearest_object == "red_box" and error_px(switched.H) < 3.0
    assert not switched.verification <= 1e-9  # still unverified: the open set judges it by its statistic
