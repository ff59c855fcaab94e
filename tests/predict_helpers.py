"""Shared by the eval and predict tests: a tiny trained run, gallery/query files with a known H, stub networks."""

from __future__ import annotations

import csv
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
import torch.nn.functional as F
from omegaconf import DictConfig, OmegaConf, open_dict
from torch import nn

from matl.evaluation.evaluate import evaluate
from matl.models.stn import STNOutput
from matl.training.fit import train
from tests.conftest import TINY, compose_config

REPO = Path(__file__).resolve().parents[1]
RECORD_KEYS = {"image", "object", "plane", "known", "nearest_object", "anchor", "distance", "score", "statistic",
               "H", "gallery_image", "verification", "covered_by"}


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


# --------------------------------------------------------------------------------- predict e2e
def predict_cfg(tmp_path: Path, ckpt: Path, gallery: Path, images: Path, extra: list[str] | None = None) -> DictConfig:
    cfg = compose_config("predict", [f"ckpt={ckpt}", f"gallery={gallery}", f"images={images}",
                                     f"out={tmp_path / 'out' / 'pred.jsonl'}", *(extra or [])], tmp_path / "run")
    with open_dict(cfg):
        cfg.viz_dir = str(tmp_path / "run" / "viz")
    return cfg


