"""matl.utils.threads: a batch's per-crop work over threads, in order, errors as the loop raises them."""

from __future__ import annotations

import os
import signal
import threading

import pytest

from matl.utils.threads import thread_map


def test_results_come_in_the_items_order_from_several_threads() -> None:
    seen: set[str] = set()
    barrier = threading.Barrier(2, timeout=10)

    def square(x: int) -> int:
        if x < 2:  # the first two items meet: they run at once, in two threads
            barrier.wait()
        seen.add(threading.current_thread().name)
        return x * x

    assert thread_map(square, range(6), workers=2) == [0, 1, 4, 9, 16, 25]
    assert len(seen) == 2


def test_one_worker_or_one_item_is_the_plain_loop() -> None:
    here = threading.current_thread().name
    assert thread_map(lambda x: threading.current_thread().name, [1, 2, 3], workers=1) == [here] * 3
    assert thread_map(lambda x: threading.current_thread().name, [1], workers=4) == [here]
    assert thread_map(lambda x: x, [], workers=4) == []


def test_a_call_from_a_pool_thread_runs_its_items_in_that_thread() -> None:
    def inner(x: int) -> list[str]:
        outer = threading.current_thread().name
        names = thread_map(lambda y: threading.current_thread().name, range(3), workers=2)
        return [name == outer for name in names]

    assert thread_map(inner, range(4), workers=2) == [[True] * 3] * 4


def test_the_first_error_is_raised() -> None:
    def fail_at_two(x: int) -> int:
        if x == 2:
            raise ValueError("two")
        return x

    with pytest.raises(ValueError, match="two"):
        thread_map(fail_at_two, range(5), workers=2)


@pytest.mark.skipif(not hasattr(os, "fork"), reason="fork is POSIX")
def test_a_forked_child_makes_its_own_pool() -> None:
    assert thread_map(lambda x: x + 1, range(4), workers=2) == [1, 2, 3, 4]  # the parent's pool exists
    pid = os.fork()
    if pid == 0:  # the child: the inherited pool has no threads; a hang ends by the alarm
        signal.alarm(20)
        os._exit(0 if thread_map(lambda x: x * 2, range(4), workers=2) == [0, 2, 4, 6] else 1)
    _, status = os.waitpid(pid, 0)
    assert os.waitstatus_to_exitcode(status) == 0
