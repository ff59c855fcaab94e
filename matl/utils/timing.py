"""Timing helpers shared by train, eval and bench: thread counts, single-query and batched query timings, methods
alternating in rounds, and :class:`StageTimer`, the per-stage milliseconds of a call that the timed code fills."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager, contextmanager, nullcontext
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


def _single_query_ms(predict: Callable[[torch.Tensor], Any], queries: torch.Tensor, warmup: int,
                     after: Callable[[bool], None] | None = None) -> list[float]:
    """Milliseconds of each ``predict`` call on one query at a time, the first ``warmup`` calls left out;
    ``after(timed)`` runs after each call, outside the timed region."""
    times = []
    for i in range(len(queries)):
        start = time.perf_counter()
        predict(queries[i:i + 1])
        elapsed = (time.perf_counter() - start) * 1000.0
        if i >= warmup:
            times.append(elapsed)
        if after is not None:
            after(i >= warmup)
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
    times: dict[str, list[float]] = {name: [] for name in methods}
    for name in _rounds(list(methods), rounds):
        predict, threads = methods[name]
        with compute_threads(threads):
            times[name] += _single_query_ms(predict, queries, warmup)
    return {name: _median(t) for name, t in times.items()}


def _rounds(names: list[str], rounds: int) -> Iterator[str]:
    """The methods' turns over ``rounds`` rounds: each round every method once, the first rotating by one."""
    for r in range(int(rounds)):
        turn = r % len(names)
        yield from names[turn:] + names[:turn]


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
    _check_batches(queries, batch, warmup)
    with compute_threads(threads):
        total, timed = _batch_pass(predict, queries, batch, warmup)
    return total * 1000.0 / timed


def _check_batches(queries: torch.Tensor, batch: int, warmup: int) -> None:
    if batch < 1 or len(queries) < (warmup + 1) * batch:
        raise ValueError(f"{len(queries)} queries do not make {warmup + 1} batches of {batch}")


def _batch_pass(predict: Callable[[torch.Tensor], Any], queries: torch.Tensor, batch: int, warmup: int
                ) -> tuple[float, int]:
    """One pass over consecutive whole batches: seconds of the timed batches (after ``warmup``) and their queries."""
    total, timed = 0.0, 0
    for k, first in enumerate(range(0, len(queries) - batch + 1, batch)):
        start = time.perf_counter()
        predict(queries[first:first + batch])
        if k >= warmup:
            total += time.perf_counter() - start
            timed += batch
    return total, timed


@torch.no_grad()
def alternating_batch_query_ms(methods: dict[str, tuple[Callable[[torch.Tensor], Any], int | None]],
                               queries: torch.Tensor, batch: int, warmup: int = 1, rounds: int = 3
                               ) -> dict[str, float]:
    """:func:`batch_query_ms` of each method, the methods alternating in ``rounds`` rounds as in
    :func:`alternating_query_ms` (each round one pass per method over the batches, the order rotating): milliseconds
    per query, the wall clock of every timed batch of every round over their queries (a throughput).

    Args:
        methods: name -> ``(predict, threads)``, ``predict`` called on ``(batch, ...)`` slices of ``queries``.
        queries: ``(Q, ...)``, ``Q >= (warmup + 1) * batch``; a last partial batch is left out.
        batch: queries per call; warmup: first batches of each pass run untimed.
    """
    _check_batches(queries, batch, warmup)
    totals = {name: [0.0, 0] for name in methods}
    for name in _rounds(list(methods), rounds):
        predict, threads = methods[name]
        with compute_threads(threads):
            total, timed = _batch_pass(predict, queries, batch, warmup)
        totals[name][0] += total
        totals[name][1] += timed
    return {name: total * 1000.0 / timed if timed else float("nan") for name, (total, timed) in totals.items()}


def synced(fn: Callable[[torch.Tensor], Any], device: torch.device) -> Callable[[torch.Tensor], Any]:
    """``fn`` followed by a device sync on a GPU, so its timings include the work and not just its launch."""
    if device.type != "cuda":
        return fn

    def call(x: torch.Tensor) -> Any:
        out = fn(x)
        torch.cuda.synchronize(device)
        return out
    return call


# ------------------------------------------------------------------------------------------ stages
class StageTimer:
    """Wall-clock milliseconds of the named stages of a call, filled by the code timed (``with timer.stage(name)``,
    or a callable replaced by :meth:`wrap`); :meth:`take` hands them over and starts afresh.

    Stages do not overlap: a stage entered while another is open counts in the open one (so the stages of a call
    add up to at most its wall clock) and is recorded beside it in ``within[outer][inner]`` (one level deep), e.g.
    the networks that a verification runs count as verification, and ``within["verification"]["networks"]`` says
    how much of it they were. ``calls`` counts entries, ``"name"`` or ``"outer/inner"``.
    """

    def __init__(self) -> None:
        self.ms: dict[str, float] = {}
        self.within: dict[str, dict[str, float]] = {}
        self.calls: dict[str, int] = {}
        self._open: list[str] = []
        self._wrapped: list[tuple[Any, str, bool, Any]] = []

    @contextmanager
    def stage(self, name: str) -> Iterator[None]:
        """Time the block as stage ``name`` (see the class docstring)."""
        self._open.append(name)
        start = time.perf_counter()
        try:
            yield
        finally:
            self._record(name, (time.perf_counter() - start) * 1000.0)

    def _record(self, name: str, ms: float) -> None:
        self._open.pop()
        depth = len(self._open)
        if depth == 0:
            self.ms[name] = self.ms.get(name, 0.0) + ms
            key = name
        elif depth == 1:
            inner = self.within.setdefault(self._open[0], {})
            inner[name] = inner.get(name, 0.0) + ms
            key = f"{self._open[0]}/{name}"
        else:  # deeper: in its parent's time only
            return
        self.calls[key] = self.calls.get(key, 0) + 1

    def take(self) -> dict[str, Any]:
        """``{"ms", "within", "calls"}`` recorded since the last take; the timer starts afresh."""
        taken = {"ms": self.ms, "within": self.within, "calls": self.calls}
        self.ms, self.within, self.calls = {}, {}, {}
        return taken

    def wrap(self, owner: Any, attr: str, name: str) -> None:
        """Time every call of ``owner.<attr>`` (a method or a callable object) as stage ``name``, until
        :meth:`unwrap`; attribute reads go through to the callable (a wrapped object keeps its settings)."""
        had = attr in vars(owner)
        target = getattr(owner, attr)
        setattr(owner, attr, _TimedCall(target, self, name))
        self._wrapped.append((owner, attr, had, target))

    def unwrap(self) -> None:
        """Undo every :meth:`wrap`, last first."""
        while self._wrapped:
            owner, attr, had, target = self._wrapped.pop()
            if had:
                setattr(owner, attr, target)
            else:
                delattr(owner, attr)


class _TimedCall:
    """A callable timed as a stage of a :class:`StageTimer`; other attributes are the wrapped callable's."""

    def __init__(self, target: Any, timer: StageTimer, name: str) -> None:
        self._target, self._timer, self._name = target, timer, name

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        with self._timer.stage(self._name):
            return self._target(*args, **kwargs)

    def __getattr__(self, name: str) -> Any:
        if name.startswith("_"):
            raise AttributeError(name)
        return getattr(self._target, name)


_NO_STAGE = nullcontext()


def stage(timer: StageTimer | None, name: str) -> AbstractContextManager[Any]:
    """``timer.stage(name)``, or a shared no-op context when ``timer`` is None: what a stage hook costs when off."""
    return _NO_STAGE if timer is None else timer.stage(name)


@torch.no_grad()
def stage_query_ms(predict: Callable[[torch.Tensor], Any], queries: torch.Tensor, timer: StageTimer,
                   warmup: int = 5, threads: int | None = None) -> dict[str, Any]:
    """Where single-query calls spend their milliseconds: ``predict`` on one query at a time (as
    :func:`median_query_ms`), ``timer`` filled by the code it runs; means per timed query.

    Returns:
        ``call_ms`` (the mean wall clock of a call) and ``call_ms_median``; ``stages_ms``: each stage's mean
        milliseconds per query (a stage a call did not enter counts 0) plus ``other`` (``call_ms`` minus the stages:
        whatever ran outside them), so ``stages_ms`` adds up to ``call_ms``; ``within_ms``: the nested stages'
        means (``{outer: {inner: ms}}``); ``calls_per_query``: the entries of each stage per query; ``per_call``: each
        timed call's ``{"ms", "stages"}`` (its wall clock and the stages it entered), in call order.
    """
    records: list[dict[str, Any]] = []

    def after(timed: bool) -> None:
        record = timer.take()
        if timed:
            records.append(record)

    with compute_threads(threads):
        timer.take()
        times = _single_query_ms(predict, queries, warmup, after)
    n = max(len(times), 1)
    stages: dict[str, float] = {}
    within: dict[str, dict[str, float]] = {}
    calls: dict[str, float] = {}
    for record in records:
        for name, ms in record["ms"].items():
            stages[name] = stages.get(name, 0.0) + ms / n
        for outer, inner in record["within"].items():
            mean = within.setdefault(outer, {})
            for name, ms in inner.items():
                mean[name] = mean.get(name, 0.0) + ms / n
        for key, count in record["calls"].items():
            calls[key] = calls.get(key, 0.0) + count / n
    call_ms = sum(times) / n if times else float("nan")
    stages["other"] = call_ms - sum(stages.values())
    return {"call_ms": call_ms, "call_ms_median": _median(times), "stages_ms": stages, "within_ms": within,
            "calls_per_query": calls,
            "per_call": [{"ms": ms, "stages": record["ms"]} for ms, record in zip(times, records, strict=True)]}


@torch.no_grad()
def measure_query_ms(model, datamodule, num_queries: int = 50, warmup: int = 5) -> float:
    """Median milliseconds of MATL inference on one query (batch of 1), gallery features in memory."""
    recognizer = model.build_recognizer(datamodule.gallery)
    batch = datamodule.materialize({k: v[: num_queries + warmup] for k, v in datamodule.test_set.params.items()})
    return median_query_ms(recognizer, batch["query"].to(model.device), warmup)
