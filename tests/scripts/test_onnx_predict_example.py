"""scripts/onnx_predict_example.py: the exported ONNX files with numpy, OpenCV and onnxruntime answer as matl does."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from matl.models.checkpoint import PRETRAINED
from tests.scripts.conftest import SCRIPTS, load_script

SCRIPT = SCRIPTS / "onnx_predict_example.py"
GALLERY_HW = (120, 160)
pytest.importorskip("onnxruntime", reason="format=onnx needs onnxruntime (a dependency of matl)")
needs_model = pytest.mark.skipif(not PRETRAINED.is_file(), reason=f"{PRETRAINED} is not in this checkout")


@pytest.fixture(scope="module")
def example():
    return load_script("onnx_predict_example")


def art(seed: int) -> np.ndarray:
    """A product's print: smooth patterns of its own in each channel and a few flat bars, uint8 RGB."""
    rng = np.random.default_rng(seed)
    h, w = GALLERY_HW
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    channels = [0.5 + 0.15 * sum(np.sin(2 * np.pi * (rng.uniform(0.5, 3) * x / w + rng.uniform(0.5, 3) * y / h)
                                        + rng.uniform(0, 2 * np.pi)) for _ in range(3)) for _ in range(3)]
    image = np.stack(channels, -1)
    for _ in range(4):
        top, left = int(rng.integers(5, h - 20)), int(rng.integers(5, w - 60))
        image[top:top + 8, left:left + int(rng.integers(20, 55))] = rng.uniform(0, 1, 3)
    return (np.clip(image, 0, 1) * 255).round().astype(np.uint8)


def query_H_gallery(rng: np.random.Generator) -> np.ndarray:
    """A gallery-file -> query-file pose: turned, shrunk, a little perspective, into a 150 x 130 crop."""
    h, w = GALLERY_HW
    angle, scale = math.radians(rng.uniform(-30, 30)), rng.uniform(0.6, 0.8)
    centre = np.array([[1, 0, -(w - 1) / 2], [0, 1, -(h - 1) / 2], [0, 0, 1]])
    turn = np.array([[scale * math.cos(angle), -scale * math.sin(angle), 0],
                     [scale * math.sin(angle), scale * math.cos(angle), 0], [*rng.uniform(-4e-4, 4e-4, 2), 1]])
    return np.array([[1, 0, 74.5], [0, 1, 64.5], [0, 0, 1]]) @ turn @ centre


@needs_model
def test_the_example_reproduces_the_librarys_pose(example, tmp_path: Path) -> None:
    from matl import Recognizer
    from matl.geometry import corner_error_px
    from matl.inference.export import export
    from tests.conftest import compose_config

    export(compose_config("export", ["ckpt=pretrained", "format=onnx", f"out={tmp_path / 'exported'}"],
                          tmp_path / "run"))
    gallery, queries = tmp_path / "gallery", tmp_path / "queries"
    rng = np.random.default_rng(0)
    for k in range(4):
        (gallery / f"product_{k}").mkdir(parents=True)
        cv2.imwrite(str(gallery / f"product_{k}" / "front.png"), art(k)[..., ::-1])
        for j in range(2):
            queries.mkdir(exist_ok=True)
            crop = cv2.warpPerspective(art(k), query_H_gallery(rng), (150, 130), flags=cv2.INTER_LINEAR)
            cv2.imwrite(str(queries / f"product_{k}_{j}.png"), crop[..., ::-1])

    onnx = example.OnnxRecognizer(tmp_path / "exported", gallery)
    # the same computation in the library: no foreground step, no verification, no open set, no refinement
    library = Recognizer.pretrained(foreground="none", verify_top_k=0, threshold=None).enrol(gallery, cache=False)
    differences = []
    for path in sorted(queries.iterdir()):
        ours, theirs = onnx.predict(path), library.predict(path)
        assert (ours["object"], ours["plane"], ours["anchor"]) == (theirs.object, theirs.plane, theirs.anchor)
        assert ours["gallery_image"] == theirs.gallery_image
        differences.append(float(corner_error_px(torch.tensor(ours["H"])[None], torch.from_numpy(theirs.H)[None],
                                                 GALLERY_HW)))
    assert np.median(differences) < 0.1, differences

    # the command line of the script: one JSON line per query, with numpy, OpenCV and onnxruntime alone
    first = sorted(queries.iterdir())[0]
    proc = subprocess.run([sys.executable, str(SCRIPT), str(tmp_path / "exported"), str(gallery), str(first)],
                          capture_output=True, text=True, timeout=300, check=True)
    line = json.loads(proc.stdout)
    assert line["image"] == str(first) and np.allclose(line["H"], onnx.predict(first)["H"])


def test_the_resize_is_the_librarys(example) -> None:
    from matl.data.image_files import fit_to_model

    rng = np.random.default_rng(1)
    for h, w, fill in ((130, 150, 1.0), (40, 90, 0.6), (300, 200, 1.0), (7, 5, 1.0)):  # shrinking and enlarging
        image = rng.random((h, w, 3)).astype(np.float32)
        ours, model_H_file = example.fit_to_model(image, 100, fill)
        theirs, fit = fit_to_model(image, 100, fill)
        assert np.abs(ours - theirs.numpy()).max() < 1e-5
        assert np.allclose(model_H_file, fit.model_H_file.numpy())


def test_docs_show_the_examples_code() -> None:
    """docs/usage.md's onnxruntime snippet is this file's code (the tests run it): every line of it is here."""
    usage = (SCRIPT.parents[1] / "docs" / "usage.md").read_text()
    section = usage.split("### Without matl: the exported files in onnxruntime", 1)[1]
    snippet = section.split("```python", 1)[1].split("```", 1)[0]
    code = SCRIPT.read_text()
    lines = [line.strip() for line in snippet.splitlines() if line.strip() and not line.strip().startswith("#")]
    missing = [line for line in lines if line.split("  #")[0].rstrip() not in code]
    assert len(lines) > 10 and not missing, missing
