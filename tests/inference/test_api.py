"""The Python API (``from matl import Recognizer``): enrol, add, remove, predict, open set, save / load."""

from __future__ import annotations

import json
import math
import threading
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from torch import nn

import matl
from matl import Match, Recognizer
from matl.data.image_files import fit_geometry
from matl.geometry import corner_error_px
from matl.inference.api import calibrate_open_set
from matl.inference.files import predict
from matl.utils.errors import MatlError
from tests.predict_helpers import (
    COLOURS,
    GALLERY_HW,
    QUERY_HW,
    FixedSTN,
    MeanColour,
    make_files,
    predict_cfg,
    smooth_texture,
    tiny_run,  # noqa: F401 - the module fixture
)

SIZE = 48


class StubModel(nn.Module):
    """An embedding model whose ``c()`` is the mean colour and whose ``s()`` returns a fixed pose."""

    def __init__(self, query_H_anchor: torch.Tensor) -> None:
        super().__init__()
        self.feature_net, self.stn, self.anchor_choice = MeanColour(), FixedSTN(query_H_anchor), "feature"


def exact_model_pose() -> torch.Tensor:
    """The model-frame pose of make_files' queries (N = 1: the anchor is the canonical image)."""
    from tests.predict_helpers import true_query_H_gallery

    gallery_fit = fit_geometry(*GALLERY_HW, SIZE).model_H_file
    query_fit = fit_geometry(*QUERY_HW, SIZE).model_H_file
    return query_fit @ torch.from_numpy(true_query_H_gallery()) @ torch.linalg.inv(gallery_fit)


def stub_recognizer(**options) -> Recognizer:
    return Recognizer(StubModel(exact_model_pose()), SIZE, 1, "stub-model", **options)


def read_rgb(path: Path) -> np.ndarray:
    return cv2.imread(str(path), cv2.IMREAD_COLOR)[..., ::-1].copy()


def test_enrol_add_predict_and_pose_in_the_callers_pixels(tmp_path: Path) -> None:
    gallery, queries, H_true = make_files(tmp_path)
    rec = stub_recognizer(threshold=None).enrol(gallery)
    assert rec.objects == sorted(COLOURS)
    # a product added at run time from an array, without retraining
    rec.add("yellow_tin", "front", (smooth_texture(*GALLERY_HW, (1.0, 0.9, 0.1), 5) * 255).astype(np.uint8))
    assert "yellow_tin" in rec.objects and len(rec.planes) == 4

    query = read_rgb(queries / "green_can.png")  # HxWx3 uint8 RGB, another size than the gallery file
    match = rec.predict(query)
    assert isinstance(match, Match) and match.object == "green_can" and match.known
    assert match.gallery_image == str(gallery / "green_can" / "front.png")
    # H maps the gallery file onto the query image: corner error in query pixels, scaled to 100 px
    err = corner_error_px(torch.from_numpy(match.H)[None], torch.from_numpy(H_true)[None], GALLERY_HW)
    assert float(err) * 100 / max(GALLERY_HW) < 2.0
    warped = cv2.warpPerspective(read_rgb(gallery / "green_can" / "front.png").astype(np.float32), match.H,
                                 (QUERY_HW[1], QUERY_HW[0]))
    assert np.abs(warped - query.astype(np.float32)).max() <= 1.0

    # a batch: paths, arrays, an RGBA array whose alpha is the mask, a (B, 3, H, W) tensor
    rgba = np.dstack([query, np.full(query.shape[:2], 255, np.uint8)])
    batch = rec.predict([queries / "red_box.png", read_rgb(queries / "blue_card.png"), rgba])
    assert [m.object for m in batch] == ["red_box", "blue_card", "green_can"]
    tensor = torch.from_numpy(np.stack([query, query])).permute(0, 3, 1, 2).float() / 255.0
    assert [m.object for m in rec.predict(tensor)] == ["green_can", "green_can"]
    # top-k: the other products, nearest first
    top = rec.predict(query, top_k=3)
    assert len(top.alternatives) == 2 and all(a.object not in (None, "green_can") for a in top.alternatives)
    assert top.alternatives[0].distance <= top.alternatives[1].distance

    rec.remove("green_can")
    assert rec.predict(query).object != "green_can"
    with pytest.raises(MatlError, match="no such product"):
        rec.remove("green_can")


def test_alpha_is_the_mask(tmp_path: Path) -> None:
    gallery, queries, _ = make_files(tmp_path)
    # exactly as given without the foreground step (foreground=grabcut decides its edge: test_foreground.py)
    rec = stub_recognizer(threshold=None, foreground="none").enrol(gallery)
    query = read_rgb(queries / "red_box.png")
    alpha = np.zeros(query.shape[:2], np.uint8)
    alpha[20:100, 10:80] = 255
    masked = query * (alpha[..., None] > 0)
    a = rec.predict(np.dstack([query, alpha]))
    b = rec.predict(masked)
    assert a.distance == pytest.approx(b.distance) and a.object == b.object


def test_open_set_threshold_and_score(tmp_path: Path) -> None:
    gallery, queries, _ = make_files(tmp_path)
    query = read_rgb(queries / "red_box.png")
    closed = stub_recognizer(threshold=None).enrol(gallery)
    assert closed.threshold is None and closed.predict(query).known
    # a product that is not enrolled: the query of red_box against a gallery without it
    strict = stub_recognizer(threshold=0.5, open_set_statistic="ratio").enrol(gallery).remove("red_box")
    answer = strict.predict(query)
    assert not answer.known and answer.object is None and answer.nearest_object in ("green_can", "blue_card")
    auto = stub_recognizer().enrol(gallery)
    samples = auto.calibration()
    assert len(samples["genuine"]) == 3 * auto.calibration_warps and len(samples["impostor"]) == len(samples["genuine"])
    assert auto.threshold == pytest.approx(calibrate_open_set(samples["genuine"], samples["impostor"],
                                                                    auto.open_set_quantile))
    match = auto.predict(query)
    assert match.known and 0.0 <= match.score <= 1.0
    with pytest.raises(MatlError, match="open_set_quantile"):
        calibrate_open_set(samples["genuine"], samples["impostor"], 0.0)


def product_art(colour: tuple[float, float, float], seed: int) -> np.ndarray:
    """``GALLERY_HW`` uint8 RGB art of full contrast in every channel (a product's print), mean about ``colour``."""
    h, w = GALLERY_HW
    channels = [smooth_texture(h, w, (1.0, 1.0, 1.0), seed * 3 + c)[..., 0] for c in range(3)]
    pattern = (np.stack(channels, -1) - 0.55) / 0.15  # about [-1, 1] per channel, each its own pattern
    return (np.clip(0.5 * np.asarray(colour) + 0.25 + 0.25 * pattern, 0, 1) * 255).round().astype(np.uint8)


def easy_files(root: Path) -> tuple[Path, Path, torch.Tensor]:
    """A gallery of four textured products (``GALLERY_HW`` PNGs) and, per product, a query of the same size
    turned by 10 degrees and shrunk to 0.8 about its centre; returns the folders and the queries'
    model-frame ``query_H_anchor``."""
    colours = {**COLOURS, "yellow_tin": (1.0, 0.9, 0.1)}
    c, s = 0.8 * math.cos(math.radians(10)), 0.8 * math.sin(math.radians(10))
    h, w = GALLERY_HW
    centre = np.array([[1, 0, -(w - 1) / 2], [0, 1, -(h - 1) / 2], [0, 0, 1]])
    H = np.linalg.inv(centre) @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]) @ centre
    gallery, queries = root / "easy_gallery", root / "easy_queries"
    for k, (name, colour) in enumerate(colours.items()):
        art = product_art(colour, k)
        (gallery / name).mkdir(parents=True)
        queries.mkdir(exist_ok=True)
        cv2.imwrite(str(gallery / name / "front.png"), art[..., ::-1])
        query = cv2.warpPerspective(art[..., ::-1], H, (w, h), flags=cv2.INTER_LINEAR)
        cv2.imwrite(str(queries / f"{name}.png"), query)
    fit = fit_geometry(h, w, SIZE).model_H_file
    return gallery, queries, fit @ torch.from_numpy(H) @ torch.linalg.inv(fit)


def test_verification_accepts_an_enrolled_product_and_rejects_an_unenrolled_one(tmp_path: Path) -> None:
    gallery, queries, pose = easy_files(tmp_path)
    rec = Recognizer(StubModel(pose), SIZE, 1, "stub-model").enrol(gallery)  # auto threshold, statistic verify
    enrolled = rec.predict(read_rgb(queries / "red_box.png"))
    # the stub's pose is exact: the query warped onto red_box's anchor correlates with it
    assert enrolled.known and enrolled.object == "red_box" and enrolled.verification < rec.verify_max
    assert enrolled.statistic == 0.0 and enrolled.score == 1.0
    rec.remove("green_can")
    unenrolled = rec.predict(read_rgb(queries / "green_can.png"), top_k=2)
    # no candidate verifies: the statistic is the ratio of the two nearest products' distances
    assert unenrolled.verification > rec.verify_max
    assert unenrolled.statistic == pytest.approx(unenrolled.distance / unenrolled.alternatives[0].distance)
    assert unenrolled.statistic > rec.threshold and not unenrolled.known and unenrolled.object is None
    # the same query with the plain ratio and verification off: the same statistic, no verification
    plain = Recognizer(StubModel(pose), SIZE, 1, "stub-model", open_set_statistic="ratio", verify_top_k=0)
    plain.enrol(gallery).remove("green_can")
    answer = plain.predict(read_rgb(queries / "green_can.png"))
    assert answer.statistic == pytest.approx(unenrolled.statistic) and math.isnan(answer.verification)
    # verify_or_ratio: the same statistic, calibrated on the ratio's own samples
    lenient = Recognizer(StubModel(pose), SIZE, 1, "stub-model", open_set_statistic="verify_or_ratio")
    lenient.enrol(gallery).remove("green_can")
    for key, value in lenient.calibration().items():
        assert torch.equal(value, plain.calibration()[key])
    again = lenient.predict(read_rgb(queries / "green_can.png"))
    assert again.statistic == pytest.approx(unenrolled.statistic) and again.verification > lenient.verify_max
    for bad in ({"verify_top_k": -1}, {"verify_max": 3.0}, {"verify_blur": -1.0}, {"open_set_statistic": "zncc"},
                {"verify_refine": "yes"}):
        with pytest.raises(MatlError, match=next(iter(bad))):
            stub_recognizer(**bad)


def test_calibration_by_hand() -> None:
    genuine = torch.tensor([0.1, 0.2, 0.3, 0.4, 0.5], dtype=torch.float64)
    assert calibrate_open_set(genuine, torch.zeros(0), 1.0) == pytest.approx(0.5)
    assert calibrate_open_set(genuine, torch.zeros(0), 0.5) == pytest.approx(0.3)
    assert calibrate_open_set(genuine[:0], torch.zeros(0), 0.5) == float("inf")


def test_save_load_and_refusal(tmp_path: Path) -> None:
    gallery, queries, _ = make_files(tmp_path)
    rec = stub_recognizer(threshold=None).enrol(gallery)
    rec.add("extra", "top", read_rgb(queries / "blue_card.png"))
    rec.save(tmp_path / "gallery.pt")
    again = stub_recognizer(threshold=None).load(tmp_path / "gallery.pt")
    assert again.planes == rec.planes
    query = read_rgb(queries / "red_box.png")
    a, b = rec.predict(query), again.predict(query)
    assert (a.object, a.distance) == (b.object, b.distance) and np.array_equal(a.H, b.H)
    other = Recognizer(StubModel(exact_model_pose()), SIZE, 1, "another-model")
    with pytest.raises(MatlError, match="another model"):
        other.load(tmp_path / "gallery.pt")
    (tmp_path / "junk.pt").write_text("junk")
    with pytest.raises(MatlError, match="not a matl gallery"):
        other.load(tmp_path / "junk.pt")


def test_bad_inputs_are_one_line_errors(tmp_path: Path) -> None:
    rec = stub_recognizer()
    with pytest.raises(MatlError, match="gallery is empty"):
        rec.predict(np.zeros((10, 10, 3), np.uint8))
    gallery, _, _ = make_files(tmp_path)
    rec.enrol(gallery)
    with pytest.raises(MatlError, match="expected an HxWx3"):
        rec.predict(np.zeros((10, 10, 5), np.uint8))
    with pytest.raises(MatlError, match="uint8"):
        rec.predict(np.zeros((10, 10, 3), np.int32))
    with pytest.raises(MatlError, match="no such file"):
        rec.predict(tmp_path / "missing.png")
    with pytest.raises(MatlError, match="top_k"):
        rec.predict(np.zeros((10, 10, 3), np.uint8), top_k=0)
    with pytest.raises(MatlError, match="threshold"):
        stub_recognizer(threshold="high")
    if not matl.inference.api.PRETRAINED.is_file():
        with pytest.raises(MatlError, match="no pretrained model"):
            Recognizer.pretrained()


def test_threads_take_turns(tmp_path: Path) -> None:
    gallery, queries, _ = make_files(tmp_path)
    rec = stub_recognizer(threshold=None).enrol(gallery)
    images = [read_rgb(p) for p in sorted(queries.iterdir())]
    expected = [m.object for m in rec.predict(images)]
    answers: list[list[str | None]] = []

    def worker() -> None:
        for _ in range(3):
            answers.append([m.object for m in rec.predict(images)])

    threads = [threading.Thread(target=worker) for _ in range(3)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(answers) == 9 and all(a == expected for a in answers)


def test_same_numbers_as_the_predict_command(tiny_run: Path, tmp_path: Path) -> None:
    ckpt = tiny_run / "checkpoints" / "best.ckpt"
    gallery, queries, _ = make_files(tmp_path)
    predict(predict_cfg(tmp_path, ckpt, gallery, queries, ["cache=false"]))
    records = [json.loads(line) for line in (tmp_path / "out" / "pred.jsonl").read_text().splitlines()]
    rec = Recognizer.from_checkpoint(ckpt).enrol(gallery, cache=False)
    matches = rec.predict([record["image"] for record in records])  # one batch, as predict's
    for record, match in zip(records, matches, strict=True):
        assert (match.object, match.known, match.anchor) == (record["object"], record["known"], record["anchor"])
        assert match.distance == record["distance"] and match.H.tolist() == record["H"]


# ------------------------------------------------------------------------------ saved galleries
def gallery_folder(root: Path, planes: int) -> Path:
    """``planes`` products of one plane each, distinct textured art (``GALLERY_HW`` PNGs)."""
    for k in range(planes):
        (root / f"p{k:02d}").mkdir(parents=True)
        art = product_art((0.2 + 0.04 * k, 0.5, 0.9 - 0.03 * k), k)
        cv2.imwrite(str(root / f"p{k:02d}" / "front.png"), art[..., ::-1])
    return root


def test_a_saved_gallery_grows_linearly_and_holds_images_and_features_only(tmp_path: Path) -> None:
    """Each plane stores its own canonical image and features (a view into an enrolled batch would store the whole
    batch: the file grew with the square of the gallery), plus the calibration's samples."""
    sizes, payloads = {}, {}
    for n in (1, 20):
        rec = stub_recognizer().enrol(gallery_folder(tmp_path / f"g{n}", n), cache=False)
        rec.save(tmp_path / f"g{n}.pt")
        sizes[n] = (tmp_path / f"g{n}.pt").stat().st_size
        payloads[n] = torch.load(tmp_path / f"g{n}.pt", weights_only=True)
        assert payloads[n]["calibration"] is not None  # threshold=auto: kept with the gallery
    assert sizes[20] <= 20 * sizes[1] * 1.1
    for n, payload in payloads.items():
        tensors = [t for plane in payload["planes"] for t in plane.values() if isinstance(t, torch.Tensor)]
        tensors += [t for t in payload["calibration"].values() if isinstance(t, torch.Tensor)]
        content = sum(t.numel() * t.element_size() for t in tensors)
        image_bytes = n * 3 * SIZE * SIZE
        assert content <= image_bytes * 1.1  # the canonical images dominate: features, matrices, samples are small
        assert sizes[n] <= content + 1024 * len(tensors) + 8192, (n, sizes[n], content)  # torch.save's framing


def test_the_calibration_is_kept_by_save_and_beside_an_enrolled_folder(tmp_path: Path,
                                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    gallery, queries, _ = make_files(tmp_path)
    rec = stub_recognizer().enrol(gallery)  # cache=True: features and calibration kept in the folder
    threshold = rec.threshold
    cache = rec.calibration_cache_file()
    assert cache is not None and cache.parent == gallery and cache.is_file()
    rec.save(tmp_path / "saved.pt")
    computed: list[str] = []
    calibrate = Recognizer.calibration

    def counted(self: Recognizer) -> dict[str, torch.Tensor]:
        computed.append(self.calibration_key())
        return calibrate(self)

    monkeypatch.setattr(Recognizer, "calibration", counted)
    assert stub_recognizer().load(tmp_path / "saved.pt").threshold == threshold
    again = stub_recognizer().enrol(gallery)
    assert again.threshold == threshold and again.calibration_cache_file() == cache
    samples = rec.calibration()  # (counted)
    assert stub_recognizer(open_set_quantile=0.5).load(tmp_path / "saved.pt").threshold == pytest.approx(
        calibrate_open_set(samples["genuine"], samples["impostor"], 0.5))  # the quantile is not in the key
    assert len(computed) == 1
    query = read_rgb(queries / "red_box.png")
    a, b = stub_recognizer().load(tmp_path / "saved.pt").predict(query), rec.predict(query)
    assert (a.object, a.known, a.score, a.statistic) == (b.object, b.known, b.score, b.statistic)
    # other calibration options, another gallery, an edited file: calibrated again
    assert stub_recognizer(verify_max=0.2).load(tmp_path / "saved.pt").threshold is not None and len(computed) == 2
    grown = stub_recognizer().load(tmp_path / "saved.pt").add("extra", "top", read_rgb(queries / "blue_card.png"))
    assert grown.calibration_cache_file() is None and grown.threshold is not None and len(computed) == 3
    cv2.imwrite(str(gallery / "red_box" / "front.png"), read_rgb(queries / "red_box.png")[..., ::-1])
    edited = stub_recognizer().enrol(gallery)
    assert edited.threshold is not None and len(computed) == 4 and computed[-1] != computed[0]


def test_grey_queries_are_matched_against_the_grey_twins_of_the_planes(tmp_path: Path) -> None:
    gallery, queries, _ = make_files(tmp_path)
    rec = stub_recognizer(threshold=None).enrol(gallery)
    colour = read_rgb(queries / "red_box.png")
    grey = cv2.cvtColor(colour, cv2.COLOR_RGB2GRAY)
    answer = rec.predict(grey)  # an HxW uint8 array
    twin = rec._grey_twin()
    assert twin is not rec and twin.planes == rec.planes
    assert all(bool((p.canon_u8[0] == p.canon_u8[1]).all()) for p in twin._planes)
    # the stub's c() is the mean colour: a grey query is as far from a colour gallery as its colours are, and at
    # its own luma from the grey twins
    as_colour = rec._predict_arrays([np.repeat(grey[..., None], 3, -1).astype(np.float32) / 255.0])[0][0]
    assert answer.distance < 0.05 < as_colour.distance
    tensor = torch.from_numpy(grey.astype(np.float32) / 255.0)[None]  # (1, H, W) float
    assert rec.predict(tensor).distance == pytest.approx(answer.distance)
    # a mixed batch: each answered as alone, in the given order
    batch = rec.predict([colour, grey, queries / "blue_card.png"])
    assert [m.distance for m in batch] == pytest.approx([rec.predict(colour).distance, answer.distance,
                                                         rec.predict(queries / "blue_card.png").distance])
    assert batch[0].object == "red_box" and batch[2].object == "blue_card"


def test_the_query_mask_travels_with_the_query_as_its_visibility() -> None:
    from matl.inference.api import _query_visibility
    from matl.inference.foreground import GrabCutForeground, mask_query

    rng = np.random.default_rng(0)
    rgb = rng.uniform(0.2, 1.0, (30, 20, 3)).astype(np.float32)
    alpha = np.ones((30, 20), np.float32)
    alpha[:, 5:9] = 0.0
    alpha[:, 9] = 0.5  # a soft edge
    rgba = np.concatenate([rgb, alpha[..., None]], -1)
    plain = mask_query(None, rgb)
    assert _query_visibility([plain], SIZE, 1.0, torch.device("cpu")) is None  # no mask: ones everywhere
    seen = _query_visibility([mask_query(None, rgba), plain], SIZE, 1.0, torch.device("cpu"))
    framed = torch.from_numpy(alpha)[None]
    from matl.data.image_files import fit_to_model

    expected = fit_to_model(framed, SIZE, 1.0)[0][:1]
    assert seen.shape == (2, 1, SIZE, SIZE) and torch.allclose(seen[0], expected, atol=1e-6)  # the alpha read back
    ones = fit_to_model(torch.ones_like(framed), SIZE, 1.0)[0][:1]
    assert torch.equal(seen[1], ones)  # a query without a mask beside one with it: ones where the file is
    assert float(ones[:, :, :8].max()) == 0.0 and float(ones.max()) == 1.0  # the frame's padding holds no pixel
    # the foreground step's mask is the visibility of an RGB query
    step = GrabCutForeground(retry_insets=())
    crop = np.zeros((40, 40, 3), np.float32)
    crop[10:30, 12:28] = rgb[:20, :16]
    found = mask_query(step, crop)
    assert found[2] is not None
    assert torch.allclose(_query_visibility([found], SIZE, 1.0, torch.device("cpu"))[0],
                          fit_to_model(torch.from_numpy(found[2])[None], SIZE, 1.0)[0][:1])


def test_an_occluded_query_verifies_on_what_it_shows(tmp_path: Path) -> None:
    gallery, queries, pose = easy_files(tmp_path)
    query = read_rgb(queries / "red_box.png")
    other = read_rgb(queries / "blue_card.png")
    covered = query.copy()
    covered[:, 60:90] = other[:, 60:90]  # another product's print across the crop, kept by the mask
    options = {"threshold": None, "foreground": "none", "verify_max": 0.2}  # 6 px patches at 48 px: a looser level
    visible = Recognizer(StubModel(pose), SIZE, 1, "stub-model", **options).enrol(gallery)
    whole = Recognizer(StubModel(pose), SIZE, 1, "stub-model", verify_statistic="global", **options).enrol(gallery)
    assert visible.verify_statistic == "patches"  # the default
    seen, judged_whole = visible.predict(covered), whole.predict(covered)
    assert seen.object == judged_whole.object == "red_box"
    assert seen.verification <= visible.verify_max < judged_whole.verification
    # an RGBA query whose alpha leaves the occluder out shows too little when the bar is most of the product
    alpha = np.full((*query.shape[:2], 1), 255, np.uint8)
    alpha[:, 20:130] = 0
    hidden = visible.predict(np.concatenate([query, alpha], -1))
    assert hidden.verification == 1.0
    lenient = Recognizer(StubModel(pose), SIZE, 1, "stub-model", verify_min_visible=0.0, **options).enrol(gallery)
    assert lenient.predict(np.concatenate([query, alpha], -1)).verification < 1.0
    for bad in ({"verify_statistic": "median"}, {"verify_min_visible": 1.5}, {"verify_min_visible": True}):
        with pytest.raises(MatlError, match=next(iter(bad))):
            stub_recognizer(**bad)


def test_the_calibration_copies_are_partly_occluded() -> None:
    from matl.inference.api import CALIBRATION_HIDDEN, _occluded_copies

    S, W = 32, 8
    images = torch.zeros(2 * W, 3, S, S)
    images[:, :, 6:26, 4:28] = torch.rand(2 * W, 3, 20, 24, generator=torch.Generator().manual_seed(0)) * 0.8 + 0.1
    out, visibility, rows = _occluded_copies(images, ["a/front", "b/back"])
    assert rows.tolist() == [j for j in range(2 * W) if j % 2 == 1]  # half of each plane's copies
    again = _occluded_copies(images, ["a/front", "b/back"])
    assert torch.equal(again[0], out) and torch.equal(again[1], visibility)  # seeded by the planes' names
    plane = images[0].amax(0) > 0
    for row in range(2 * W):
        changed = (out[row] != images[row]).any(0)
        if row % 2 == 0:
            assert not bool(changed.any()) and float(visibility[row].min()) == 1.0
            continue
        share = float((changed & plane).sum() / plane.sum())
        low, high = CALIBRATION_HIDDEN
        assert low - 0.05 <= share <= high + 0.05
        if row % 4 == 1:  # drawn grey: seen (a mask that kept the occluder)
            assert float(visibility[row].min()) == 1.0 and float(out[row][:, changed].std()) < 1e-6
        else:             # cut out: 0 and not seen
            assert float(out[row][:, changed].abs().max()) == 0.0
            assert bool((visibility[row][0][changed] == 0).all()) and float(visibility[row].max()) == 1.0
