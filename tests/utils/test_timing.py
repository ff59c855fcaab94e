"""matl.utils.timing: several methods timed in alternating rounds, batches, and the stages of a call."""

from __future__ import annotations

import math

import cv2
import pytest
import torch

from matl.utils.timing import (
    StageTimer,
    alternating_batch_query_ms,
    alternating_query_ms,
    compute_threads,
    stage,
    stage_query_ms,
)


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


# ------------------------------------------------------------------------------------------ stages
def test_stage_timer_nested_stages_count_in_the_open_one_and_are_recorded_beside_it() -> None:
    timer = StageTimer()
    with timer.stage("a"):
        with timer.stage("b"), timer.stage("c"):  # two levels down: in b's time only
            pass
        with timer.stage("b"):
            pass
    with timer.stage("b"):
        pass
    taken = timer.take()
    assert set(taken["ms"]) == {"a", "b"} and all(ms >= 0 for ms in taken["ms"].values())
    assert set(taken["within"]) == {"a"} and set(taken["within"]["a"]) == {"b"}
    assert taken["within"]["a"]["b"] <= taken["ms"]["a"]
    assert taken["calls"] == {"a": 1, "a/b": 2, "b": 1}
    assert timer.take() == {"ms": {}, "within": {}, "calls": {}}  # taken: the timer starts afresh
    with pytest.raises(ValueError, match="inside"), timer.stage("a"):
        raise ValueError("inside")  # an error in a stage propagates, and the stage is still closed
    with timer.stage("d"):
        pass
    assert timer.take()["calls"] == {"a": 1, "d": 1}


def test_stage_timer_wraps_callables_and_unwrap_restores_them() -> None:
    class Thing:
        level = 3

        def work(self, x: int) -> int:
            return x + 1

    thing, refiner = Thing(), Thing()
    holder = type("Holder", (), {})()
    holder.refiner = refiner
    timer = StageTimer()
    timer.wrap(thing, "work", "networks")
    timer.wrap(holder, "refiner", "refinement")  # an object held in an attribute: its settings still read
    assert thing.work(1) == 2 and holder.refiner.level == 3 and holder.refiner.work(2) == 3
    assert timer.take()["calls"] == {"networks": 1}
    timer.unwrap()
    assert "work" not in vars(thing) and holder.refiner is refiner
    thing.work(1)
    assert timer.take()["calls"] == {}


def test_stage_hook_without_a_timer_is_a_shared_no_op() -> None:
    assert stage(None, "a") is stage(None, "b")
    with stage(None, "a"):
        pass
    timer = StageTimer()
    with stage(timer, "a"):
        pass
    assert timer.take()["calls"] == {"a": 1}


def test_stage_query_ms_means_per_query_add_up_to_the_call() -> None:
    timer = StageTimer()

    def predict(x: torch.Tensor) -> None:
        with timer.stage("first"):
            sum(range(2000))
        if int(x[0]) % 2:
            with timer.stage("second"):
                sum(range(2000))
        sum(range(500))  # outside every stage: other

    out = stage_query_ms(predict, torch.arange(5), timer, warmup=1, threads=1)
    stages = out["stages_ms"]
    assert set(stages) == {"first", "second", "other"} and all(ms > 0 for ms in stages.values())
    assert math.isclose(sum(stages.values()), out["call_ms"], rel_tol=1e-9)
    assert out["calls_per_query"] == {"first": 1.0, "second": 0.5}  # queries 1..4 timed, 1 and 3 odd
    assert out["call_ms_median"] > 0 and out["within_ms"] == {}
    calls = out["per_call"]  # the timed calls one by one: queries 1..4, "second" in the odd ones
    assert [set(c["stages"]) for c in calls] == [{"first", "second"}, {"first"}, {"first", "second"}, {"first"}]
    assert math.isclose(sum(c["ms"] for c in calls) / 4, out["call_ms"], rel_tol=1e-9)
    assert all(sum(c["stages"].values()) <= c["ms"] for c in calls)


def test_alternating_batches_rotate_and_time_whole_batches() -> None:
    calls: list[tuple[str, int]] = []

    def method(name: str):
        return lambda x: calls.append((name, len(x)))

    queries = torch.zeros(7, 3)
    out = alternating_batch_query_ms({"a": (method("a"), 1), "b": (method("b"), None)}, queries, batch=3, warmup=1,
                                     rounds=2)
    assert set(out) == {"a", "b"} and all(ms >= 0 for ms in out.values())
    assert calls == [("a", 3)] * 2 + [("b", 3)] * 2 + [("b", 3)] * 2 + [("a", 3)] * 2  # the partial batch left out
    with pytest.raises(ValueError, match="do not make 3 batches of 3"):
        alternating_batch_query_ms({"a": (method("a"), None)}, queries, batch=3, warmup=2)
