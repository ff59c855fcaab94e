"""matl.eval, matl.predict, the STN classifier (row c) and the one-line user errors.

Everything runs at TINY scale (32 px, one epoch); a single MATL run is trained per module and shared.
"""

from __future__ import annotations

import csv
import json
import logging
import math
import os
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
import torch.nn.functional as F
from omegaconf import DictConfig, OmegaConf, open_dict
from torch import nn

from matl.data.image_files import fit_geometry, fit_to_model, load_image_file, pose_in_files
from matl.evaluation.evaluate import DEFAULT_N, DEFAULT_SEED, evaluate
from matl.geometry import warp_image
from matl.inference.api import Recognizer
from matl.inference.files import predict, predict_files
from matl.inference.gallery import enrol_gallery
from matl.metrics import METRIC_NAMES
from matl.models.stn import STNOutput
from matl.training.fit import train
from matl.utils.errors import MatlError
from tests.conftest import TINY, compose_config

REPO = Path(__file__).resolve().parents[1]
RECORD_KEYS = {"image", "object", "plane", "known", "nearest_object", "anchor", "distance", "score", "statistic",
               "H", "gallery_image"}


# --------------------------------------------------------------------------------------- helpers
def save_run_config(cfg: DictConfig, run_dir: Path) -> None:
    """What Hydra writes for a real run: train() called directly does not."""
    (run_dir / ".hydra").mkdir(parents=True, exist_ok=True)
    OmegaConf.save(cfg, run_dir / ".hydra" / "config.yaml")


def train_run(run_dir: Path, cache_dir: Path, extra: list[str] | None = None) -> dict:
    cfg = compose_config("train", [*TINY, f"paths.cache_dir={cache_dir}", "logger=none", *(extra or [])], run_dir)
    save_run_config(cfg, run_dir)
    return train(cfg)


def eval_cfg(out: Path, overrides: list[str]) -> DictConfig:
    return compose_config("eval", overrides, out)


def read_csv(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def smooth_texture(height: int, width: int, colour: tuple[float, float, float], seed: int) -> np.ndarray:
    """A low-frequency RGB pattern (resampling-friendly) dominated by ``colour``: ``(H, W, 3)`` in [0, 1]."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:height, 0:width].astype(np.float64)
    pattern = np.zeros((height, width))
    for _ in range(3):
        fx, fy, phase = rng.uniform(0.5, 2.0) / width, rng.uniform(0.5, 2.0) / height, rng.uniform(0, 2 * np.pi)
        pattern += np.sin(2 * np.pi * (fx * x + fy * y) + phase)
    shade = 0.55 + 0.15 * pattern / 3.0
    return np.clip(np.asarray(colour)[None, None, :] * shade[..., None] + 0.05, 0.0, 1.0)


def write_png(path: Path, rgb: np.ndarray, alpha: np.ndarray | None = None) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    bgr = (np.clip(rgb, 0, 1) * 255).round().astype(np.uint8)[..., ::-1]
    if alpha is not None:
        bgr = np.dstack([bgr, (alpha * 255).round().astype(np.uint8)])
    assert cv2.imwrite(str(path), bgr)


# A gallery-file -> query-file homography (pixels): half size, rotated 20 deg, a little perspective,
# mapping a 160x120 gallery image inside a 90x130 query image.
def true_query_H_gallery() -> np.ndarray:
    c, s = math.cos(math.radians(20)), math.sin(math.radians(20))
    centre_gallery = np.array([[1, 0, -79.5], [0, 1, -59.5], [0, 0, 1]])
    rotate_scale = np.array([[0.5 * c, 0.5 * s, 0], [-0.5 * s, 0.5 * c, 0], [0, 0, 1]])
    to_query = np.array([[1, 0, 44.5], [0, 1, 64.5], [0, 0, 1]])
    perspective = np.array([[1, 0, 0], [0, 1, 0], [4e-4, -3e-4, 1]])
    H = to_query @ rotate_scale @ perspective @ centre_gallery
    return H / H[2, 2]


COLOURS = {"red_box": (1.0, 0.15, 0.1), "green_can": (0.1, 1.0, 0.2), "blue_card": (0.15, 0.2, 1.0)}
GALLERY_HW, QUERY_HW = (120, 160), (130, 90)


def make_files(root: Path) -> tuple[Path, Path, np.ndarray]:
    """A gallery of 3 one-plane objects (160x120 PNG) and one 90x130 query per object warped by a known H."""
    gallery, queries = root / "gallery", root / "queries"
    H = true_query_H_gallery()
    for k, (name, colour) in enumerate(COLOURS.items()):
        image = smooth_texture(*GALLERY_HW, colour, seed=k)
        write_png(gallery / name / "front.png", image)
        warped = cv2.warpPerspective(image.astype(np.float32), H, (QUERY_HW[1], QUERY_HW[0]), flags=cv2.INTER_LINEAR)
        write_png(queries / f"{name}.png", warped)
    return gallery, queries, H


# ------------------------------------------------------------------------------------- fixtures
@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory: pytest.TempPathFactory, cache_dir: Path) -> Path:
    run_dir = tmp_path_factory.mktemp("matl_run")
    train_run(run_dir, cache_dir)
    return run_dir


@pytest.fixture(scope="module")
def tiny_eval(tiny_run: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("eval")
    evaluate(eval_cfg(out, [f"run={tiny_run}"]), show_progress=False)
    return out


# ----------------------------------------------------------------------------------------- eval
def test_eval_reproduces_train_test_metrics(tiny_run: Path, tiny_eval: Path) -> None:
    trained = json.loads((tiny_run / "metrics.json").read_text())
    evaluated = json.loads((tiny_eval / "eval.json").read_text())
    for name in METRIC_NAMES:
        assert evaluated[name] == pytest.approx(trained[name], abs=1e-6), name
    assert evaluated["query_ms"] > 0
    assert evaluated["evaluated"] == "checkpoint" and evaluated["checkpoint"].endswith("best.ckpt")
    assert evaluated["num_queries"] == 48 and evaluated["N"] == 4 and evaluated["image_size"] == 32
    rows = read_csv(tiny_eval / "per_query.csv")
    assert len(rows) == 48
    assert np.mean([int(r["correct"]) for r in rows]) == pytest.approx(evaluated["rec_acc"])
    correct = [float(r["frobenius_err"]) for r in rows if r["correct"] == "1"]
    assert np.mean(correct) == pytest.approx(evaluated["pose_err"], rel=1e-9)
    est = np.array([[float(r[f"est_H_{i}{j}"]) for i in range(3) for j in range(3)] for r in rows])
    assert np.allclose(est[:, 8], 1.0)


def test_eval_last_checkpoint_and_other_data(tiny_run: Path, tmp_path: Path, cache_dir: Path) -> None:
    out = evaluate(eval_cfg(tmp_path / "a", [f"run={tiny_run}", "ckpt=last", "+data.test_queries=8"]),
                   show_progress=False)
    assert out["checkpoint"].endswith("last.ckpt") and out["num_queries"] == 8
    # data=<name>: composed and swapped in, the run's image size / N / seed stay
    other = evaluate(eval_cfg(tmp_path / "b", [f"run={tiny_run}", "data=synthetic_apc", "data.test_queries=8"]),
                     show_progress=False)
    assert other["image_size"] == 32 and other["N"] == 4 and other["seed"] == 0
    assert other["gallery_size"] == 90 * 4 and other["num_queries"] == 8


def test_eval_user_errors(tiny_run: Path, tmp_path: Path) -> None:
    with pytest.raises(MatlError, match="no such folder"):
        evaluate(eval_cfg(tmp_path / "e", [f"run={tmp_path / 'missing'}"]))
    (tmp_path / "bare").mkdir()
    with pytest.raises(MatlError, match=r"no \.hydra/config\.yaml"):
        evaluate(eval_cfg(tmp_path / "e", [f"run={tmp_path / 'bare'}"]))
    with pytest.raises(MatlError, match="not found"):
        evaluate(eval_cfg(tmp_path / "e", [f"run={tiny_run}", f"ckpt={tmp_path / 'nope.ckpt'}"]))
    with pytest.raises(MatlError, match="seed=3 differs"):
        evaluate(eval_cfg(tmp_path / "e", [f"run={tiny_run}", "seed=3"]))
    with pytest.raises(MatlError, match="run=<run dir> is required"):
        evaluate(eval_cfg(tmp_path / "e", []))
    # a 32 px checkpoint against a run config of another size / N
    for key, value, message in (("data.image_size", 48, "trained at 32 px"), ("N", 2, "with N=4")):
        other = tmp_path / f"other_{value}"
        saved = OmegaConf.load(tiny_run / ".hydra" / "config.yaml")
        OmegaConf.update(saved, key, value)
        save_run_config(saved, other)
        ckpt = tiny_run / "checkpoints" / "best.ckpt"
        with pytest.raises(MatlError, match=message):
            evaluate(eval_cfg(tmp_path / "e", [f"run={other}", f"ckpt={ckpt}"]))


def test_eval_defaults_match_train() -> None:
    train_cfg = compose_config("train", [])
    assert (train_cfg.N, train_cfg.seed) == (DEFAULT_N, DEFAULT_SEED)


def test_baseline_sift_same_queries(tiny_run: Path, tiny_eval: Path, tmp_path: Path) -> None:
    pytest.importorskip("matl.baselines.sift")
    cfg = eval_cfg(tmp_path, [f"run={tiny_run}", "baseline=sift", "timing_queries=3"])
    out = evaluate(cfg, show_progress=False)
    assert out["evaluated"] == "baseline" and out["checkpoint"] is None
    assert 0.0 <= out["rec_acc"] <= 1.0 and out["query_ms"] > 0
    rows, model_rows = read_csv(tmp_path / "per_query.csv"), read_csv(tiny_eval / "per_query.csv")
    true_cols = [f"true_H_{i}{j}" for i in range(3) for j in range(3)]
    assert [[r[c] for c in true_cols] for r in rows] == [[r[c] for c in true_cols] for r in model_rows]
    assert all(r["inliers"] != "" for r in rows)


def test_baseline_without_run(tmp_path: Path, cache_dir: Path) -> None:
    pytest.importorskip("matl.baselines.sift")
    cfg = eval_cfg(tmp_path, ["baseline=sift", "data=synthetic_arc", "data.image_size=32", "data.test_queries=6",
                              "seed=1", "N=2", "timing_queries=2", f"paths.cache_dir={cache_dir}"])
    out = evaluate(cfg, show_progress=False)
    assert out["run"] is None and out["seed"] == 1 and out["N"] == 2 and out["num_queries"] == 6
    assert out["gallery_size"] == 152 * 2


# --------------------------------------------------------------------------------- classifier
def test_stn_classifier_trains_evaluates_and_cannot_enrol(tmp_path: Path, cache_dir: Path) -> None:
    matl_stn = compose_config("train", ["model=matl"]).model.stn
    assert compose_config("train", ["model=stn_classifier"]).model.stn == matl_stn, "row (c) must use MATL's STN"
    run_dir = tmp_path / "cls"
    results = train_run(run_dir, cache_dir, ["model=stn_classifier"])
    for name in METRIC_NAMES:
        assert results[name] is not None and math.isfinite(results[name]), name
    ckpt = torch.load(run_dir / "checkpoints" / "best.ckpt", weights_only=True)
    assert len(ckpt["matl_class_names"]) == 34 and not any(k.startswith("recognizer.") for k in ckpt["state_dict"])
    evaluated = evaluate(eval_cfg(tmp_path / "eval", [f"run={run_dir}"]), show_progress=False)
    for name in METRIC_NAMES:
        assert evaluated[name] == pytest.approx(results[name], abs=1e-6), name
    with pytest.raises(MatlError, match="trained on"):
        evaluate(eval_cfg(tmp_path / "eval2", [f"run={run_dir}", "data=synthetic_apc", "data.test_queries=4"]))
    gallery, queries, _ = make_files(tmp_path / "files")
    with pytest.raises(MatlError, match="cannot enrol"):
        predict(predict_cfg(tmp_path, run_dir / "checkpoints" / "best.ckpt", gallery, queries))


# ------------------------------------------------------------------------- image coordinates
@pytest.mark.parametrize("hw,size,fill", [((120, 160), 32, 1.0), ((130, 90), 48, 1.0), ((20, 30), 64, 1.0),
                                          ((120, 160), 40, 0.6)])
def test_fit_matrix_matches_the_pixels(hw: tuple[int, int], size: int, fill: float) -> None:
    """A blob's centroid lands where ``model_H_file`` says, for down- and up-scaling and padding."""
    h, w = hw
    sigma = max(h, w) / 20
    centre = np.array([0.37 * (w - 1) + 0.3, 0.61 * (h - 1) - 0.2])
    y, x = np.mgrid[0:h, 0:w]
    blob = np.exp(-((x - centre[0]) ** 2 + (y - centre[1]) ** 2) / (2 * sigma**2))
    image, fit = fit_to_model(np.repeat(blob[..., None], 3, axis=2).astype(np.float32), size, fill)
    assert image.shape == (3, size, size)
    m = image[0].double()
    ys, xs = torch.meshgrid(torch.arange(size, dtype=torch.float64), torch.arange(size, dtype=torch.float64),
                            indexing="ij")
    measured = torch.stack([(m * xs).sum() / m.sum(), (m * ys).sum() / m.sum()])
    expected = fit.model_H_file @ torch.tensor([*centre, 1.0], dtype=torch.float64)
    assert torch.allclose(measured, expected[:2], atol=0.05), (measured, expected)
    assert max(fit.new_height, fit.new_width) == round(fill * size)  # the longer side spans fill * size
    # padding is zero and centred
    assert image[:, :, : fit.left].abs().max() == 0 if fit.left else True
    assert abs((size - fit.new_width) - 2 * fit.left) <= 1 and abs((size - fit.new_height) - 2 * fit.top) <= 1


def test_load_image_file_alpha_and_bad_files(tmp_path: Path) -> None:
    rgb = np.full((10, 12, 3), 0.8)
    alpha = np.zeros((10, 12))
    alpha[2:8, 3:9] = 1.0
    write_png(tmp_path / "a.png", rgb, alpha)
    loaded = load_image_file(tmp_path / "a.png")
    assert loaded.shape == (10, 12, 3) and loaded[0, 0].max() == 0 and loaded[4, 5].min() > 0.75
    (tmp_path / "empty.png").write_bytes(b"")
    (tmp_path / "text.png").write_text("hello")
    for name, message in (("empty.png", "empty file"), ("text.png", "not an image"), ("none.png", "no such file")):
        with pytest.raises(MatlError, match=message):
            load_image_file(tmp_path / name)


class MeanColour(nn.Module):
    """Stub ``c()``: the L2-normalised mean colour ``(B, 3, S, S) -> (B, 3)`` (background 0 only scales it)."""

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        return F.normalize(images.mean(dim=(-2, -1)), dim=-1)


class FixedSTN(nn.Module):
    """Stub ``s()`` that 'predicts' a given model-frame ``query_H_anchor`` for every query."""

    def __init__(self, query_H_anchor: torch.Tensor) -> None:
        super().__init__()
        self.register_buffer("H", query_H_anchor.double())

    def forward(self, images: torch.Tensor) -> STNOutput:
        B = len(images)
        return STNOutput(images, self.H.expand(B, 3, 3).clone(), torch.zeros(B, dtype=torch.bool))


def test_predict_files_reports_H_in_original_file_pixels(tmp_path: Path) -> None:
    """With an STN that outputs the exact model-frame pose, predict's H is the true file-to-file H."""
    size = 48
    gallery_dir, queries_dir, H_true = make_files(tmp_path)
    gallery_fit = fit_geometry(*GALLERY_HW, size).model_H_file
    query_fit = fit_geometry(*QUERY_HW, size).model_H_file
    # the pose a perfect STN would give at model resolution (N = 1: anchor = canonical image)
    model_H = query_fit @ torch.from_numpy(H_true) @ torch.linalg.inv(gallery_fit)

    enrolled = enrol_gallery(gallery_dir, MeanColour(), size, num_anchors=1)
    assert enrolled.gallery.object_names == sorted(COLOURS)
    # that model-frame pose really aligns the model-size images (the fit matrices describe the pixels)
    canon = enrolled.gallery.images[0:1]  # blue_card/front
    query, _ = fit_to_model(load_image_file(queries_dir / "blue_card.png"), size)
    warped = warp_image(canon, model_H[None].float())
    inside = warp_image(torch.ones_like(canon), model_H[None].float())[0, 0] > 0.999
    inside = -F.max_pool2d(-inside[None].float(), 5, 1, 2)[0] > 0.5  # away from the resampled border
    assert inside.sum() > 100
    assert (warped[0] - query).abs()[:, inside].mean() < 0.02

    model = nn.Module()
    model.feature_net, model.stn, model.anchor_choice = MeanColour(), FixedSTN(model_H), "feature"
    recognizer = Recognizer(model, size, 1, "stub", threshold=None, batch_size=2).enrol(gallery_dir, cache=False)
    records: list[dict] = []
    (queries_dir / "notes.txt").write_text("not an image")
    files = sorted(queries_dir.iterdir())
    done, bad = predict_files(recognizer, files, records.append, viz_dir=tmp_path / "viz", show_progress=False)
    assert (done, bad) == (3, [queries_dir / "notes.txt"])
    assert sorted(p.name for p in (tmp_path / "viz").iterdir()) == ["blue_card.png", "green_can.png", "red_box.png"]
    for record in records:
        assert set(record) == RECORD_KEYS
        assert record["object"] == Path(record["image"]).stem and record["anchor"] == 0 and record["known"]
        np.testing.assert_allclose(np.array(record["H"]), H_true, rtol=1e-9, atol=1e-9)
        # the promise of docs/design.md: cv2.warpPerspective of the gallery file with H lands on the query file
        g = cv2.imread(record["gallery_image"]).astype(np.float32)
        q = cv2.imread(record["image"]).astype(np.float32)
        back = cv2.warpPerspective(g, np.array(record["H"]), (QUERY_HW[1], QUERY_HW[0]), flags=cv2.INTER_LINEAR)
        assert np.abs(back - q).max() <= 1.0
    # the bookkeeping function alone, batched
    H = pose_in_files(model_H[None].repeat(2, 1, 1), gallery_fit[None].repeat(2, 1, 1),
                      query_fit[None].repeat(2, 1, 1))
    np.testing.assert_allclose(H.numpy(), np.stack([H_true, H_true]), rtol=1e-9, atol=1e-9)


# --------------------------------------------------------------------------------- predict e2e
def predict_cfg(tmp_path: Path, ckpt: Path, gallery: Path, images: Path, extra: list[str] | None = None) -> DictConfig:
    cfg = compose_config("predict", [f"ckpt={ckpt}", f"gallery={gallery}", f"images={images}",
                                     f"out={tmp_path / 'out' / 'pred.jsonl'}", *(extra or [])], tmp_path / "run")
    with open_dict(cfg):
        cfg.viz_dir = str(tmp_path / "run" / "viz")
    return cfg


def test_predict_end_to_end_with_tiny_checkpoint(tiny_run: Path, tmp_path: Path,
                                                 caplog: pytest.LogCaptureFixture) -> None:
    ckpt = tiny_run / "checkpoints" / "best.ckpt"
    gallery, queries, _ = make_files(tmp_path)
    # a second plane of another size, with alpha, a JPEG plane and files that must be skipped
    alpha = np.zeros((70, 50))
    alpha[5:65, 5:45] = 1.0
    write_png(gallery / "red_box" / "top.png", smooth_texture(70, 50, (1, 0.2, 0.1), 7), alpha)
    jpg = (smooth_texture(40, 90, (0.2, 0.9, 0.3), 8) * 255).astype(np.uint8)
    cv2.imwrite(str(gallery / "green_can" / "side.jpg"), jpg[..., ::-1])
    (gallery / "notes.txt").write_text("not an object folder")
    (gallery / "blue_card" / "notes.md").write_text("not a plane")
    (queries / "broken.png").write_text("not an image")
    (queries / "empty.jpg").write_bytes(b"")

    with caplog.at_level(logging.WARNING):
        summary = predict(predict_cfg(tmp_path, ckpt, gallery, queries, ["viz=true", "batch_size=2"]))
    assert summary["predicted"] == 3 and summary["skipped"] == 2
    assert summary["gallery_planes"] == 5 and summary["gallery_objects"] == 3
    skipped = [r.getMessage() for r in caplog.records if r.getMessage().startswith("skipped")]
    assert any("broken.png: not an image" in m for m in skipped) and any("empty.jpg: empty file" in m for m in skipped)
    assert any("notes.txt" in m for m in skipped) and any("notes.md" in m for m in skipped)
    assert all("\n" not in m for m in skipped)

    lines = (tmp_path / "out" / "pred.jsonl").read_text().splitlines()
    assert len(lines) == 3
    for line in lines:
        record = json.loads(line)
        assert set(record) == RECORD_KEYS
        assert record["nearest_object"] in COLOURS and 0 <= record["anchor"] < 4
        assert record["object"] == (record["nearest_object"] if record["known"] else None)
        assert np.isfinite(record["distance"]) and np.array(record["H"]).shape == (3, 3)
        assert record["H"][2][2] == pytest.approx(1.0)
    assert len(list((tmp_path / "run" / "viz").glob("*.png"))) == 3

    # features cached next to the gallery, loadable safely; reused, and refreshed when a file changes
    caches = list(gallery.glob(".matl_gallery_*.pt"))
    assert len(caches) == 1
    payload = torch.load(caches[0], weights_only=True)
    assert payload["features"].shape[0] == 5 * 4
    caplog.clear()
    with caplog.at_level(logging.INFO):
        predict(predict_cfg(tmp_path, ckpt, gallery, queries, ["batch_size=2"]))
    assert any("loaded from" in r.getMessage() for r in caplog.records)
    # same answers from the cached features
    assert (tmp_path / "out" / "pred.jsonl").read_text().splitlines() == lines
    stat = (gallery / "red_box" / "front.png").stat()
    os.utime(gallery / "red_box" / "front.png", ns=(stat.st_atime_ns, stat.st_mtime_ns + 10**9))
    predict(predict_cfg(tmp_path, ckpt, gallery, queries))
    refreshed = list(gallery.glob(".matl_gallery_*.pt"))
    assert len(refreshed) == 1 and refreshed != caches

    # a single file works too
    single = predict(predict_cfg(tmp_path, ckpt, gallery, queries / "red_box.png", ["cache=false"]))
    assert single["predicted"] == 1


def test_predict_user_errors(tiny_run: Path, tmp_path: Path) -> None:
    ckpt = tiny_run / "checkpoints" / "best.ckpt"
    gallery, queries, _ = make_files(tmp_path)
    with pytest.raises(MatlError, match="not found"):
        predict(predict_cfg(tmp_path, tmp_path / "missing.ckpt", gallery, queries))
    (tmp_path / "empty_gallery").mkdir()
    with pytest.raises(MatlError, match="holds no canonical images"):
        predict(predict_cfg(tmp_path, ckpt, tmp_path / "empty_gallery", queries))
    (tmp_path / "bad_gallery" / "obj").mkdir(parents=True)
    (tmp_path / "bad_gallery" / "obj" / "front.png").write_text("not a png")
    with pytest.raises(MatlError, match="no usable image"):
        predict(predict_cfg(tmp_path, ckpt, tmp_path / "bad_gallery", queries))
    with pytest.raises(MatlError, match="trained at 32 px"):
        predict(predict_cfg(tmp_path, ckpt, gallery, queries, ["image_size=48"]))
    with pytest.raises(MatlError, match="no such file or folder"):
        predict(predict_cfg(tmp_path, ckpt, gallery, tmp_path / "nothing_here"))
    with pytest.raises(MatlError, match="required"):
        predict(compose_config("predict", [f"ckpt={ckpt}"], tmp_path / "run"))
    (tmp_path / "not_a_ckpt.ckpt").write_text("garbage")
    with pytest.raises(MatlError, match="cannot be read"):
        predict(predict_cfg(tmp_path, tmp_path / "not_a_ckpt.ckpt", gallery, queries))


@pytest.mark.parametrize("module,args", [
    ("matl.eval", ["run=/nonexistent/run"]),
    ("matl.predict", ["ckpt=/nonexistent.ckpt", "gallery=/nonexistent", "images=/nonexistent"]),
])
def test_cli_prints_one_line_and_exits_2(module: str, args: list[str], tmp_path: Path) -> None:
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(REPO)}
    proc = subprocess.run([sys.executable, "-m", module, *args, f"hydra.run.dir={tmp_path / 'h'}"],
                          cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 2, proc.stderr
    assert "Traceback" not in proc.stderr + proc.stdout
    errors = [line for line in proc.stderr.splitlines() if line.startswith("error: ")]
    assert len(errors) == 1 and "/nonexistent" in errors[0]
