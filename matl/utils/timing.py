"""Timing helpers shared by train, eval and bench."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

import torch


@contextmanager
def torch_threads(threads: int | None) -> Iterator[None]:
    """``torch.set_num_threads(threads)`` inside the block, the previous count restored after (None: unchanged)."""
    previous = torch.get_num_threads()
    if threads is not None and threads != previous:
        torch.set_num_threads(int(threads))
    try:
        yield
    finally:
        if torch.get_num_threads() != previous:
            torch.set_num_threads(previous)


@contextmanager
def opencv_threads(threads: int | None) -> Iterator[None]:
    """``cv2.setNumThreads(threads)`` inside the block, the previous count restored after (None: unchanged)."""
    try:
        import cv2
    except ImportError:
        cv2 = None
    previous = cv2.getNumThreads() if cv2 is not None and threads is not None else None
    if previous is not None and threads != previous:
        cv2.setNumThreads(int(threads))
    try:
        yield
    finally:
        if previous is not None and cv2.getNumThreads() != previous:
            cv2.setNumThreads(previous)


@contextmanager
def compute_threads(threads: int | None) -> Iterator[None]:
    """A method's thread count: torch's intra-op threads and OpenCV's alike inside the block (None: unchanged).
    MATL's query path and the keypoint baselines both run OpenCV (warps, SIFT), so a count timed is both."""
    with torch_threads(threads), opencv_threads(threads):
        yield


@torch.no_grad()
def median_query_ms(predict: Callable[[torch.Tensor], Any], queries: torch.Tensor, warmup: int = 5,
                    threads: int | None = None) -> float:
    """Median milliseconds of ``predict`` on one query at a time (docs/design.md ``query_ms``: batch of 1).

    The timed region is the ``predict`` call alone (wall clock), the same for every method.

    Args:
        predict: anything answering a ``(1, 3, H, W)`` batch (a recognizer with its gallery in memory,
            or a keypoint baseline adapter), so models and baselines are timed the same way.
        queries: ``(Q, 3, H, W)``; the first ``warmup`` are run untimed (lazy initialisation: the
            recognizer compiles its query graph at its first call; caches).
        threads: torch's and OpenCV's threads during the measurement (None: leave them; :func:`compute_threads`).
            One query is a few small operations: on a small CPU shared with other work one thread is both faster
            and far steadier than several, whose every operation waits for the slowest core (docs/speed.md).
    """
    with compute_threads(threads):
        return _median(_single_query_ms(predict, queries, warmup))


def _single_query_ms(predict: Callable[[torch.Tensor], Any], queries: torch.Tensor, warmup: int) -> list[float]:
    """Milliseconds of each ``predict`` call on one query at a time, the first ``warmup`` calls left out."""
    times = []
    for i in range(len(queries)):
        start = time.perf_counter()
        predict(queries[i:i + 1])
        if i >= warmup:
            times.append((time.perf_counter() - start) * 1000.0)
    return times


def _median(times: list[float]) -> float:
    return float(torch.tensor(times).median()) if times else float("nan")


@torch.no_grad()
def alternating_query_ms(methods: dict[str, tuple[Callable[[torch.Tensor], Any], int | None]], queries: torch.Tensor,
                         warmup: int = 5, rounds: int = 3) -> dict[str, float]:
    """Median milliseconds of each method on one query at a time, the methods alternating in rounds.

    :func:`median_query_ms` times one method, then the next: on a shared machine whose speed drifts over tens of
    seconds, two methods timed a minute apart can be slowed differently. Here each of ``rounds`` rounds times every
    method on all the queries (the first ``warmup`` untimed), the methods' order rotating from round to round, and
    each method's median is over all its rounds: a slow phase falls on every method alike, so their ratio holds.
    A method keeps the machine for a whole pass over the queries (its caches its own, as in use); taking turns
    query by query would time each method right after another's working set.

    Args:
        methods: name -> ``(predict, threads)``: the callable (as for :func:`median_query_ms`) and the thread
            count during its calls, torch's and OpenCV's (:func:`compute_threads`; None: leave them).
        queries: ``(Q, 3, H, W)``.
    Returns:
        name -> median milliseconds.
    """
    names = list(methods)
    times: dict[str, list[float]] = {name: [] for name in names}
    for r in range(int(rounds)):
        turn = r % len(names)
        for name in names[turn:] + names[:turn]:
            predict, threads = methods[name]
            with compute_threads(threads):
                times[name] += _single_query_ms(predict, queries, warmup)
    return {name: _median(t) for name, t in times.items()}


@torch.no_grad()
def batch_query_ms(predict: Callable[[torch.Tensor], Any], queries: torch.Tensor, batch: int,
                   warmup: int = 1, threads: int | None = None) -> float:
    """Milliseconds *per query* of ``predict`` on consecutive batches of ``batch`` queries (the crops of one
    camera frame answered in one call): the wall clock of every timed batch together divided by the queries in
    them, i.e. the throughput of a stream of frames (a slow query counts in full, as it delays its frame).

    Args:
        predict: as :func:`median_query_ms`'s, called on ``(batch, 3, H, W)``.
        queries: ``(Q, 3, H, W)``, ``Q >= (warmup + 1) * batch``; a last partial batch is left out.
        batch: queries per call (>= 1).
        warmup: first batches run untimed.
        threads: torch's and OpenCV's threads during the measurement (:func:`compute_threads`; None: leave them).
    """
    if batch < 1 or len(queries) < (warmup + 1) * batch:
        raise ValueError(f"{len(queries)} queries do not make {warmup + 1} batches of {batch}")
    total, timed = 0.0, 0
    with compute_threads(threads):
        for k, first in enumerate(range(0, len(queries) - batch + 1, batch)):
            start = time.perf_counter()
            predict(queries[first:first + batch])
            if k >= warmup:
                total += time.perf_counter() - start
                timed += batch
    return total * 1000.0 / timed


@torch.no_grad()
def measure_query_ms(model, datamodule, num_queries: int = 50, warmup: int = 5) -> float:
    """Median milliseconds of MATL inference on one query (batch of 1), gallery features in memory."""
    recognizer = model.build_recognizer(datamodule.gallery)
    batch = datamodule.materialize({k: v[: num_queries + warmup] for k, v in datamodule.test_set.params.items()})
    return median_query_ms(recognizer, batch["query"].to(model.device), warmup)
