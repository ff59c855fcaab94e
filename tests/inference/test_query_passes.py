"""The passes of a query: framing at model size, the foreground step's pose passes, verification."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from matl.data.image_files import fit_to_model
from matl.inference.foreground import mask_query
from tests.inference.test_api import SIZE, read_rgb, stub_recognizer
from tests.predict_helpers import make_files


def test_the_answer_of_queries_framed_at_model_size(tmp_path: Path) -> None:
    gallery, queries, _ = make_files(tmp_path)
    rgb = read_rgb(queries / "red_box.png").astype(np.float32) / 255.0
    plain = stub_recognizer(threshold=None, foreground="none", verify_top_k=0).enrol(gallery)
    recognizer, _ = plain._build()
    prepared = [mask_query(plain.foreground, rgb)]
    pred, framed, model_H_file, verification, visibility = plain._answer(recognizer, prepared)
    expected, fit = fit_to_model(rgb, SIZE, plain.query_fill)
    assert verification is None and visibility is None and framed.shape == (1, 3, SIZE, SIZE)
    assert torch.equal(framed[0], expected) and torch.equal(model_H_file[0], fit.model_H_file)
    assert torch.equal(pred.plane_index, recognizer(framed).plane_index)
    verified = stub_recognizer(threshold=None, foreground="none").enrol(gallery)
    pred_v, framed_v, _, verification, _ = verified._answer(verified._build()[0], prepared)
    assert verification is not None and bool(verification.verified[0]) and torch.equal(framed_v, framed)
    assert verified.planes[int(pred_v.plane_index[0])][0] == "red_box"
