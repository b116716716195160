"""core/threads.py: independent solves two at a time."""
from __future__ import annotations

import threading

import numpy as np
import pytest

from nrsfm_ros.core.threads import map_threads


def test_map_threads_keeps_order_and_uses_two_threads():
    seen: set[int] = set()
    barrier = threading.Barrier(2, timeout=10)

    def fn(x: int) -> int:
        seen.add(threading.get_ident())
        if x < 2:
            barrier.wait()        # both first calls at once: two threads, or this times out
        return x * x
    assert map_threads(fn, list(range(5))) == [0, 1, 4, 9, 16]
    assert len(seen) == 2
    assert map_threads(fn, [3]) == [9]            # one item: this thread


def test_map_threads_raises_what_a_call_raises():
    def fn(x: int) -> int:
        if x == 2:
            raise ValueError('bad item 2')
        return x
    with pytest.raises(ValueError, match='bad item 2'):
        map_threads(fn, [0, 1, 2, 3])


def test_blas_is_one_thread_inside_and_restored_after():
    threadpoolctl = pytest.importorskip('threadpoolctl')
    np.ones((4, 4)) @ np.ones((4, 4))              # numpy's BLAS loaded
    before = [i['num_threads'] for i in threadpoolctl.threadpool_info()
              if i['user_api'] == 'blas']
    inside = map_threads(lambda _: [i['num_threads'] for i in threadpoolctl.threadpool_info()
                                    if i['user_api'] == 'blas'], [0, 1])
    after = [i['num_threads'] for i in threadpoolctl.threadpool_info()
             if i['user_api'] == 'blas']
    assert before and all(n == 1 for call in inside for n in call)
    assert after == before


def test_set_workers_one_runs_serially_and_a_fleet_worker_takes_its_threads():
    import cv2

    from nrsfm_ros.core import threads
    from nrsfm_ros.fleet import _init_worker
    saved, cv_threads = threads.WORKERS, cv2.getNumThreads()
    try:
        _init_worker(1)                 # a fleet worker with one thread
        assert threads.WORKERS == 1
        seen: set[int] = set()
        assert map_threads(lambda x: seen.add(threading.get_ident()) or x, [1, 2, 3]) == \
            [1, 2, 3]
        assert seen == {threading.get_ident()}
        with pytest.raises(ValueError, match='workers'):
            threads.set_workers(0)
    finally:
        threads.set_workers(saved)
        cv2.setNumThreads(cv_threads)


def test_overlapping_callers_leave_blas_as_it_was():
    """Two map_threads calls from two threads, overlapping and leaving in the other order: BLAS
    stays at one thread while either runs and gets its own count back after both."""
    threadpoolctl = pytest.importorskip('threadpoolctl')
    np.ones((4, 4)) @ np.ones((4, 4))

    def blas() -> list[int]:
        return [i['num_threads'] for i in threadpoolctl.threadpool_info()
                if i['user_api'] == 'blas']
    before = blas()
    first_in, second_in, first_may_leave = (threading.Event() for _ in range(3))
    seen: dict[str, list[int]] = {}

    def first(_):
        first_in.set()
        first_may_leave.wait(10)
        return None

    def second(_):
        second_in.set()
        first_may_leave.set()            # the first caller leaves while this one is inside
        return None

    def run_first():
        map_threads(first, [0, 1])

    t = threading.Thread(target=run_first)
    t.start()
    first_in.wait(10)
    seen['first running'] = blas()
    map_threads(lambda x: second(x) if x == 0 else (second_in.wait(10), t.join(10),
                                                     seen.setdefault('first gone', blas())),
                [0, 1])
    t.join(10)
    assert all(n == 1 for n in seen['first running'] + seen['first gone'])
    assert blas() == before
