"""matl.utils.timing: the interleaved single-query timing of several methods."""

from __future__ import annotations

import math

import torch

from matl.utils.timing import interleaved_query_ms


def test_interleaved_methods_take_turns_on_every_query_in_a_rotating_order() -> None:
    calls: list[tuple[str, float, int]] = []

    def method(name: str):
        def predict(x: torch.Tensor) -> None:
            calls.append((name, float(x[0, 0, 0, 0]), torch.get_num_threads()))
        return predict

    queries = torch.arange(5, dtype=torch.float32).view(5, 1, 1, 1).expand(5, 3, 2, 2)
    threads = torch.get_num_threads()
    out = interleaved_query_ms({"a": (method("a"), 1), "b": (method("b"), None), "c": (method("c"), None)}, queries,
                               warmup=2)
    assert set(out) == {"a", "b", "c"} and all(math.isfinite(ms) and ms >= 0 for ms in out.values())
    # every query answered by each method once, one query at a time, the first method rotating
    assert [(name, q) for name, q, _ in calls] == [
        ("a", 0), ("b", 0), ("c", 0), ("b", 1), ("c", 1), ("a", 1), ("c", 2), ("a", 2), ("b", 2),
        ("a", 3), ("b", 3), ("c", 3), ("b", 4), ("c", 4), ("a", 4)]
    # each method at its own torch thread count, restored after
    assert all(n == 1 for name, _, n in calls if name == "a") and torch.get_num_threads() == threads
    assert math.isnan(interleaved_query_ms({"a": (method("a"), None)}, queries, warmup=5)["a"])
