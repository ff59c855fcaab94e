"""Enrolment: save / load of a gallery, its refusal for another model, its size."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from matl import Recognizer
from matl.utils.errors import MatlError
from tests.inference.test_api import SIZE, StubModel, exact_model_pose, gallery_folder, read_rgb, stub_recognizer
from tests.predict_helpers import make_files


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


def test_a_gallery_changed_by_add_or_remove_reuses_the_anchors_it_had(tmp_path: Path,
                                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    """After ``add`` or ``remove`` the next query warps only the new planes' anchors; the gallery is the one a fresh
    build makes."""
    import matl.inference.api as api
    from matl.inference.gallery import build_gallery

    warped: list[int] = []

    def counting(canon_u8, objects, names, object_names, num_anchors, images=None):
        warped.append(0 if images is not None else len(canon_u8))
        return build_gallery(canon_u8, objects, names, object_names, num_anchors, images)

    monkeypatch.setattr(api, "build_gallery", counting)
    gallery, queries, _ = make_files(tmp_path)
    rec = stub_recognizer(threshold=None).enrol(gallery, cache=False)
    query = read_rgb(queries / "red_box.png")
    rec.predict(query)
    assert warped == [3]  # the first build warps every plane
    warped.clear()

    def fresh() -> torch.Tensor:
        return build_gallery(torch.stack([p.canon_u8 for p in rec._planes]), rec._plane_objects(),
                             [p.name for p in rec._planes], rec.objects, rec.num_anchors).images

    rec.add("extra", "top", read_rgb(queries / "blue_card.png"))
    rec.predict(query)
    assert warped == [1, 0] and torch.equal(rec._build()[1].images, fresh())  # the new plane, then the labels
    warped.clear()
    rec.remove("red_box")
    answer = rec.predict(query)
    assert warped == [0] and torch.equal(rec._build()[1].images, fresh()) and answer.nearest_object != "red_box"
