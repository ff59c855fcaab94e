"""matl.unseen's benchmark conditions, held-out image sources, keypoint baselines on files and its table.

Each condition's writer runs on a tiny in-memory set (or, for rendered views and other sizes, on two
products of the held-out catalog at 32 px), and its files are checked for the property that makes the
condition what it is; the ground truth is checked against the pixels.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from omegaconf import open_dict
from PIL import Image

from matl.data.canonical import load_canonical
from matl.data.catalog import SyntheticCatalog
from matl.data.catalog.drawing import HELDOUT_BACKGROUND_FILES, HELDOUT_PHOTO_FILES, PHOTO_FILES
from matl.evaluation.conditions import CONDITIONS, sample_poses, warp_planes
from matl.evaluation.unseen import (
    WRITERS,
    Queries,
    _check,
    benchmark_table,
    foreground_choice,
    method_overrides,
    predict_args,
    write_gallery,
)
from matl.geometry import HomographySampler
from matl.training.fit import check_training_photos
from matl.utils.errors import MatlError
from tests.conftest import compose_config
from tests.evaluation.test_unseen import tiny_set


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


def textured_set(size: int = 80, objects: int = 2):
    """``objects`` one-plane objects: rectangles of blurred random texture (keypoints to match), in memory."""
    from matl.data.canonical import CanonicalSet

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


# ----------------------------------------------------------------------------- held-out sources
def test_heldout_catalog_prints_only_heldout_photos() -> None:
    default, heldout = SyntheticCatalog("apc", 1), SyntheticCatalog("apc", 1, photos="skimage")
    assert default.cache_key() == SyntheticCatalog("apc", 1, photos="matplotlib").cache_key()
    assert "photos" not in default.cache_key() and heldout.cache_key()["photos"].startswith("skimage-")
    assert heldout.cache_key() != default.cache_key()
    arts = {p.art for p in heldout.products()}
    assert arts <= {f"photo_{k}" for k in HELDOUT_PHOTO_FILES} and len(arts) == len(HELDOUT_PHOTO_FILES)
    assert not {p.art for p in default.products()} & arts  # the training catalogs never print them
    assert [p.name for p in heldout.products()] == [p.name for p in default.products()]
    assert not set(HELDOUT_PHOTO_FILES) & set(HELDOUT_BACKGROUND_FILES) and not set(HELDOUT_PHOTO_FILES) & set(
        PHOTO_FILES)
    with pytest.raises(ValueError, match="photos"):
        SyntheticCatalog("apc", 1, photos="flickr")


def test_training_refuses_the_heldout_photos(tmp_path: Path) -> None:
    check_training_photos(compose_config("train", [], tmp_path))
    with pytest.raises(MatlError, match="held-out"):
        check_training_photos(compose_config("train", ["data=heldout"], tmp_path))


# ------------------------------------------------------------------------------ options and table
@pytest.mark.parametrize("override,match", [
    ("condition=foggy", "condition=foggy is invalid: use one or a list of clean, photometric, mask, clutter, "
                        "occluded, view, sizes or all"),
    ("methods=[matl,orb]", r"methods=\['matl', 'orb'\] is invalid: use a list of matl, matl_refine, sift, sift_ecc, "
                           "lightglue, xfeat, xfeat_lighterglue$"),
    ("methods=[]", "methods=.* is invalid"),
    ("sizes.query=8", "sizes.query=8 is invalid"),
    ("photometric.gain=[2.0,1.0]", r"photometric.gain=\[2.0, 1.0\] is invalid: use \[low, high\]"),
    ("occluded.hidden=[0.5,0.1]", r"occluded.hidden=\[0.5, 0.1\] is invalid: use \[low, high\]"),
    ("occluded.hidden=[0.1,1.0]", r"occluded: occluder hidden=\[0.1, 1.0\] is invalid: use \[low, high\] with 0 <= "),
    ("+occluded.kinds.hand=1", "occluded: occluder kind 'hand' is unknown: use product, gripper, suction or edge"),
    ("occluded.kinds.edge=-1", "occluded: occluder kind weight edge=-1 is invalid: use a number >= 0"),
    ("occluded.floors.dark=0", None),
    ("+occluded.floors.carpet=1", r"occluded.floors=\{.*\} is invalid: use weights >= 0 of dark and texture"),
    ("occluded.rgba_share=1.5", r"occluded.rgba_share=1.5 is invalid: use a fraction in \[0, 1\]"),
    ("occluded.bins=[0.35,0.2]", r"occluded.bins=\[0.35, 0.2\] is invalid: use increasing upper edges in \(0, 1\)"),
    ("occluded.dark_floor.level=[0.1,0.0]", r"occluded.dark_floor.level=\[0.1, 0.0\] is invalid"),
])
def test_bad_options_are_one_line_errors(tmp_path: Path, override: str, match: str | None) -> None:
    if match is None:  # a valid setting
        _check(_cfg(tmp_path, override))
        return
    with pytest.raises(MatlError, match=match) as error:
        _check(_cfg(tmp_path, override))
    assert "\n" not in str(error.value)


def test_condition_lists_and_method_commands(tmp_path: Path) -> None:
    assert _check(_cfg(tmp_path, "condition=all"))[0] == list(CONDITIONS)
    assert _check(_cfg(tmp_path, "condition=[view,clean]", "methods=[sift]")) == (["view", "clean"], ["sift"])
    common = ["ckpt=c", "threshold=null"]
    refined = predict_args("matl_refine", common)
    assert refined == [*common, "refine=true", "foreground=grabcut", "runtime=onnxruntime"]
    plain = predict_args("matl", common, "none", "torch")
    assert plain == [*common, "refine=false", "foreground=none", "runtime=torch"]
    assert predict_args("sift_ecc", common) == ["ckpt=c", "baseline=sift_ecc", "threshold=null"]
    assert predict_args("xfeat_lighterglue", common) == ["ckpt=c", "baseline=xfeat_lighterglue", "threshold=null"]
    assert _check(_cfg(tmp_path, "methods=[matl,lightglue,xfeat,xfeat_lighterglue]"))[1] == [
        "matl", "lightglue", "xfeat", "xfeat_lighterglue"]
    assert method_overrides("sift") == []  # called as a function: no command-line overrides
    assert foreground_choice(_cfg(tmp_path)) == "grabcut"  # the default, passed on to predict
    assert foreground_choice(_cfg(tmp_path, "foreground=none")) == "none"


def test_the_refiner_choice_and_its_keys_reach_matl_refine_only(monkeypatch) -> None:
    import matl.evaluation.unseen as unseen

    given = ["ckpt=c", "refiner=fast", "refiner.levels=2", "baselines.sift.ratio=0.7", "queries=10",
             "foreground.passes=1"]
    monkeypatch.setattr(unseen, "_task_overrides", lambda: given)
    assert method_overrides("matl_refine") == ["refiner=fast", "refiner.levels=2", "foreground.passes=1"]
    assert method_overrides("matl") == ["foreground.passes=1"]
    assert method_overrides("sift") == ["baseline.ratio=0.7"]


def test_benchmark_table_has_a_row_per_condition_and_a_column_per_method() -> None:
    methods = ["matl", "sift"]
    results = {c: {"num_queries": 10, "num_objects": 3, "num_planes": 6, "image_size": 100, "checkpoint": "c.ckpt",
                   "data": {}, "query_seed": 1, "timing": None,
                   "methods": {m: {"rec_acc": 0.5 + 0.1 * j, "corner_err_px_median": 2.0, "pose_acc_5px": 0.25,
                                   "query_ms": 3.0 if m == "matl" else None} for j, m in enumerate(methods)}}
               for c in ("clean", "mask")}
    data, text = benchmark_table(results, methods, "python -m matl.unseen ckpt=c.ckpt condition=all")
    assert data["conditions"] == ["clean", "mask"] and data["methods"] == methods
    assert data["table"]["mask"]["sift"]["rec_acc"] == pytest.approx(0.6)
    lines = [line for line in text.splitlines() if line.startswith("|")]
    assert lines[0] == "| condition | queries | matl | sift |" and len(lines) == 4
    assert lines[2] == "| clean | 10 | 0.500 / 2.0 / 0.250 / 3.0 | 0.600 / 2.0 / 0.250 / - |"
    assert "python -m matl.unseen ckpt=c.ckpt condition=all" in text
    json.dumps(data)


def test_keypoint_baseline_on_files_frames_like_predict(tmp_path: Path) -> None:
    """predict's baseline path: the enrolled files framed by enrol_gallery, the pose back in file pixels."""
    from matl.baselines.sift import SiftRansacMatcher
    from matl.inference.baseline_files import KeypointFileRecognizer
    from matl.inference.files import predict_files

    cs = textured_set()
    q = Queries(cs, *sample_poses(cs, HomographySampler(rotation_deg=(-20.0, 20.0)), 4, 3), 3, None,
                list(range(cs.num_objects)), _cfg(tmp_path))
    truth = _write(q, "clean", tmp_path)
    rec = KeypointFileRecognizer(SiftRansacMatcher(), "sift", 64, 2).enrol(tmp_path / "gallery")
    assert len(rec.gallery) == cs.num_planes * 2 and rec.threshold is None
    records: list[dict] = []
    files = [tmp_path / t["image"] for t in truth]
    done, bad = predict_files(rec, files, records.append, show_progress=False)
    assert done == 4 and bad == [] and [r["image"] for r in records] == [str(f) for f in files]
    right = 0
    for record, t in zip(records, truth, strict=True):
        assert record["distance"] is None and (record["object"] is None) == (record["H"] is None)
        if record["object"] == t["object"] and record["plane"] == t["plane"]:
            # the corners of the textured rectangle, in gallery file pixels (80 px)
            corners = np.array([[16, 20, 1], [63, 20, 1], [63, 55, 1], [16, 55, 1.0]]).T
            a, b = np.array(record["H"]) @ corners, np.array(t["H"]) @ corners
            assert np.abs(a[:2] / a[2] - b[:2] / b[2]).max() < 2.5
            right += 1
    assert right >= 3


def test_cfg_helper_keeps_the_defaults(tmp_path: Path) -> None:
    cfg = _cfg(tmp_path)
    assert cfg.condition == "clean" and list(cfg.methods) == ["matl", "matl_refine", "sift", "sift_ecc"]
    assert cfg.data.source.photos == "skimage" and cfg.baselines.sift_ecc._target_.endswith("SiftEccMatcher")
    with open_dict(cfg):
        cfg.timing.queries = 0
    assert _check(cfg)[1] == ["matl", "matl_refine", "sift", "sift_ecc"]
    assert torch.is_tensor(sample_poses(tiny_set(), HomographySampler(), 3, 0)[1])
