"""The flow pose of answers that do not verify (``flow_pose``): a pose a few px off corrected by dense optical flow
over the visible print, an occluder left out, and kept only where it verifies better."""

from __future__ import annotations

import dataclasses
import pickle
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from matl import Match, Recognizer
from matl.data.image_files import fit_geometry
from matl.geometry import corner_error_px
from matl.inference.fast_refine import FastRefiner
from matl.inference.flow_pose import FlowPose
from matl.inference.refine import RefineResult
from matl.utils.errors import MatlError
from tests.inference.test_api import StubModel
from tests.inference.test_keypoint_pose import GALLERY_HW, QUERY_H_GALLERY, QUERY_HW, error_px, hidden_query, print_like
from tests.predict_helpers import write_png

SIZE = 100
#: anchor pixels -> query pixels at the model's size: a turn, a scale and a little perspective
QUERY_H_ANCHOR = torch.tensor([[0.93, -0.2, 12.0], [0.18, 0.9, 8.0], [0.0003, -0.0002, 1.0]], dtype=torch.float64)
#: a start about 6 px off: shifted and turned a little in the anchor's frame
OFF = torch.tensor([[0.995, -0.05, 6.0], [0.05, 0.995, -4.0], [0.0, 0.0, 1.0]], dtype=torch.float64)


def anchor_and_query(hide: bool) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """A printed anchor ``(3, S, S)`` on black, the query it gives at ``QUERY_H_ANCHOR`` and, with ``hide``, its
    visibility ``(1, S, S)`` with a bar hiding a third of the product (its pixels black, as a mask leaves them)."""
    print_ = cv2.resize(print_like(3, (0.7, 0.6, 0.2)), (80, 80), interpolation=cv2.INTER_AREA)
    anchor = np.zeros((SIZE, SIZE, 3), np.float32)
    anchor[10:90, 10:90] = print_
    query = cv2.warpPerspective(anchor, QUERY_H_ANCHOR.numpy(), (SIZE, SIZE), flags=cv2.INTER_LINEAR)
    visibility = None
    if hide:
        seen = np.ones((SIZE, SIZE), np.float32)
        seen[:, 55:80] = 0.0
        query = query * seen[..., None]
        visibility = torch.from_numpy(seen)[None]
    return torch.from_numpy(anchor).permute(2, 0, 1), torch.from_numpy(query).permute(2, 0, 1), visibility


def error(query_H_anchor: torch.Tensor) -> float:
    return float(corner_error_px(query_H_anchor[None], QUERY_H_ANCHOR[None], (SIZE, SIZE))[0])


@pytest.mark.parametrize("hide", [False, True])
def test_a_pose_a_few_px_off_is_corrected(hide: bool) -> None:
    anchor, query, visibility = anchor_and_query(hide)
    start = QUERY_H_ANCHOR @ OFF
    assert error(start) > 4.0
    pose = FlowPose(mode="unverified").pose(query, anchor, start, visibility)
    assert pose is not None and pose.dtype == torch.float64 and error(pose) < 1.0


def test_rounds_reach_a_start_one_flow_does_not() -> None:
    anchor, query, visibility = anchor_and_query(True)
    turn = 0.05
    far = torch.tensor([[np.cos(turn), -np.sin(turn), 10.0], [np.sin(turn), np.cos(turn), -7.0], [0.0, 0.0, 1.0]],
                       dtype=torch.float64)
    start = QUERY_H_ANCHOR @ far
    assert error(start) > 7.0
    once = FlowPose(mode="unverified", rounds=1).pose(query, anchor, start, visibility)
    again = FlowPose(mode="unverified", rounds=3).pose(query, anchor, start, visibility)
    assert once is not None and again is not None and error(once) > 1.0 and error(again) < 0.5
    assert FlowPose().rounds == 3  # the default


def test_the_true_pose_stays() -> None:
    anchor, query, visibility = anchor_and_query(True)
    pose = FlowPose(mode="unverified").pose(query, anchor, QUERY_H_ANCHOR, visibility)
    assert pose is not None and error(pose) < 0.5


def test_no_pose_without_visible_texture() -> None:
    anchor, query, _ = anchor_and_query(False)
    flat = torch.full_like(anchor, 0.5)
    assert FlowPose(mode="unverified").pose(query, flat, QUERY_H_ANCHOR) is None  # no gradient: nothing to fit
    hidden = torch.zeros(1, SIZE, SIZE)
    assert FlowPose(mode="unverified").pose(query, anchor, QUERY_H_ANCHOR, hidden) is None  # nothing shown
    bad = QUERY_H_ANCHOR.clone()
    bad[0, 0] = float("nan")
    assert FlowPose(mode="unverified").pose(query, anchor, bad) is None


@pytest.mark.parametrize(("key", "value", "named"), [
    ("mode", "sometimes", "flow_pose='sometimes'"), ("scale", 0, "scale=0"), ("preset", "slow", "preset='slow'"),
    ("finest_scale", -1, "finest_scale=-1"), ("variational_iterations", 1.5, "variational_iterations=1.5"),
    ("reproj_threshold", 0, "reproj_threshold=0"), ("min_points", 3, "min_points=3"),
    ("max_points", 5, "max_points=5"), ("texture", -1, "texture=-1"), ("dark", 255, "dark=255"),
    ("above", -0.1, "above=-0.1"), ("verifies", 3, "verifies=3"), ("max_upscale", 0.5, "max_upscale=0.5"),
    ("rounds", 0, "rounds=0")])
def test_bad_settings_are_one_line_errors(key: str, value: object, named: str) -> None:
    with pytest.raises(MatlError, match=named.replace("(", r"\(")) as info:
        FlowPose(**{key: value})
    assert "\n" not in str(info.value)


def test_settings_survive_a_copy() -> None:
    settings = FlowPose(mode="always", scale=3, texture=10.0)
    again = pickle.loads(pickle.dumps(settings))
    assert again.options() == settings.options() and again.active
    anchor, query, visibility = anchor_and_query(True)
    assert again.pose(query, anchor, QUERY_H_ANCHOR @ OFF, visibility) is not None


@pytest.fixture()
def gallery(tmp_path: Path) -> Path:
    write_png(tmp_path / "red_box" / "front.png", print_like(0, (0.8, 0.2, 0.1)))
    return tmp_path


def off_pose_recognizer(shift: float, **options) -> Recognizer:
    """One anchor, ``c()`` the mean colour, ``s()`` the truth shifted by ``shift`` px; the keypoint pose off (this
    file tests the flow pose alone)."""
    gallery_fit = fit_geometry(*GALLERY_HW, SIZE).model_H_file
    query_fit = fit_geometry(*QUERY_HW, SIZE).model_H_file
    truth = query_fit @ torch.from_numpy(QUERY_H_GALLERY) @ torch.linalg.inv(gallery_fit)
    wrong = truth @ torch.tensor([[1.0, 0.0, shift], [0.0, 1.0, -shift], [0.0, 0.0, 1.0]], dtype=torch.float64)
    options = {"threshold": None, "foreground": "none", "keypoint_pose": "none", **options}
    return Recognizer(StubModel(wrong), SIZE, 1, "stub-model", **options)


def test_an_answer_that_does_not_verify_takes_the_flow_pose(gallery: Path) -> None:
    query = hidden_query(print_like(0, (0.8, 0.2, 0.1)))
    without = off_pose_recognizer(4.0, flow_pose="none").enrol(gallery, cache=False).predict(query)
    answer = off_pose_recognizer(4.0, flow_pose="unverified").enrol(gallery, cache=False).predict(query)
    assert error_px(without.H) > 4.0 and error_px(answer.H) < 3.0
    assert answer.verification < without.verification
    assert off_pose_recognizer(4.0).options()["flow_pose"]["mode"] == "always"  # the default


def test_a_pose_that_verifies_is_left_alone(gallery: Path) -> None:
    query = hidden_query(print_like(0, (0.8, 0.2, 0.1)))
    # verify_max=2 verifies every pose: unverified leaves it, always (the default) corrects it where it verifies
    # better, unless its verification distance is at most ``above``
    loose = off_pose_recognizer(4.0, verify_max=2.0, flow_pose="unverified").enrol(gallery, cache=False).predict(query)
    always = off_pose_recognizer(4.0, verify_max=2.0).enrol(gallery, cache=False).predict(query)
    assert error_px(loose.H) > 4.0 and error_px(always.H) < 3.0
    close = FlowPose(mode="always", above=loose.verification + 0.01)
    kept = off_pose_recognizer(4.0, verify_max=2.0, flow_pose=close).enrol(gallery, cache=False).predict(query)
    np.testing.assert_array_equal(kept.H, loose.H)


def test_an_answer_the_flow_pose_alone_makes_verify_counts_as_verified_only_within_verifies(gallery: Path) -> None:
    query = hidden_query(print_like(0, (0.8, 0.2, 0.1)))
    # verify_max=0.3: the networks' pose does not verify, the flow pose does; the open-set statistic is 0 for an
    # answer counted as verified
    strict = {"verify_max": 0.3, "verify_refine": False}  # no candidate refinement: the networks' pose stays

    def answer(**options) -> Match:
        return off_pose_recognizer(4.0, **strict, **options).enrol(gallery, cache=False).predict(query)

    plain, never = answer(flow_pose="none"), answer(flow_pose=FlowPose(mode="always", verifies=None))
    counted = answer(flow_pose=FlowPose(mode="always", verifies=0.3))
    below = answer(flow_pose=FlowPose(mode="always", verifies=never.verification - 1e-6))
    assert plain.verification > 0.3 and never.verification <= 0.3 and counted.verification == never.verification
    assert never.statistic == plain.statistic > 0.0 and counted.statistic == 0.0 and below.statistic > 0.0
    default = answer()  # verifies=0.08
    assert default.verification == never.verification
    assert (default.statistic == 0.0) == (default.verification <= 0.08)
    assert FlowPose().verifies == 0.08


def test_an_answer_held_unverified_below_verify_max_stays_so(gallery: Path) -> None:
    # an answer whose pose verifies but that is not counted as verified (another product's keypoint pose, which can
    # be a product lying across an unenrolled one) is not made verified by the flow pose
    query = hidden_query(print_like(0, (0.8, 0.2, 0.1)))
    recognizer = off_pose_recognizer(4.0, verify_max=2.0, flow_pose=FlowPose(mode="always", verifies=2.0)).enrol(
        gallery, cache=False)
    held = recognizer._flow_poses

    def flow_poses(queries, pred, verification, visibility, upscale=None):
        unverified = dataclasses.replace(verification, verified=torch.zeros_like(verification.verified))
        return held(queries, pred, unverified, visibility, upscale)

    recognizer._flow_poses = flow_poses
    answer = recognizer.predict(query)
    assert error_px(answer.H) < 3.0  # the flow pose is taken ...
    assert answer.statistic > 0.0  # ... and the answer stays unverified


def test_rounds_after_the_first_go_on_only_while_the_answer_does_not_verify(gallery: Path) -> None:
    query = hidden_query(print_like(0, (0.8, 0.2, 0.1)))

    def rounds_run(verify_max: float) -> tuple[int, Match]:
        settings = FlowPose(mode="always", above=0.0, rounds=3)
        one_round, calls = settings.step, []

        def step(*args):
            calls.append(args)
            return one_round(*args)

        settings.step = step
        answer = off_pose_recognizer(4.0, verify_max=verify_max, flow_pose=settings).enrol(
            gallery, cache=False).predict(query)
        return len(calls), answer

    verifying, answer = rounds_run(2.0)  # every pose verifies: the first round only
    assert verifying == 1 and error_px(answer.H) < 3.0
    strict, answer = rounds_run(1e-6)  # no pose verifies: the rounds go on until they settle or stop converging
    assert strict > 1 and error_px(answer.H) < 3.0


def test_a_query_enlarged_beyond_max_upscale_is_left_alone(gallery: Path) -> None:
    small = cv2.resize(hidden_query(print_like(0, (0.8, 0.2, 0.1))), (75, 70), interpolation=cv2.INTER_AREA)
    # 75 px on the longer side: enlarged 1.33 times to the model's 100 px
    plain = off_pose_recognizer(4.0, flow_pose="none").enrol(gallery, cache=False).predict(small)
    skipped = off_pose_recognizer(4.0, flow_pose=FlowPose(mode="always", max_upscale=1.2)).enrol(
        gallery, cache=False).predict(small)
    tried = off_pose_recognizer(4.0, flow_pose=FlowPose(mode="always", max_upscale=1.5)).enrol(
        gallery, cache=False).predict(small)
    np.testing.assert_array_equal(skipped.H, plain.H)
    assert skipped.verification == plain.verification and tried.verification < plain.verification


def test_a_bad_flow_pose_option_is_a_one_line_error() -> None:
    with pytest.raises(MatlError, match="flow_pose=3 is invalid"):
        off_pose_recognizer(0.0, flow_pose=3)


@pytest.mark.parametrize("judge", ["both", "explained", "verification"])
def test_every_pose_judge_takes_the_better_flow_pose_and_the_true_one_stays(gallery: Path, judge: str) -> None:
    query = hidden_query(print_like(0, (0.8, 0.2, 0.1)))
    off = off_pose_recognizer(4.0, pose_judge=judge).enrol(gallery, cache=False)
    assert off.options()["pose_judge"] == judge and error_px(off.predict(query).H) < 3.0
    plain = off_pose_recognizer(0.0, flow_pose="none").enrol(gallery, cache=False).predict(query)
    judged = off_pose_recognizer(0.0, pose_judge=judge).enrol(gallery, cache=False).predict(query)
    assert error_px(judged.H) <= max(error_px(plain.H), 0.5)


def test_a_bad_pose_judge_is_a_one_line_error() -> None:
    with pytest.raises(MatlError, match="pose_judge='median' is invalid: use both or explained or verification"):
        off_pose_recognizer(0.0, pose_judge="median")
    assert off_pose_recognizer(0.0).options()["pose_judge"] == "both"  # the default


class Astray(FastRefiner):
    """The fast refinement, its poses then moved 6 px off (a refinement led away by an occluder)."""

    def __call__(self, queries: torch.Tensor, index: torch.Tensor, query_H_anchor: torch.Tensor, templates: object,
                 **options: object) -> RefineResult:
        result = super().__call__(queries, index, query_H_anchor, templates, **options)
        shift = torch.tensor([[1.0, 0.0, 6.0], [0.0, 1.0, -6.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
        return dataclasses.replace(result, query_H_anchor=result.query_H_anchor @ shift)


def test_a_refined_answer_that_does_not_verify_meets_its_unrefined_pose(gallery: Path) -> None:
    query = hidden_query(print_like(0, (0.8, 0.2, 0.1)))

    def answer(check: str, shift: float = 0.0, **options: object) -> Match:
        return off_pose_recognizer(shift, refine=Astray(), refine_check=check, flow_pose="none", **options).enrol(
            gallery, cache=False).predict(query)

    # s() gives the truth: refine_check=judge takes it over the refinement's pose 6 px off, which verifies worse
    astray, judged = answer("none"), answer("judge")
    assert error_px(astray.H) > 5.0 and error_px(judged.H) < 1.0 and judged.verification < astray.verification
    # s() 8 px off: the refined pose (6 px off the truth) is judged the better and stays
    np.testing.assert_array_equal(answer("judge", 8.0).H, answer("none", 8.0).H)
    # a refined answer that verifies (here every pose does) is left as it is
    np.testing.assert_array_equal(answer("judge", verify_max=2.0).H, answer("none", verify_max=2.0).H)
    assert off_pose_recognizer(0.0).options()["refine_check"] == "judge"  # the default
