"""The one image reader: alpha, 16-bit grey, EXIF-free basics, and the errors that name the file."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from matl.data.image_files import ImageFileError, load_image_file, read_rgba


def test_read_rgba_and_load_image_file_agree(tmp_path: Path) -> None:
    rgba = np.zeros((6, 5, 4), np.uint8)
    rgba[..., 0], rgba[..., 3] = 200, 255
    rgba[0, 0, 3] = 0  # one transparent pixel
    Image.fromarray(rgba).save(tmp_path / "a.png")
    rgb, alpha = read_rgba(tmp_path / "a.png")
    assert rgb.shape == (6, 5, 3) and alpha is not None and alpha[0, 0] == 0 and alpha[1, 1] == 1
    loaded = load_image_file(tmp_path / "a.png")
    assert np.array_equal(loaded, rgb * alpha[..., None]) and loaded[0, 0].max() == 0
    assert np.isclose(loaded[1, 1, 0], 200 / 255)

    Image.fromarray(np.full((4, 4, 3), 51, np.uint8)).save(tmp_path / "b.png")
    rgb, alpha = read_rgba(tmp_path / "b.png")
    assert alpha is None and np.allclose(rgb, 0.2) and np.array_equal(load_image_file(tmp_path / "b.png"), rgb)


def test_16_bit_grey_is_scaled_by_its_depth(tmp_path: Path) -> None:
    Image.fromarray(np.array([[0, 32768], [65535, 13107]], np.uint16)).save(tmp_path / "g.png")
    rgb, alpha = read_rgba(tmp_path / "g.png")
    assert alpha is None and rgb.shape == (2, 2, 3)
    assert np.allclose(rgb[..., 0], [[0.0, 32768 / 65535], [1.0, 0.2]], atol=1e-6)
    assert np.array_equal(rgb[..., 0], rgb[..., 2])


def test_unusable_files_name_themselves(tmp_path: Path) -> None:
    with pytest.raises(ImageFileError, match=r"nope\.png: no such file"):
        read_rgba(tmp_path / "nope.png")
    (tmp_path / "empty.png").write_bytes(b"")
    with pytest.raises(ImageFileError, match=r"empty\.png: empty file"):
        read_rgba(tmp_path / "empty.png")
    (tmp_path / "text.png").write_text("not an image")
    with pytest.raises(ImageFileError, match=r"text\.png: not an image"):
        load_image_file(tmp_path / "text.png")
    Image.fromarray(np.zeros((1, 3, 3), np.uint8)).save(tmp_path / "line.png")
    assert read_rgba(tmp_path / "line.png")[0].shape == (1, 3, 3)
    with pytest.raises(ImageFileError, match=r"line\.png: image has no pixels"):
        read_rgba(tmp_path / "line.png", min_side=2)  # the photo path needs 2 px each way
