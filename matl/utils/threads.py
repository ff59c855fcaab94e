"""Per-crop work of a batch spread over threads: the OpenCV, onnxruntime and numba calls of a query's foreground,
retries, refinement, keypoints and flow release the GIL, so a frame's crops use every core torch is allowed
(``torch.get_num_threads()``).

The pools are kept (one per worker count): their threads, and the per-thread OpenCV objects the pose stages keep
(:class:`~matl.inference.stage_settings.StageSettings`), live from one call to the next; a forked child starts its own.
A call made from inside a pool's thread runs its items in that thread, one after another (no nested pools, no
deadlock).
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable, Iterable
from concurrent.futures import ThreadPoolExecutor
from typing import Any, TypeVar

import torch

__all__ = ["thread_map"]

T = TypeVar("T")

_pools: dict[int, ThreadPoolExecutor] = {}
_lock = threading.Lock()
_inside = threading.local()
os.register_at_fork(after_in_child=_pools.clear)  # a forked child has the pools but not their threads


def _mark_inside() -> None:
    _inside.pool = True


def _pool(workers: int) -> ThreadPoolExecutor:
    with _lock:
        if workers not in _pools:
            _pools[workers] = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="matl",
                                                 initializer=_mark_inside)
        return _pools[workers]


def thread_map(fn: Callable[[Any], T], items: Iterable[Any], workers: int | None = None) -> list[T]:
    """``[fn(x) for x in items]``, the items spread over up to ``workers`` threads (None: torch's thread count);
    the results in the items' order, the first exception raised as the loop would. One item, one worker or a call
    from a pool thread: the plain loop."""
    items = list(items)
    workers = torch.get_num_threads() if workers is None else int(workers)
    if min(workers, len(items)) <= 1 or getattr(_inside, "pool", False):
        return [fn(x) for x in items]
    return list(_pool(workers).map(fn, items))  # one pool per thread count, whatever the batch's size
