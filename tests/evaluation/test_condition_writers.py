"""The condition writers of matl.unseen's benchmark: each condition's files and their ground truth.

Each writer runs on a tiny in-memory set (or, for rendered views and other sizes, on two products of the
held-out catalog at 32 px), and its files are checked for the property that makes the condition what it
is; the ground truth is checked against the pixels (the gallery file warped by the true H *is* the query file).
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from PIL import Image

from matl.data.canonical import CanonicalSet, load_canonical
from matl.data.catalog import SyntheticCatalog
from matl.evaluation.condition_writers import WRITERS, Queries, write_gallery, write_queries
from matl.evaluation.conditions import sample_poses, warp_planes
from matl.evaluation.score import read_truth
from matl.geometry import HomographySampler
from matl.utils.errors import MatlError
from tests.conftest import compose_config


def tiny_set(size: int = 40, objects: int = 3) -> CanonicalSet:
    """``objects`` two-plane objects: smooth coloured rectangles of different shapes on black, in memory."""
    rng = np.random.default_rng(0)
    images, masks, plane_object, names = [], [], [], []
    y, x = np.mgrid[0:size, 0:size]
    for o in range(objects):
        for p, plane in enumerate(("front", "back")):
            h, w = int(size * (0.3 + 0.1 * p)), int(size * (0.6 - 0.05 * o))
            top, left = (size - h) // 2, (size - w) // 2
            mask = (y >= top) & (y < top + h) & (x >= left) & (x < left + w)
            colour = rng.uniform(0.2, 1.0, 3)
            shade = 0.6 + 0.4 * np.sin(x / (3.0 + o) + p)[..., None]
            images.append((mask[..., None] * colour * shade * 255).round().astype(np.uint8))
            masks.append(mask)
            plane_object.append(o)
            names.append(plane)
    return CanonicalSet(np.stack(images), np.stack(masks), np.array(plane_object, dtype=np.int64), names,
                        [f"obj_{o}" for o in range(objects)], ["planar"] * objects)


def write_case(root: Path, crop: bool = False, n: int = 12) -> tuple[Path, list[dict]]:
    cs = tiny_set()
    gallery, offsets = write_gallery(cs, root / "gallery", crop)
    truth = write_queries(cs, HomographySampler(), n, 7, root / "queries", gallery, offsets, root)
    (root / "truth.jsonl").write_text("".join(json.dumps(t) + "\n" for t in truth))
    return root / "truth.jsonl", truth


def _cfg(tmp_path: Path, *overrides: str):
    return compose_config("unseen", ["ckpt=unused.ckpt", *overrides], tmp_path / "run")


def _queries(tmp_path: Path, n: int = 10, cs=None, source=None, *overrides: str) -> Queries:
    cs = cs if cs is not None else tiny_set()
    cfg = _cfg(tmp_path, *overrides)
    plane, H = sample_poses(cs, HomographySampler(), n, 7)
    return Queries(cs, plane, H, 7, source, list(range(cs.num_objects)), cfg)


def _write(q: Queries, condition: str, out: Path) -> list[dict]:
    gallery_cs = q.at_size(int(q.cfg.sizes.gallery)) if condition == "sizes" else q.cs
    files, canon_H_file = write_gallery(gallery_cs, out / "gallery")
    return WRITERS[condition](q, out / "queries", files, canon_H_file, out)


def _rgba(path: Path) -> np.ndarray:
    with Image.open(path) as im:
        return np.asarray(im)


def textured_set(size: int = 80, objects: int = 2) -> CanonicalSet:
    """``objects`` one-plane objects: rectangles of blurred random texture (keypoints to match), in memory."""
    rng = np.random.default_rng(1)
    images, masks = [], []
    for o in range(objects):
        texture = cv2.GaussianBlur(rng.uniform(0.1, 1.0, (size, size, 3)), (0, 0), 1.5)
        mask = np.zeros((size, size), bool)
        mask[size // 4:size - size // 4 - 4 * o, size // 5:size - size // 5] = True
        images.append((texture * mask[..., None] * 255).round().astype(np.uint8))
        masks.append(mask)
    return CanonicalSet(np.stack(images), np.stack(masks), np.arange(objects, dtype=np.int64), ["front"] * objects,
                        [f"obj_{o}" for o in range(objects)], ["planar"] * objects)


class FirstProducts(SyntheticCatalog):
    """The first ``count`` products of a catalog only (a tiny mesh source for rendered views)."""

    def __init__(self, count: int = 2, **kwargs) -> None:
        super().__init__(**kwargs)
        self.count = count

    def products(self):
        return super().products()[: self.count]

    @property
    def num_planes(self) -> int:
        return sum({"planar": 2, "rectangular": 6, "cylindrical": 10}[p.shape] for p in self.products())

    def cache_key(self) -> dict:
        return {**super().cache_key(), "first": self.count}


@pytest.fixture(scope="module")
def heldout_two(cache_dir: Path):
    """Two planar products of the held-out catalog (4 planes) at 32 px."""
    source = FirstProducts(2, catalog="apc", seed=1, photos="skimage")
    return source, load_canonical(source, 32, cache_dir)


@pytest.mark.parametrize("crop", [False, True])
def test_truth_is_what_the_files_show(tmp_path: Path, crop: bool) -> None:
    """cv2.warpPerspective(gallery file, H) reproduces the query file: H is in the files' pixels."""
    truth_path, truth = write_case(tmp_path, crop)
    for record in truth:
        query = cv2.imread(str(tmp_path / record["image"])).astype(np.float64)
        gallery = cv2.imread(str(tmp_path / record["gallery_image"]))
        warped = cv2.warpPerspective(gallery, np.array(record["H"]), (query.shape[1], query.shape[0]))
        assert np.abs(warped.astype(np.float64) - query).mean() < 1.0
    if crop:  # tight crops: smaller than the frame
        assert any(cv2.imread(str(tmp_path / r["gallery_image"])).shape[0] < 40 for r in truth)
    assert [t.object for t in read_truth(truth_path)] == [r["object"] for r in truth]


# ------------------------------------------------------------------------------------ conditions
def test_clean_and_photometric_share_poses_and_differ_in_pixels(tmp_path: Path) -> None:
    q = _queries(tmp_path)
    clean, photo = _write(q, "clean", tmp_path / "c"), _write(q, "photometric", tmp_path / "p")
    assert len(clean) == len(photo) == 10
    diffs = []
    for c, p in zip(clean, photo, strict=True):
        assert c["H"] == p["H"] and c["plane"] == p["plane"] and p["image"].endswith(".jpg")
        a = _rgba(tmp_path / "c" / c["image"]).astype(float)
        b = _rgba(tmp_path / "p" / p["image"]).astype(float)
        assert a.shape == b.shape == (40, 40, 3)
        diffs.append(np.abs(a - b).mean())
        assert np.corrcoef(a.ravel(), b.ravel())[0, 1] > 0.5  # the same product where it was
        assert set(p["photometric"]) >= {"gain", "bias", "gamma", "tint", "blur_sigma", "noise_sigma", "jpeg_quality"}
    assert min(diffs) > 1.0
    again = _write(q, "photometric", tmp_path / "p2")  # seeded
    assert all(np.array_equal(_rgba(tmp_path / "p" / a["image"]), _rgba(tmp_path / "p2" / b["image"]))
               for a, b in zip(photo, again, strict=True))


def test_mask_files_are_rgba_with_an_imperfect_alpha(tmp_path: Path) -> None:
    q = _queries(tmp_path, cs=tiny_set(size=100))  # offsets of a few px at the model's 100 px
    truth = _write(q, "mask", tmp_path)
    _, true_masks = warp_planes(q.cs, q.plane, q.query_H_canon)
    for record, true in zip(truth, true_masks > 0.5, strict=True):
        rgba = _rgba(tmp_path / record["image"])
        assert rgba.shape == (100, 100, 4)
        alpha = rgba[..., 3] > 127
        assert set(np.unique(rgba[..., 3])) <= {0, 255}
        assert (alpha != true).any()  # not the true mask
        assert (alpha & true).sum() / (alpha | true).sum() > 0.5  # but mostly overlapping it
        assert rgba[..., :3][~true].mean() > 5  # a real background under the alpha
        assert record["mask_file"] == f"masks/{Path(record['image']).stem}.png"
        assert np.array_equal(_rgba(tmp_path / record["mask_file"]), np.where(true, 255, 0).astype(np.uint8))


def test_clutter_files_are_rgb_with_background_and_a_neighbour(tmp_path: Path) -> None:
    q = _queries(tmp_path)
    truth = _write(q, "clutter", tmp_path)
    _, true_masks = warp_planes(q.cs, q.plane, q.query_H_canon)
    for record, true in zip(truth, true_masks > 0.5, strict=True):
        rgb = _rgba(tmp_path / record["image"])
        assert rgb.shape == (40, 40, 3)
        assert (rgb[~true].max(axis=-1) > 0).mean() > 0.9  # no black background left
        assert record["neighbour"]["object"] != record["object"]
        assert np.array_equal(_rgba(tmp_path / record["mask_file"]), np.where(true, 255, 0).astype(np.uint8))


def test_occluded_files_hide_the_recorded_share_of_the_product(tmp_path: Path) -> None:
    q = _queries(tmp_path, 16, tiny_set(size=64), None, "occluded.rgba_share=0.5")
    truth = _write(q, "occluded", tmp_path / "o")
    clean = _write(q, "clean", tmp_path / "c")
    images, true_masks = warp_planes(q.cs, q.plane, q.query_H_canon)
    kinds, rgba_seen = set(), set()
    for record, c, image, true in zip(truth, clean, images, true_masks > 0.5, strict=True):
        assert record["H"] == c["H"] and record["plane"] == c["plane"]  # the clean poses
        assert 0.05 <= record["hidden_fraction"] <= 0.55 and record["floor"] in ("dark", "texture")
        assert record["occlusion"]["target_fraction"] == pytest.approx(record["hidden_fraction"], abs=0.05)
        kinds.add(record["occluder"])
        rgba_seen.add(record["rgba"])
        if record["occluder"] == "product":  # another held-out product lies on it
            assert record["occlusion"]["product"]["object"] != record["object"]
        visible = _rgba(tmp_path / "o" / record["mask_file"])
        assert record["mask_file"] == f"masks/{Path(record['image']).stem}.png" and visible.dtype == np.uint8
        assert set(np.unique(visible)) <= {0, 255} and visible.shape == (64, 64)
        visible = visible > 0
        assert not (visible & ~true).any()  # within the product
        assert 1.0 - visible.sum() / true.sum() == pytest.approx(record["hidden_fraction"], abs=0.1)
        pixels = _rgba(tmp_path / "o" / record["image"])
        assert pixels.shape == ((64, 64, 4) if record["rgba"] else (64, 64, 3))
        if record["rgba"]:  # alpha: the visible part only
            assert np.array_equal(pixels[..., 3] > 127, visible)
        hidden = true & ~visible
        assert np.abs(pixels[..., :3].astype(float) - image * 255)[hidden].mean() > 5  # something else shows there
    assert len(kinds) >= 3 and rgba_seen == {True, False}
    again = _write(q, "occluded", tmp_path / "o2")  # seeded per query
    assert again == truth
    assert all((tmp_path / "o" / r["image"]).read_bytes() == (tmp_path / "o2" / r["image"]).read_bytes()
               for r in truth)


def test_occluded_needs_other_products_for_product_occluders(tmp_path: Path) -> None:
    q = _queries(tmp_path, 2, tiny_set(objects=1))
    with pytest.raises(MatlError, match=r"needs at least two products, or occluded\.kinds\.product=0"):
        _write(q, "occluded", tmp_path / "o")
    q = _queries(tmp_path, 2, tiny_set(objects=1), None, "occluded.kinds.product=0")
    assert {r["occluder"] for r in _write(q, "occluded", tmp_path / "o2")} <= {"gripper", "suction", "edge"}


@pytest.mark.slow
def test_view_truth_is_the_plane_induced_homography(tmp_path: Path, heldout_two, cache_dir: Path) -> None:
    source, cs = heldout_two
    q = _queries(tmp_path, 6, cs, source, f"paths.cache_dir={cache_dir}")
    truth = _write(q, "view", tmp_path)
    for i, record in enumerate(truth):
        view = _rgba(tmp_path / record["image"]).astype(np.float64) / 255.0
        gallery = cv2.imread(str(tmp_path / record["gallery_image"]))[..., ::-1].astype(np.float64) / 255.0
        H = np.array(record["H"])
        warped = cv2.warpPerspective(gallery, H, (32, 32))
        plane_mask = cv2.warpPerspective(cs.masks[int(q.plane[i])].astype(np.float64), H, (32, 32)) > 0.99
        plane_mask = cv2.erode(plane_mask.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0  # away from the edge
        assert plane_mask.sum() > 10
        assert (view[plane_mask].max(-1) > 0).mean() > 0.95  # the canonical plane lands on the rendered product
        shifted = cv2.warpPerspective(gallery, np.array([[1, 0, 3], [0, 1, 0], [0, 0, 1.0]]) @ H, (32, 32))
        err, err_shifted = (np.abs(x - view)[plane_mask].mean() for x in (warped, shifted))
        assert err < 0.15 and err < err_shifted


@pytest.mark.slow
def test_sizes_files_have_the_requested_sizes_and_truth(tmp_path: Path, heldout_two, cache_dir: Path) -> None:
    source, cs = heldout_two
    q = _queries(tmp_path, 6, cs, source, f"paths.cache_dir={cache_dir}", "sizes.gallery=48", "sizes.query=40")
    truth = _write(q, "sizes", tmp_path)
    for record in truth:
        query = _rgba(tmp_path / record["image"]).astype(np.float64)
        gallery = _rgba(tmp_path / record["gallery_image"])
        assert query.shape == (40, 40, 3) and gallery.shape == (48, 48, 3)
        warped = cv2.warpPerspective(gallery, np.array(record["H"]), (40, 40)).astype(np.float64)
        assert np.abs(warped - query).mean() < 8.0
