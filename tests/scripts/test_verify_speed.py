"""scripts/verify_speed.py: both paths give the same distances, the reference is restored, one JSON line a batch."""

from __future__ import annotations

import json
import sys

import pytest

from matl.inference import verify
from tests.scripts.conftest import load_script


def test_the_two_paths_agree_and_the_module_is_restored(monkeypatch: pytest.MonkeyPatch,
                                                        capsys: pytest.CaptureFixture) -> None:
    script = load_script("verify_speed")
    queries, poses, anchors, _ = script.cases(2)
    assert queries.shape == anchors.shape == (2, 3, script.S, script.S) and poses.shape == (2, 3, 3)
    blur = verify.gaussian_blur
    with script.torch_reference():
        assert verify.gaussian_blur is verify._gaussian_blur_torch
    assert verify.gaussian_blur is blur
    monkeypatch.setattr(sys, "argv", ["verify_speed.py", "--rounds", "2", "--batches", "1", "2"])
    script.main()
    lines = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert [line["batch"] for line in lines] == [1, 2]
    assert all(line["max_difference"] < 1e-6 and line["ms"]["cpu_path"] > 0 for line in lines)
