"""Image files in, model-size tensors out: the fit matrices describe the pixels, bad files are one line."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from matl.data.image_files import fit_to_model, load_image_file
from matl.utils.errors import MatlError
from tests.predict_helpers import (
    write_png,
)


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


