"""matl.utils.timing: several methods timed in alternating rounds."""

from __future__ import annotations

import math

import cv2
import torch

from matl.utils.timing import alternating_query_ms, compute_threads


def test_methods_alternate_in_rounds_each_a_whole_pass_over_the_queries() -> None:
    calls: list[tuple[str, int, int]] = []

    def method(name: str):
        def predict(x: torch.Tensor) -> None:
            calls.append((name, int(x[0, 0, 0, 0]), torch.get_num_threads(), cv2.getNumThreads()))
        return predict

    queries = torch.arange(3, dtype=torch.float32).view(3, 1, 1, 1).expand(3, 3, 2, 2)
    threads, opencv = torch.get_num_threads(), cv2.getNumThreads()
    out = alternating_query_ms({"a": (method("a"), 1), "b": (method("b"), None)}, queries, warmup=1, rounds=3)
    assert set(out) == {"a", "b"} and all(math.isfinite(ms) and ms >= 0 for ms in out.values())
    # each round one pass per method over every query, the first method rotating from round to round
    order = [name for name, *_ in calls]
    assert order == ["a"] * 3 + ["b"] * 3 + ["b"] * 3 + ["a"] * 3 + ["a"] * 3 + ["b"] * 3
    assert [q for _, q, *_ in calls] == [0, 1, 2] * 6
    # each method at its own thread count, torch's and OpenCV's alike, both restored after
    assert all(n == cv == 1 for name, _, n, cv in calls if name == "a")
    assert torch.get_num_threads() == threads and cv2.getNumThreads() == opencv
    assert math.isnan(alternating_query_ms({"a": (method("a"), None)}, queries, warmup=3)["a"])


def test_compute_threads_sets_torch_and_opencv_and_none_leaves_them() -> None:
    threads, opencv = torch.get_num_threads(), cv2.getNumThreads()
    with compute_threads(1):
        assert torch.get_num_threads() == 1 and cv2.getNumThreads() == 1
    assert torch.get_num_threads() == threads and cv2.getNumThreads() == opencv
    with compute_threads(None):
        assert torch.get_num_threads() == threads and cv2.getNumThreads() == opencv
