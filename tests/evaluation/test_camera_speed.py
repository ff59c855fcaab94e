"""matl.bench's camera crops (query_ms_camera): crops as a camera delivers them, their options, and where a public
call's milliseconds go (matl.Recognizer.time_stages), on a tiny in-memory catalog."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch
from omegaconf import DictConfig

from matl.evaluation.camera_speed import (
    KINDS,
    STAGES,
    _matl_call,
    camera_options,
    crop_kinds,
    decode_crops,
    make_crops,
    measure_stages,
)
from matl.evaluation.conditions import sample_poses, warp_planes
from matl.evaluation.speed import bench_options
from matl.geometry import HomographySampler
from matl.utils.errors import MatlError
from tests.conftest import compose_config
from tests.evaluation.test_unseen import tiny_set


def _camera(*overrides: str) -> DictConfig:
    """``bench.camera`` with ``overrides``, checked (one warm-up call, no batches: a few crops are enough)."""
    return bench_options(compose_config("bench", ["bench.query_warmup=1", "bench.batch=0", *overrides])).camera


def test_crop_kinds_follow_the_mix_exactly_in_a_seeded_order() -> None:
    kinds = crop_kinds({"background": 1, "clutter": 2, "occluded": 1}, 10, 3)
    assert [kinds.count(k) for k in KINDS] == [3, 5, 2]  # 2.5 / 5 / 2.5: the largest remainders first
    assert kinds == crop_kinds({"background": 1, "clutter": 2, "occluded": 1}, 10, 3)
    assert kinds != crop_kinds({"background": 1, "clutter": 2, "occluded": 1}, 10, 4)
    assert crop_kinds({"clutter": 1}, 4, 0) == ["clutter"] * 4


def test_crops_are_rgb_scenes_without_a_mask_decoded_once() -> None:
    cs = tiny_set()
    camera = _camera("bench.camera.crops=6", "bench.camera.photometric=0.5")
    crops = make_crops(cs, HomographySampler(), camera)
    assert len(crops) == 6 and sum(c.photometric for c in crops) == 3
    assert sum(c.kind == "clutter" for c in crops) == 3 and {c.object for c in crops} <= set(cs.object_names)
    for crop in crops:  # JPEG through the camera model, PNG otherwise
        assert crop.data[:3] == b"\xff\xd8\xff" if crop.photometric else crop.data[:8] == b"\x89PNG\r\n\x1a\n"
    assert [c.data for c in make_crops(cs, HomographySampler(), camera)] == [c.data for c in crops]  # seeded
    images, ms = decode_crops(crops)
    assert images.shape == (6, cs.image_size, cs.image_size, 3) and images.dtype == np.uint8 and len(ms) == 6
    # a real background all round: no crop's border is black (the model's convention a mask would give)
    border = np.concatenate([images[:, 0], images[:, -1], images[:, :, 0], images[:, :, -1]], axis=1)
    assert (border.max(-1) > 0).mean(1).min() > 0.9


def test_occluded_crops_hide_part_of_the_product() -> None:
    cs = tiny_set()
    common = ["bench.camera.crops=4", "bench.camera.photometric=0", "bench.camera.seed=5"]
    only = ["bench.camera.mix.background=0", "bench.camera.mix.clutter={}", "bench.camera.mix.occluded={}"]
    clutter = make_crops(cs, HomographySampler(), _camera(*common, only[0], only[1].format(1), only[2].format(0)))
    occluded = make_crops(cs, HomographySampler(), _camera(*common, only[0], only[1].format(0), only[2].format(1)))
    assert {c.kind for c in occluded} == {"occluded"}
    plane, H = sample_poses(cs, HomographySampler(), 4, 5)
    _, masks = warp_planes(cs, plane, H)
    (before, _), (after, _) = decode_crops(clutter), decode_crops(occluded)
    changed = np.abs(before.astype(int) - after.astype(int)).max(-1) > 8  # the same scene, then the occluder
    for i in range(4):
        assert changed[i][masks[i] > 0.5].mean() > 0.03, i


@pytest.mark.parametrize(("overrides", "message"), [
    ("bench.camera.crops=-1", r"bench\.camera\.crops=-1 is invalid"),
    ("bench.camera.crops=3", r"bench\.camera\.crops=3 is smaller than bench\.query_warmup \+ 1 = 6"),
    ("bench.camera.crops=10", r"bench\.camera\.crops=10 does not make two batches of bench\.batch=8"),
    ("bench.camera.products=0", r"bench\.camera\.products=0 is invalid"),
    ("bench.camera.mix.background=0 bench.camera.mix.clutter=0 bench.camera.mix.occluded=0",
     r"bench\.camera\.mix=.* is invalid: use shares >= 0 \(not all 0\)"),
    ("+bench.camera.mix.shelf=1", r"bench\.camera\.mix=.*'shelf': 1.* is invalid"),
    ("bench.camera.photometric=1.5", r"bench\.camera\.photometric=1\.5 is invalid"),
    ("+bench.camera.occluders.kinds.hand=1", r"bench\.camera\.occluders: occluder kind 'hand' is unknown"),
])
def test_bad_camera_options_are_one_line_errors(overrides: str, message: str) -> None:
    with pytest.raises(MatlError, match=message):
        bench_options(compose_config("bench", overrides.split()))


def test_no_crops_needs_no_sizes() -> None:
    assert camera_options(bench_options(compose_config("bench", ["bench.camera.crops=0"]))).crops == 0


@pytest.fixture(scope="module")
def tiny_gallery(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from matl.evaluation.unseen import write_gallery

    folder = tmp_path_factory.mktemp("camera_gallery")
    write_gallery(tiny_set(), folder)
    return folder


@pytest.mark.parametrize("refine", [False, True])
def test_stages_of_a_public_call_add_up_and_cost_nothing_when_off(tiny_gallery: Path, refine: bool) -> None:
    from matl import Recognizer

    # closed set (threshold=None): the open-set calibration is a one-off of the gallery, not a stage of a call
    recognizer = Recognizer.pretrained(refine=refine, threshold=None).enrol(tiny_gallery, cache=False)
    crops = make_crops(tiny_set(), HomographySampler(), _camera("bench.camera.crops=5", "bench.camera.seed=9"))
    queries = torch.from_numpy(decode_crops(crops)[0])
    call = _matl_call(recognizer)
    untimed = call(queries)
    parts = measure_stages(recognizer, call, queries, warmup=1, threads=1, decode_ms=0.25)

    stages = parts["stages_ms"]
    assert list(stages) == ["decode", *STAGES, "other"] and stages["decode"] == 0.25
    assert math.isclose(sum(stages.values()), parts["total_ms"], rel_tol=1e-9)
    assert math.isclose(parts["total_ms"], 0.25 + parts["call_ms"], rel_tol=1e-9)
    for name in ("foreground", "framing", "networks", "search", "verification"):  # GrabCut on every RGB crop
        assert stages[name] > 0, name
    # the default model's alignment stage runs without refinement; refine=true skips it (refiner.start=stn) but for
    # answers that do not verify closely (refine_check=judge)
    assert (stages["refinement"] > 0) == refine and (refine or stages["alignment"] > 0)
    assert -0.05 * parts["call_ms"] <= stages["other"] < 0.5 * parts["call_ms"]  # the stages are most of a call
    assert 0.0 <= parts["retried_share"] <= 1.0 and parts["threads"] == 1
    # timing changes no answer, and once off it leaves nothing behind
    timed = call(queries)  # already off again: measure_stages stops the timer
    assert recognizer.stage_timer is None
    inner = recognizer._gallery_recognizer()
    assert "embed_queries" not in vars(inner) and "search" not in vars(inner.search)
    assert [(m.object, m.plane, m.anchor) for m in timed] == [(m.object, m.plane, m.anchor) for m in untimed]
    assert all(np.allclose(a.H, b.H) for a, b in zip(timed, untimed, strict=True) if a.H is not None)
