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
