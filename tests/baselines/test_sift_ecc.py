"""Tests of the SIFT + RANSAC + ECC baseline (``baseline=sift_ecc``, matl/baselines/ecc.py).

A synthetic gallery of the keypoint tests' shapes: 4 textured "labels" on a black background, each
with its 4 anchors (rotations by k * 90 deg about the image centre), 100 x 100 px, and 4 queries
warped from the canonical labels by known homographies.
"""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from hydra.utils import instantiate

from matl.baselines import SiftEccMatcher
from matl.baselines.ecc import EccRefiner, _scale_homography, corner_shift_px, foreground_masks
from matl.baselines.keypoints import MatchResult
from matl.baselines.sift import SiftRansacMatcher
from matl.evaluation.evaluate import evaluate
from tests.baselines.test_keypoints import _rotation
from tests.conftest import compose_config

SIZE = 100
N_ANCHORS = 4
N_PLANES = 4


# ---------------------------------------------------------------------------------------------------
# synthetic data


def _texture(rng: np.random.Generator) -> np.ndarray:
    """A label ``(SIZE, SIZE, 3)`` float32 in [0, 1]: smooth colour noise and shapes on a 70 x 64 body."""
    h, w = 64, 70
    body = np.empty((h, w, 3), np.float32)
    for c in range(3):
        body[..., c] = cv2.GaussianBlur(rng.random((h, w)).astype(np.float32), (0, 0), 1.5)
    body = (body - body.min()) / (body.max() - body.min()) * 0.6 + 0.2
    for _ in range(25):
        colour = tuple(float(v) for v in rng.uniform(0.05, 1.0, 3))
        x0, y0 = (int(v) for v in rng.integers(0, w, 2))
        a, b = (int(v) for v in rng.integers(2, 7, 2))
        if rng.random() < 0.5:
            cv2.rectangle(body, (x0, y0), (x0 + a, y0 + b), colour, -1)
        else:
            cv2.ellipse(body, (x0, y0), (a, b), float(rng.uniform(0, 180)), 0, 360, colour, -1)
    img = np.zeros((SIZE, SIZE, 3), np.float32)
    y0, x0 = (SIZE - h) // 2, (SIZE - w) // 2
    img[y0 : y0 + h, x0 : x0 + w] = body
    return img


def _homography(angle: float, scale: float, shift: tuple[float, float], persp: tuple[float, float]) -> np.ndarray:
    """``query_H_canon``: rotation and scale about the centre, mild perspective, then a shift."""
    c = (SIZE - 1) / 2.0
    to_c = np.array([[1, 0, -c], [0, 1, -c], [0, 0, 1]], float)
    a = math.radians(angle)
    core = np.array([[scale * math.cos(a), -scale * math.sin(a), 0.0], [scale * math.sin(a), scale * math.cos(a), 0.0],
                     [persp[0], persp[1], 1.0]])
    back = np.array([[1, 0, c + shift[0]], [0, 1, c + shift[1]], [0, 0, 1]], float)
    H = back @ core @ to_c
    return H / H[2, 2]


def _warp(img: np.ndarray, H: np.ndarray) -> np.ndarray:
    """``out(H x) = img(x)``, zeros outside."""
    return cv2.warpPerspective(img, H, (SIZE, SIZE), flags=cv2.INTER_LINEAR, borderValue=0)


def _to_tensor(images: list[np.ndarray]) -> torch.Tensor:
    return torch.from_numpy(np.stack(images)).permute(0, 3, 1, 2).contiguous()


QUERY_POSES = [
    (0, _homography(25.0, 1.05, (3.0, -2.0), (0.0008, -0.0005))),
    (1, _homography(-120.0, 0.9, (-4.0, 4.0), (-0.0006, 0.0007))),
    (2, _homography(160.0, 1.1, (2.0, 5.0), (0.0005, 0.0005))),
    (3, _homography(70.0, 0.95, (-3.0, -3.0), (0.0, -0.0008))),
]


@pytest.fixture(scope="module")
def scene() -> dict:
    """Gallery ``(16, 3, 100, 100)`` (4 planes x 4 anchors), 4 queries and their true ``query_H_anchor``."""
    rng = np.random.default_rng(3)
    canon = [_texture(rng) for _ in range(N_PLANES)]
    anchor_H_canon = [_rotation(k * 360.0 / N_ANCHORS) for k in range(N_ANCHORS)]
    return {
        "gallery": _to_tensor([_warp(c, H) for c in canon for H in anchor_H_canon]),
        "queries": _to_tensor([_warp(canon[p], H) for p, H in QUERY_POSES]),
        "planes": [p for p, _ in QUERY_POSES],
        "query_H_canon": [H for _, H in QUERY_POSES],
        "anchor_H_canon": anchor_H_canon,
    }


@pytest.fixture(scope="module")
def sift_result(scene: dict) -> MatchResult:
    matcher = SiftRansacMatcher()
    matcher.index_gallery(scene["gallery"])
    return matcher.match(scene["queries"])


@pytest.fixture(scope="module")
def ecc_matcher(scene: dict) -> SiftEccMatcher:
    matcher = SiftEccMatcher()
    matcher.index_gallery(scene["gallery"])
    return matcher


def _corner_errors(result: MatchResult, scene: dict) -> list[float]:
    """Mean corner distance (px) of each query's ``query_H_anchor`` to the true one of the matched anchor."""
    errors = []
    for i, plane in enumerate(scene["planes"]):
        g = int(result.gallery_index[i])
        assert g // N_ANCHORS == plane, f"query {i} matched gallery image {g}"
        true = scene["query_H_canon"][i] @ np.linalg.inv(scene["anchor_H_canon"][g % N_ANCHORS])
        c = np.array([[0, SIZE - 1, SIZE - 1, 0], [0, 0, SIZE - 1, SIZE - 1], [1, 1, 1, 1]], float)
        a, b = result.query_H_anchor[i].numpy() @ c, true @ c
        errors.append(float(np.linalg.norm(a[:2] / a[2] - b[:2] / b[2], axis=0).mean()))
    return errors


# ---------------------------------------------------------------------------------------------------
# conventions


def test_ecc_warp_is_query_H_anchor() -> None:
    """ECC's warp maps template (anchor) pixels to input (query) pixels: it *is* query_H_anchor."""
    rng = np.random.default_rng(0)
    anchor = _texture(rng)
    query_H_anchor = _homography(12.0, 1.04, (2.0, -1.5), (0.0004, -0.0003))
    query = _warp(anchor, query_H_anchor)
    start = np.array([[1, 0, 0.8], [0, 1, -0.6], [0, 0, 1]]) @ query_H_anchor  # RANSAC-like, ~1 px off
    grey = lambda im: cv2.cvtColor(im, cv2.COLOR_RGB2GRAY)  # noqa: E731
    mask = foreground_masks(torch.from_numpy(anchor).permute(2, 0, 1)[None])[0]
    out = EccRefiner()(grey(anchor), mask, grey(query), start)
    assert out.outcome == "refined"
    assert corner_shift_px(start, query_H_anchor, (SIZE, SIZE)) == pytest.approx(1.0, abs=1e-9)
    assert corner_shift_px(out.query_H_anchor, query_H_anchor, (SIZE, SIZE)) < 0.2
    assert out.query_H_anchor[2, 2] == 1.0 and out.query_H_anchor.dtype == np.float64


def test_corner_shift_and_pyramid_scaling_hand_values() -> None:
    shift = np.array([[1, 0, 3.0], [0, 1, 4.0], [0, 0, 1]])
    assert corner_shift_px(shift, np.eye(3), (SIZE, SIZE)) == pytest.approx(5.0)
    zoom = np.diag([2.0, 2.0, 1.0])  # about the origin: corner (99, 99) goes to (198, 198)
    assert corner_shift_px(zoom, np.eye(3), (SIZE, SIZE)) == pytest.approx(99.0 * math.sqrt(2.0))
    to_infinity = np.array([[1, 0, 0], [0, 1, 0], [-0.02, 0, 1.0]])  # w = 0 at x = 50
    assert corner_shift_px(to_infinity, np.eye(3), (SIZE, SIZE)) == math.inf
    # cv2.pyrDown: pixel i of the coarse level sits at pixel 2 i, so a 3 px shift is 1.5 px there
    np.testing.assert_allclose(_scale_homography(shift, 0.5), [[1, 0, 1.5], [0, 1, 2.0], [0, 0, 1]])
    H = _homography(40.0, 1.1, (2.0, 3.0), (0.001, -0.002))
    np.testing.assert_allclose(_scale_homography(_scale_homography(H, 0.5), 2.0), H, atol=1e-12)


def test_foreground_masks() -> None:
    images = torch.zeros(2, 3, 2, 3)
    images[0, 1, 0, 2] = 0.5
    images[1, 0, 1, 0] = 1e-4  # below the foreground threshold
    images[1, 2, 1, 1] = 0.01
    masks = foreground_masks(images)
    assert masks.dtype == np.uint8
    assert masks.tolist() == [[[0, 0, 1], [0, 0, 0]], [[0, 0, 0], [0, 1, 0]]]


# ---------------------------------------------------------------------------------------------------
# the matcher


def test_sift_ecc_registers_better_than_sift(scene: dict, sift_result: MatchResult,
                                             ecc_matcher: SiftEccMatcher) -> None:
    result = ecc_matcher.match(scene["queries"])
    assert result.gallery_index.shape == (4,) and result.gallery_index.dtype == torch.int64
    assert result.query_H_anchor.shape == (4, 3, 3) and result.query_H_anchor.dtype == torch.float64
    # recognition is SIFT's, unchanged
    assert torch.equal(result.gallery_index, sift_result.gallery_index)
    assert torch.equal(result.inliers, sift_result.inliers)
    sift_err, ecc_err = _corner_errors(sift_result, scene), _corner_errors(result, scene)
    assert max(ecc_err) < 1.0, ecc_err
    assert all(e < s for e, s in zip(ecc_err, sift_err, strict=True)), (ecc_err, sift_err)
    assert np.allclose(result.query_H_anchor[:, 2, 2].numpy(), 1.0)


def test_coarse_to_fine(scene: dict) -> None:
    two_levels = SiftEccMatcher(ecc_levels=2)
    two_levels.index_gallery(scene["gallery"])
    assert max(_corner_errors(two_levels.match(scene["queries"]), scene)) < 1.0


def test_older_opencv_is_a_one_line_error(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delattr(cv2, "findTransformECCWithMask", raising=False)
    with pytest.raises(ValueError, match="findTransformECCWithMask") as info:
        SiftEccMatcher()
    assert "\n" not in str(info.value)


def test_ecc_failure_keeps_ransac_homography(scene: dict, sift_result: MatchResult,
                                             ecc_matcher: SiftEccMatcher) -> None:
    # a query that is flat where the anchor is textured: OpenCV's ECC fails (NaN correlation)
    start = sift_result.query_H_anchor[0].numpy()
    g = int(sift_result.gallery_index[0])
    flat = torch.full((3, SIZE, SIZE), 0.5)
    out = ecc_matcher.refine(flat, g, start)
    assert out.outcome == "failed" and math.isnan(out.corner_shift_px)
    assert np.array_equal(out.query_H_anchor, start)


@pytest.mark.parametrize(("ecc", "outcome"), [
    ("raise", "failed"),
    ("nan", "failed"),
    ("shift_10.5", "rejected"),
    ("shift_9.5", "refined"),
])
def test_guard_outcomes(ecc: str, outcome: str, scene: dict, sift_result: MatchResult,
                        monkeypatch: pytest.MonkeyPatch) -> None:
    """ECC raising, returning NaN or moving a corner by more than max_corner_shift_px keeps RANSAC's H bit for bit."""
    matcher = SiftEccMatcher(max_corner_shift_px=10)
    matcher.index_gallery(scene["gallery"])
    moved = np.array([[1.0, 0, 0], [0, 1, 0], [0, 0, 1]])

    def fake_ecc(template: np.ndarray, query: np.ndarray, mask: np.ndarray, H: np.ndarray) -> np.ndarray:
        if ecc == "raise":
            raise cv2.error("Iterations do not converge")
        if ecc == "nan":
            return np.full((3, 3), np.nan)
        moved[0, 2] = float(ecc.split("_")[1])
        return moved @ H  # every corner moves by exactly that many pixels in x

    monkeypatch.setattr(matcher.refiner, "_ecc", fake_ecc)
    start = sift_result.query_H_anchor[1].numpy()
    out = matcher.refine(scene["queries"][1], int(sift_result.gallery_index[1]), start)
    assert out.outcome == outcome
    result = matcher.match(scene["queries"])
    if outcome == "refined":
        assert out.corner_shift_px == pytest.approx(9.5)
        np.testing.assert_allclose(out.query_H_anchor, moved @ start, atol=1e-9)
        assert not torch.equal(result.query_H_anchor, sift_result.query_H_anchor)
    else:
        assert np.array_equal(out.query_H_anchor, start)
        assert torch.equal(result.query_H_anchor, sift_result.query_H_anchor)
    assert torch.equal(result.gallery_index, sift_result.gallery_index)


def test_unmatched_query_gives_minus_one_and_identity(ecc_matcher: SiftEccMatcher) -> None:
    result = ecc_matcher.match(torch.zeros(2, 3, SIZE, SIZE))
    assert result.gallery_index.tolist() == [-1, -1]
    assert torch.equal(result.query_H_anchor, torch.eye(3, dtype=torch.float64).repeat(2, 1, 1))


def test_errors() -> None:
    matcher = SiftEccMatcher()
    with pytest.raises(RuntimeError, match="index_gallery"):
        matcher.match(torch.zeros(1, 3, SIZE, SIZE))
    with pytest.raises(RuntimeError, match="index_gallery"):
        matcher.refine(torch.zeros(3, SIZE, SIZE), 0, np.eye(3))
    for bad in ({"ecc_iterations": 0}, {"ecc_gauss_filter_size": 4}, {"ecc_levels": 0}, {"max_corner_shift_px": 0}):
        with pytest.raises(ValueError, match=next(iter(bad)).removeprefix("ecc_")):
            SiftEccMatcher(**bad)


# ---------------------------------------------------------------------------------------------------
# config and evaluator


def test_config_composes_and_instantiates() -> None:
    cfg = compose_config("eval", ["baseline=sift_ecc"])
    sift_cfg = compose_config("eval", ["baseline=sift"])
    for key, value in sift_cfg.baseline.items():  # RANSAC's part is baseline=sift's, value for value
        if key != "_target_":
            assert cfg.baseline[key] == value, key
    matcher = instantiate(cfg.baseline)
    assert isinstance(matcher, SiftEccMatcher) and isinstance(matcher, SiftRansacMatcher)
    assert (matcher.sigma, matcher.contrast_threshold, matcher.edge_threshold) == (1.6, 0.004, 1000.0)
    r = matcher.refiner
    assert (r.iterations, r.epsilon, r.gauss_filter_size, r.levels, r.max_corner_shift_px) == (
        cfg.baseline.ecc_iterations, cfg.baseline.ecc_epsilon, cfg.baseline.ecc_gauss_filter_size,
        cfg.baseline.ecc_levels, 10.0)


def test_evaluator_runs_sift_ecc(tmp_path: Path, cache_dir: Path) -> None:
    overrides = ["baseline=sift_ecc", "data=synthetic_arc", "data.image_size=32", "data.test_queries=6",
                 "timing_queries=2", f"paths.cache_dir={cache_dir}"]
    out = evaluate(compose_config("eval", overrides, tmp_path), show_progress=False)
    # outside a Hydra run there is no group choice: the evaluator names the baseline by its class
    assert out["evaluated"] == "baseline" and out["baseline"] == "SiftEccMatcher" and out["num_queries"] == 6
    assert 0.0 <= out["rec_acc"] <= 1.0 and out["query_ms"] > 0
