"""Open-set calibration: the threshold rule, the calibration's occluded copies, the samples kept."""

from __future__ import annotations

from pathlib import Path

import cv2
import pytest
import torch

from matl import Recognizer
from matl.inference import calibration
from matl.inference.calibration import CALIBRATION_HIDDEN, _occluded_copies, calibrate_open_set
from matl.utils.errors import MatlError
from tests.inference.test_api import read_rgb, stub_recognizer
from tests.predict_helpers import make_files


def test_calibration_by_hand() -> None:
    genuine = torch.tensor([0.1, 0.2, 0.3, 0.4, 0.5], dtype=torch.float64)
    assert calibrate_open_set(genuine, torch.zeros(0), 1.0) == pytest.approx(0.5)
    assert calibrate_open_set(genuine, torch.zeros(0), 0.5) == pytest.approx(0.3)
    assert calibrate_open_set(genuine[:0], torch.zeros(0), 0.5) == float("inf")


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


def test_a_gallery_calibrated_in_parts_gets_the_samples_it_gets_whole(tmp_path: Path,
                                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    gallery, _, _ = make_files(tmp_path)
    rec = stub_recognizer(verify_occluded_copies=0.5).enrol(gallery, cache=False)
    whole = rec.calibration()
    monkeypatch.setattr(calibration, "CALIBRATION_PLANES", 1)  # each plane's copies on their own
    parts = rec.calibration()
    assert len(rec.planes) > 1 and len(whole["genuine"]) == len(rec.planes) * rec.calibration_warps
    for name in ("genuine", "impostor"):
        assert torch.equal(parts[name], whole[name])
    # the occluded copies take their turns over the whole gallery, not per part
    images = torch.rand(4 * 2, 3, 16, 16)
    names = ["a/front", "b/back", "c/top", "d/left"]
    out, visibility, _ = _occluded_copies(images, names, 1)
    for first in range(4):
        rows = slice(2 * first, 2 * first + 2)
        part = _occluded_copies(images[rows], names[first:first + 1], 1, first)
        assert torch.equal(part[0], out[rows]) and torch.equal(part[1], visibility[rows])


def test_a_large_gallery_is_calibrated_on_a_sample_of_its_planes(tmp_path: Path) -> None:
    gallery, _, _ = make_files(tmp_path)
    rec = stub_recognizer().enrol(gallery, cache=False)
    planes = len(rec.planes)
    assert planes >= 3 and rec.calibration_planes == 2000  # the default: every plane of a gallery this small
    whole = rec.calibration()
    small = stub_recognizer(calibration_planes=2).enrol(gallery, cache=False)
    sample = small._calibration_sample()
    assert len(sample) == 2 and sample == sorted(sample)
    part = small.calibration()
    assert len(part["genuine"]) == 2 * small.calibration_warps
    # each sampled copy is the whole calibration's (compared with the whole gallery), the planes taken in parts or not
    rows = torch.cat([torch.arange(i * rec.calibration_warps, (i + 1) * rec.calibration_warps) for i in sample])
    assert torch.equal(part["genuine"], whole["genuine"][rows])
    # the same planes whatever the enrolment order: chosen by their names
    backwards = stub_recognizer(calibration_planes=2)
    for plane in reversed(small._planes):
        backwards.add(plane.object, plane.name, plane.path)
    assert sorted(small.planes[i] for i in sample) == sorted(
        backwards.planes[i] for i in backwards._calibration_sample())
    # the sample size is in the key where it applies; a gallery no larger than it keeps the key it had without it
    assert small.calibration_key() != rec.calibration_key()
    assert stub_recognizer(calibration_planes=planes).enrol(gallery, cache=False).calibration_key() == \
        stub_recognizer(calibration_planes=None).enrol(gallery, cache=False).calibration_key()
    for bad in (0, -3, 2.5, "many"):
        with pytest.raises(MatlError, match="calibration_planes=") as info:
            stub_recognizer(calibration_planes=bad)
        assert "\n" not in str(info.value)


def test_the_calibration_copies_are_partly_occluded() -> None:
    S, W = 32, 8
    planes = 4
    images = torch.zeros(planes * W, 3, S, S)
    images[:, :, 6:26, 4:28] = torch.rand(planes * W, 3, 20, 24, generator=torch.Generator().manual_seed(0)) * 0.8 + 0.1
    names = ["a/front", "b/back", "c/top", "d/left"]
    every = 2
    out, visibility, rows = _occluded_copies(images, names, every)
    assert rows.tolist() == [r for r in range(planes * W) if r % W % every == every - 1]  # one copy in `every`
    again = _occluded_copies(images, names, every)
    assert torch.equal(again[0], out) and torch.equal(again[1], visibility)  # seeded by the planes' names
    plane = images[0].amax(0) > 0
    kinds = set()
    for row in range(planes * W):
        changed = (out[row] != images[row]).any(0)
        if row not in rows.tolist():
            assert not bool(changed.any()) and float(visibility[row].min()) == 1.0
            continue
        share = float((changed & plane).sum() / plane.sum())
        low, high = CALIBRATION_HIDDEN
        assert low - 0.05 <= share <= high + 0.05
        if float(visibility[row].min()) == 1.0:  # drawn grey: seen (a mask that kept the occluder)
            assert float(out[row][:, changed].std()) < 1e-6 and float(out[row][:, changed].min()) >= 0.15
            kinds.add("drawn")
        else:                                    # cut out: 0 and not seen
            assert float(out[row][:, changed].abs().max()) == 0.0
            assert bool((visibility[row][0][changed] == 0).all()) and float(visibility[row].max()) == 1.0
            kinds.add("cut")
    assert kinds == {"drawn", "cut"}  # by turns
    # the recognizer's option: a share of the copies (0: whole copies, the default)
    assert stub_recognizer().verify_occluded_copies == 0.0
    assert stub_recognizer(verify_occluded_copies=0.125).verify_occluded_copies == 0.125
    with pytest.raises(MatlError, match="verify_occluded_copies"):
        stub_recognizer(verify_occluded_copies=1.5)
    # the second look (verify_occluder_margin) changes the samples of partly hidden copies alone: it is in the key then
    key = {(share, margin): stub_recognizer(verify_occluded_copies=share,
                                            verify_occluder_margin=margin).calibration_key()
           for share in (0.0, 0.5) for margin in (0, 3)}
    assert key[0.0, 0] == key[0.0, 3] and key[0.5, 0] != key[0.5, 3]
