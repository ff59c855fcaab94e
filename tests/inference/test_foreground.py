"""The foreground step of RGB queries without a mask (matl/inference/foreground.py) and its hook in the API."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from matl.inference.foreground import (
    FOREGROUNDS,
    GrabCutForeground,
    LearnedForeground,
    foreground_option,
    mask_query,
    pose_mask,
    split_alpha,
)
from matl.models.visibility import VisibilityNet
from matl.utils.errors import MatlError
from tests.inference.test_api import read_rgb, stub_recognizer
from tests.predict_helpers import make_files, smooth_texture

REPO = Path(__file__).resolve().parents[2]


def grey_texture(height: int, width: int, seed: int) -> np.ndarray:
    """A busy grey background ``(H, W, 3)`` in [0, 1] (gravel-like blobs)."""
    rng = np.random.default_rng(seed)
    noise = cv2.GaussianBlur(rng.random((height, width)), (0, 0), 1.5)
    grey = 0.25 + 0.5 * (noise - noise.min()) / (noise.max() - noise.min())
    return np.repeat(grey[..., None], 3, axis=-1)


def rotated_box(height: int, width: int, centre: tuple[float, float], size: tuple[float, float],
                angle: float) -> np.ndarray:
    """``(H, W)`` float32 mask of a filled rotated rectangle."""
    points = cv2.boxPoints(((centre[0], centre[1]), size, angle))
    mask = np.zeros((height, width), np.uint8)
    cv2.fillPoly(mask, [np.round(points).astype(np.int32)], 1)
    return mask.astype(np.float32)


def clutter_scene(seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A 96x96 crop: a red product in the middle, a blue neighbour cut by the right edge, a grey background.

    Returns the RGB image and the product's true mask.
    """
    h = w = 96
    product = rotated_box(h, w, (46.0, 50.0), (46.0, 30.0), 25.0)
    neighbour = rotated_box(h, w, (100.0, 30.0), (40.0, 40.0), -10.0)
    image = grey_texture(h, w, seed)
    for mask, colour, k in ((neighbour, (0.15, 0.2, 1.0), 1), (product, (1.0, 0.15, 0.1), 2)):
        image = np.where(mask[..., None] > 0, smooth_texture(h, w, colour, seed=k), image)
    return image.astype(np.float32), product


def iou(a: np.ndarray, b: np.ndarray) -> float:
    return float(((a > 0.5) & (b > 0.5)).sum() / ((a > 0.5) | (b > 0.5)).sum())


def test_grabcut_finds_the_product_and_leaves_out_the_neighbour() -> None:
    image, truth = clutter_scene()
    alpha = GrabCutForeground()(image)
    assert alpha.shape == truth.shape and alpha.dtype == np.float32 and set(np.unique(alpha)) <= {0.0, 1.0}
    assert iou(alpha, truth) > 0.9
    assert alpha[:, 88:].sum() == 0  # the neighbour, cut by the crop's edge, is background
    assert np.array_equal(alpha, GrabCutForeground()(image))  # seeded: the same mask every time


def test_a_black_border_is_already_segmented_and_degenerate_crops_keep_every_pixel() -> None:
    image, truth = clutter_scene()
    black = image * truth[..., None]  # the training convention: background exactly 0
    assert np.array_equal(GrabCutForeground()(black), np.ones(truth.shape, np.float32))
    assert GrabCutForeground()(black + 0.01).min() == 0.0  # a grey border is not black: segmented
    reaching = black.copy()
    reaching[:, :2] = 0.8  # a product covering a quarter of the band: still black
    assert GrabCutForeground()(reaching).min() == 1.0 and GrabCutForeground(black_fraction=0.9)(reaching).min() == 0.0
    assert np.array_equal(GrabCutForeground()(image[:5, :5]), np.ones((5, 5), np.float32))  # too small for the band
    flat = np.full((40, 40, 3), 0.5, np.float32)  # nothing to separate
    assert GrabCutForeground()(flat).shape == (40, 40)


def test_split_alpha_and_options() -> None:
    rgba = np.random.default_rng(0).random((8, 6, 4)).astype(np.float32)
    rgb, alpha = split_alpha(rgba)
    assert np.allclose(rgb, rgba[..., :3] * rgba[..., 3:]) and np.array_equal(alpha, rgba[..., 3])
    assert split_alpha(rgba[..., :3])[1] is None
    assert foreground_option("none") is None and foreground_option(None) is None
    assert foreground_option("grabcut") == GrabCutForeground()
    step = GrabCutForeground(passes=2)
    assert foreground_option(step) is step
    for name in ("grabcut", "none"):  # the config group's files
        node = OmegaConf.load(REPO / "conf" / "foreground" / f"{name}.yaml")
        assert foreground_option(node) == (GrabCutForeground() if name == "grabcut" else None)
    with pytest.raises(MatlError, match="foreground='rembg' is invalid"):
        foreground_option("rembg")
    with pytest.raises(MatlError, match="inset_px >= 1"):
        GrabCutForeground(inset_px=0)
    with pytest.raises(MatlError, match="foreground: "):
        foreground_option(OmegaConf.create({"_target_": "matl.inference.foreground.GrabCutForeground", "size": 1}))


def test_an_imperfect_alpha_is_decided_within_its_band() -> None:
    image, truth = clutter_scene()
    grown = cv2.dilate(truth, np.ones((7, 7), np.uint8))  # a segmentation 3 px too wide
    alpha = GrabCutForeground()
    refined = alpha.refine_alpha(image, grown)
    assert iou(refined, truth) > iou(grown, truth) + 0.05 and iou(refined, truth) > 0.9
    far = cv2.dilate(grown, np.ones((9, 9), np.uint8)) == 0  # farther than the band: as the alpha says
    assert refined[far].sum() == 0
    assert refined[cv2.erode(truth, np.ones((11, 11), np.uint8)) > 0].min() == 1.0
    assert GrabCutForeground(alpha_band_px=0).refine_alpha(image, grown) is grown
    everything = np.ones(truth.shape, np.float32)  # no pixel surely outside: kept as given
    assert alpha.refine_alpha(image, everything) is everything
    rgba = np.dstack([image, grown])
    masked, rgb, found = mask_query(alpha, rgba)
    assert found is None and np.array_equal(rgb, image) and np.allclose(masked, image * refined[..., None])
    masked, rgb, found = mask_query(None, rgba)
    assert found is None and np.allclose(masked, image * grown[..., None])
    masked, rgb, found = mask_query(alpha, image)
    assert found is not None and np.allclose(masked, image * found[..., None])
    assert mask_query(None, image)[2] is None


def test_pose_mask_is_the_planes_foreground_warped_by_its_pose() -> None:
    canon = torch.zeros(1, 3, 20, 20)
    canon[:, :, 5:10, 4:8] = 0.5
    same = pose_mask(canon, torch.eye(3)[None], 20)
    assert same.shape == (1, 1, 20, 20) and torch.equal(same[0, 0] > 0.5, canon[0, 0] > 0)
    shift = torch.tensor([[[1.0, 0.0, 3.0], [0.0, 1.0, 2.0], [0.0, 0.0, 1.0]]])
    moved = pose_mask(canon, shift, 20)[0, 0]
    assert torch.allclose(moved[7:12, 7:11], torch.ones(5, 4)) and float(moved.sum()) == pytest.approx(20.0)


def cluttered_query(queries: Path, name: str) -> tuple[np.ndarray, np.ndarray]:
    """make_files' query of ``name`` on a blue-grey wall, a blue neighbour filling the left half (uint8)."""
    query = read_rgb(queries / f"{name}.png").astype(np.float32) / 255.0
    h, w = query.shape[:2]
    inside = (query.max(-1) > 0).astype(np.float32)
    neighbour = rotated_box(h, w, (0.0, 0.5 * h), (96.0, 2.0 * h), 0.0) * (1 - inside)
    scene = np.where(inside[..., None] > 0, query, grey_texture(h, w, 3) * np.array([0.5, 0.6, 1.0]))
    scene = np.where(neighbour[..., None] > 0, smooth_texture(h, w, (0.15, 0.2, 1.0), seed=7), scene)
    return (scene * 255).round().astype(np.uint8), inside


@pytest.mark.parametrize("passes", [0, 1])
def test_recognizer_segments_rgb_queries_and_keeps_an_rgba_querys_alpha(tmp_path: Path, passes: int) -> None:
    gallery, queries, _ = make_files(tmp_path)
    scene, inside = cluttered_query(queries, "green_can")
    # verification off: the foreground step alone (verification's re-ranking would also find the can)
    plain = stub_recognizer(threshold=None, foreground="none", verify_top_k=0).enrol(gallery)
    assert plain.predict(scene).object != "green_can"  # the background's blue wins the mean colour
    # with verification the nearest anchor's pose does not verify, a further candidate does: the answer is re-ranked
    reranked = stub_recognizer(threshold=None, foreground="none").enrol(gallery).predict(scene)
    assert reranked.object == "green_can" and reranked.verification <= 0.1
    rec = stub_recognizer(threshold=None, foreground=GrabCutForeground(passes=passes, alpha_band_px=0),
                          verify_top_k=0).enrol(gallery)
    assert rec.options()["foreground"]["passes"] == passes
    assert rec.predict(scene).object == "green_can"
    # an RGBA query uses its own alpha, not the crop's GrabCut: a mask holding the neighbour too
    alpha = np.zeros(inside.shape, np.uint8)
    alpha[:, : inside.shape[1] // 2] = 255
    rgba = rec.predict(np.dstack([scene, alpha]))
    given = plain.predict((scene * (alpha[..., None] > 0)).astype(np.uint8))
    assert rgba.object == given.object and rgba.distance == pytest.approx(given.distance)
    # black-background queries (the convention) are used as given: the same answers as without the step
    clean = read_rgb(queries / "red_box.png")
    assert rec.predict(clean).distance == pytest.approx(plain.predict(clean).distance)
    assert math.isfinite(rec.predict(clean).distance)


@dataclass(eq=False)
class ScriptedForeground(GrabCutForeground):
    """GrabCut replaced by given masks where it would run: ``first``, and ``later`` as the retries (counted)."""

    first: np.ndarray | None = None
    later: list[np.ndarray] | None = None
    asked: int = 0

    def __call__(self, rgb: np.ndarray) -> np.ndarray:
        return self.first if self.segments(rgb) else np.ones(rgb.shape[:2], np.float32)

    def retries(self, rgb: np.ndarray) -> list[np.ndarray]:
        self.asked += 1
        return list(self.later or []) if self.segments(rgb) else []


def test_a_query_whose_answer_does_not_verify_is_masked_again_and_keeps_the_best_verified(tmp_path: Path) -> None:
    gallery, queries, _ = make_files(tmp_path)
    scene, inside = cluttered_query(queries, "green_can")
    neighbour = np.zeros(inside.shape, np.float32)
    neighbour[:, : inside.shape[1] // 3] = 1.0  # a mask on the neighbour alone: nothing there verifies
    step = ScriptedForeground(alpha_band_px=0, first=neighbour, later=[neighbour, inside])
    first = stub_recognizer(threshold=None, foreground=ScriptedForeground(alpha_band_px=0, first=neighbour,
                                                                          retry_insets=())).enrol(gallery)
    wrong = first.predict(scene)
    assert not wrong.verification <= 0.1  # the first mask's answer does not verify
    rec = stub_recognizer(threshold=None, foreground=step).enrol(gallery)
    right = rec.predict(scene)
    assert step.asked == 1 and right.object == "green_can" and right.verification <= 0.1
    truth = stub_recognizer(threshold=None, foreground=ScriptedForeground(alpha_band_px=0, first=inside)).enrol(gallery)
    expected = truth.predict(scene)  # the answer of the retry's mask, as if it had been the first
    assert right.distance == pytest.approx(expected.distance) and np.allclose(right.H, expected.H)
    # a batch: only the query that does not verify is retried, and the other keeps its answer
    clean = read_rgb(queries / "red_box.png")
    step.asked = 0
    both = rec.predict([clean, scene])
    assert step.asked == 1 and [m.object for m in both] == ["red_box", "green_can"]
    # retries that verify no better leave the first answer as it was
    worse = ScriptedForeground(alpha_band_px=0, first=neighbour, later=[neighbour])
    same = stub_recognizer(threshold=None, foreground=worse).enrol(gallery).predict(scene)
    assert worse.asked == 1 and same.object == wrong.object and same.distance == pytest.approx(wrong.distance)


def test_retries_mask_from_wider_insets_and_only_crops_grabcut_segments() -> None:
    image, truth = clutter_scene()
    step = GrabCutForeground(retry_insets=(0.08, 0.2))
    masks = step.retries(image)
    assert len(masks) == 2 and all(m.shape == truth.shape and iou(m, truth) > 0.8 for m in masks)
    assert np.array_equal(masks[0], step.segment(image, round(0.08 * 96)))
    assert step.retries(image * truth[..., None]) == []  # a black border: used as given, nothing to retry
    assert GrabCutForeground(retry_insets=[0.1]).retry_insets == (0.1,)
    for bad in ([0.0], [0.5], ["wide"]):
        with pytest.raises(MatlError, match="retry_insets"):
            GrabCutForeground(retry_insets=bad)


# ------------------------------------------------------------------------------------------ foreground=learned
def tiny_learned(**settings) -> LearnedForeground:
    """A LearnedForeground around an untrained 32 px network (its masks are arbitrary; its plumbing is not)."""
    torch.manual_seed(0)
    return LearnedForeground.from_network(VisibilityNet(size=32, channels=(4, 6, 8)).eval(), **settings)


class FixedProbability(LearnedForeground):
    """LearnedForeground whose probability map is given (the post-processing under test; GrabCut, from the map or
    from rectangles, only where the settings ask for it)."""

    def __init__(self, prob: np.ndarray, **settings) -> None:
        self.__dict__["_given"] = VisibilityNet(size=16, channels=(2, 2, 2))
        super().__init__(**{"grabcut_iterations": 0, "retry_insets": (), **settings})
        self.prob = prob

    def probability(self, rgb: np.ndarray) -> np.ndarray:
        return self.prob


def test_learned_probability_runs_in_onnxruntime_like_torch() -> None:
    pytest.importorskip("onnxruntime")
    image, _ = clutter_scene()
    onnx, plain = tiny_learned(threads=1), tiny_learned(runtime="torch")
    assert onnx.prepare() == "onnxruntime" and 1 in onnx._sessions  # the session opened before the first crop
    p = onnx.probability(image)
    assert p.shape == image.shape[:2] and p.dtype == np.float32 and p.min() >= 0.0 and p.max() <= 1.0
    assert onnx.runtime_in_use == "onnxruntime" and plain.runtime_in_use == "torch" and onnx.failure is None
    assert np.abs(onnx.logits(image) - plain.logits(image)).max() < 1e-4
    assert onnx.probability(image[:50, :70]).shape == (50, 70)  # any size: resized to 32 and back
    assert tiny_learned(size=48).working_size == 48


def test_learned_mask_keeps_the_centred_product_and_fills_only_probable_holes() -> None:
    prob = np.zeros((60, 60), np.float32)
    prob[15:45, 15:45] = 0.9                     # the product, centred
    prob[0:10, 50:60] = 0.95                     # a neighbour in the corner, outside the centre region
    prob[25:28, 25:28] = 0.3                     # a small hole the network was unsure of: filled
    prob[33:40, 33:40] = 0.02                    # an occluder's hole: stays out
    image = np.full((60, 60, 3), 0.5, np.float32)
    step = FixedProbability(prob)
    mask = step(image)
    assert mask.dtype == np.float32 and set(np.unique(mask)) <= {0.0, 1.0}
    assert mask[0:10, 50:60].sum() == 0 and mask[25:28, 25:28].min() == 1.0 and mask[33:40, 33:40].max() == 0.0
    assert FixedProbability(prob, hole_probability=0.5)(image)[25:28, 25:28].max() == 0.0
    assert FixedProbability(prob, hole_area=0.0)(image)[25:28, 25:28].max() == 0.0
    split = np.zeros((60, 60), np.float32)       # an occluder across the product splits it in two parts
    split[15:45, 15:28] = 0.9
    split[15:45, 33:45] = 0.9
    split[20:24, 40:44] = 0.0
    both = FixedProbability(split)(image)
    assert both[15:45, 15:28].min() == 1.0 and both[15:45, 33:40].min() == 1.0
    assert FixedProbability(split, min_part=1.0)(image)[15:45, 33:45].max() == 0.0  # the largest alone
    corner = np.zeros((60, 60), np.float32)
    corner[0:8, 0:8] = 0.9                       # nothing in the centre region: every pixel kept
    assert FixedProbability(corner)(image).min() == 1.0
    retries = FixedProbability(prob, retry_thresholds=(0.25, 0.6))
    low, high = retries.retries(image)
    assert np.array_equal(high, mask) and low[0:10, 50:60].sum() == 0 and low[25:28, 25:28].min() == 1.0
    assert len(FixedProbability(prob, retry_thresholds=(0.25, 0.92)).retries(image)) == 1  # nothing centred at 0.92
    assert FixedProbability(prob, retry_thresholds=()).retries(image) == []
    assert retries.retrying and not FixedProbability(prob, retry_thresholds=[]).retrying
    black = np.zeros((60, 60, 3), np.float32)
    black[15:45, 15:45] = 0.7                    # a black border: already segmented, used as given
    assert step(black).min() == 1.0 and step.retries(black) == []
    assert FixedProbability(prob, black_fraction=None)(black).min() == 0.0


def test_grabcut_from_the_learned_probability_follows_the_edge_and_keeps_what_it_rules_out_out() -> None:
    image, truth = clutter_scene()
    blunt = cv2.dilate(truth, np.ones((9, 9), np.uint8))  # the product, its edge 4 px too wide (a 64 px map's blur)
    prob = np.where(blunt > 0, 0.8, 0.3).astype(np.float32)
    alone, snapped = FixedProbability(prob), FixedProbability(prob, grabcut_iterations=1)
    assert iou(snapped(image), truth) > 0.9 > iou(alone(image), truth)
    occluder = np.zeros_like(truth)
    occluder[40:60, 30:60] = 1.0                 # a grey bar across the product that the network rules out
    covered = np.where(occluder[..., None] > 0, np.float32(0.7), image).astype(np.float32)
    ruled_out = np.where(occluder > 0, 0.02, prob).astype(np.float32)
    mask = FixedProbability(ruled_out, grabcut_iterations=1)(covered)
    assert mask[occluder > 0].max() == 0.0 and iou(mask, truth * (1 - occluder)) > 0.9
    assert np.array_equal(mask, FixedProbability(ruled_out, grabcut_iterations=1)(covered))  # seeded
    large = cv2.resize(image, (288, 288), interpolation=cv2.INTER_LINEAR)  # segmented at max_side, resized back
    big = FixedProbability(cv2.resize(prob, (288, 288)), grabcut_iterations=1, max_side=100)(large)
    assert big.shape == (288, 288) and iou(big, cv2.resize(truth, (288, 288))) > 0.85
    nothing = FixedProbability(np.zeros_like(prob), grabcut_iterations=1)(image)  # everything ruled out
    assert nothing.min() == 1.0  # nothing found: every pixel kept, as without GrabCut
    eaten = FixedProbability(prob, grabcut_iterations=1, min_kept=1.0)  # GrabCut's mask smaller than the network's:
    assert np.array_equal(eaten(image), alone(image))                   # the network's own mask is kept


def test_learned_retries_add_grabcuts_masks_from_rectangles() -> None:
    image, truth = clutter_scene()
    prob = np.where(truth > 0, 0.8, 0.1).astype(np.float32)
    step = FixedProbability(prob, retry_thresholds=(0.3,), retry_insets=(0.0, 0.1))
    network, band, wider = step.retries(image)
    assert np.array_equal(network, step.mask(prob, 0.3))
    grabcut = GrabCutForeground()  # foreground=grabcut's masks, from the border band and from 10 % of the side in
    assert np.array_equal(band, grabcut(image)) and np.array_equal(wider, grabcut.segment(image, round(0.1 * 96)))
    assert FixedProbability(prob, retry_thresholds=(), retry_insets=(0.0,)).retrying
    assert not FixedProbability(prob, retry_thresholds=(), retry_insets=()).retrying
    for bad in ([0.5], [-0.1], ["wide"]):
        with pytest.raises(MatlError, match="retry_insets"):
            FixedProbability(prob, retry_insets=bad)


def test_learned_alpha_band_and_options(tmp_path: Path) -> None:
    prob = np.zeros((40, 40), np.float32)
    prob[10:30, 10:30] = 0.9
    image = np.full((40, 40, 3), 0.5, np.float32)
    grown = np.zeros((40, 40), np.float32)
    grown[7:33, 7:33] = 1.0                      # 3 px too wide
    refined = FixedProbability(prob, alpha_band_px=4).refine_alpha(image, grown)
    assert refined[10:30, 10:30].min() == 1.0 and refined.sum() == 400
    assert FixedProbability(prob, alpha_band_px=0).refine_alpha(image, grown) is grown  # as given
    for bad in ({"threshold": 1.0}, {"retry_thresholds": [0.0]}, {"retry_thresholds": ["low"]}, {"centre": 0.0},
                {"alpha_band_px": -1}, {"size": 20}, {"runtime": "tensorrt"}, {"threads": 0},
                {"grabcut_iterations": -1}, {"background_below": 1.0}, {"band_px": 0}, {"max_side": 8},
                {"min_kept": 1.5}):
        with pytest.raises(MatlError, match="foreground learned"):
            tiny_learned(**bad)
    with pytest.raises(MatlError, match="not found"):
        LearnedForeground(weights=str(tmp_path / "missing.ckpt"))
    node = OmegaConf.load(REPO / "conf" / "foreground" / "learned.yaml")
    step = foreground_option(node)
    assert isinstance(step, LearnedForeground) and step.threshold == node.threshold
    assert isinstance(foreground_option("learned"), LearnedForeground)
    assert "learned" in FOREGROUNDS
    with pytest.raises(MatlError, match="foreground: "):
        foreground_option(OmegaConf.create({"_target_": "matl.inference.foreground.LearnedForeground", "inset": 1}))


def test_recognizer_with_the_learned_foreground(tmp_path: Path) -> None:
    gallery, queries, _ = make_files(tmp_path)
    scene, _ = cluttered_query(queries, "green_can")
    rec = stub_recognizer(threshold=None, foreground="learned").enrol(gallery)
    assert isinstance(rec.foreground, LearnedForeground)
    pytest.importorskip("onnxruntime")
    assert not rec.foreground._sessions and rec.prepare().foreground._sessions  # ready before the first crop
    match = rec.predict(scene)
    assert match.object in rec.objects and match.H.shape == (3, 3)
    options = rec.options()["foreground"]
    assert options["threshold"] == 0.5 and options["retry_thresholds"] == (0.3, 0.7)


def test_a_large_crop_is_segmented_on_a_smaller_copy() -> None:
    rng = np.random.default_rng(0)
    crop = np.empty((600, 480, 3), np.float32)
    crop[:] = rng.uniform(0.0, 0.1, 3)  # a dark floor with a little texture
    crop += rng.normal(0.0, 0.01, crop.shape).astype(np.float32)
    crop[150:450, 120:360] = (0.9, 0.5, 0.2)  # the product
    crop[200:260, 150:330] = (0.2, 0.3, 0.9)
    crop = np.clip(crop, 0, 1)
    small, full = GrabCutForeground(max_side=200)(crop), GrabCutForeground(max_side=None)(crop)
    assert small.shape == full.shape == crop.shape[:2] and set(np.unique(small)) <= {0.0, 1.0}
    truth = np.zeros(crop.shape[:2], bool)
    truth[150:450, 120:360] = True
    for mask in (small, full):
        assert (mask.astype(bool) & truth).sum() / (mask.astype(bool) | truth).sum() > 0.95
    # a crop no larger than max_side is segmented as it is
    little = cv2.resize(crop, (120, 150), interpolation=cv2.INTER_AREA)
    np.testing.assert_array_equal(GrabCutForeground(max_side=200)(little), GrabCutForeground(max_side=None)(little))
    with pytest.raises(MatlError, match="max_side"):
        GrabCutForeground(max_side=4)


def test_masks_made_in_threads_are_the_ones_made_one_after_another(monkeypatch: pytest.MonkeyPatch) -> None:
    """A batch's crops are masked over torch's threads, and a crop's GrabCut retries too (matl.utils.threads):
    GrabCut's seeded k-means draws from each thread's own generator, so every mask is the serial one."""
    import matl.inference.foreground as foreground_module

    crops = [clutter_scene(seed)[0] for seed in range(4)]
    steps = (GrabCutForeground(retry_insets=(0.05, 0.08, 0.12)),
             FixedProbability(np.where(clutter_scene()[1] > 0, 0.8, 0.1).astype(np.float32), grabcut_iterations=1,
                              retry_insets=(0.0, 0.08, 0.12)))
    previous = torch.get_num_threads()
    try:
        torch.set_num_threads(2)
        threaded = [[mask_query(step, crop)[2] for crop in crops] + [m for crop in crops for m in step.retries(crop)]
                    for step in steps]
        monkeypatch.setattr(foreground_module, "thread_map", lambda fn, items, workers=None: [fn(x) for x in items])
        serial = [[mask_query(step, crop)[2] for crop in crops] + [m for crop in crops for m in step.retries(crop)]
                  for step in steps]
    finally:
        torch.set_num_threads(previous)
    assert all(len(a) == len(b) > len(crops) for a, b in zip(threaded, serial, strict=True))
    assert all(np.array_equal(x, y) for a, b in zip(threaded, serial, strict=True) for x, y in zip(a, b, strict=True))
