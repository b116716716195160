"""Independent solves two at a time in threads.

The batch solves' inner work is NumPy's large array passes, BLAS and serial ``nogil`` numba
kernels, all of which release the GIL: independent candidates (the planar refinement's starts,
the perspective correction's two reflections) then overlap on a second core.  No kernel of the
package uses numba's parallel loops, whose default threading layer forbids concurrent calls.
While they run, OpenBLAS is held to one thread (``threadpoolctl``, where installed): its own
threads on top of ours made the captured 320x240 flag batch slower than serial (1.9-2.3 s
against 1.75-2.05 s), one thread each 1.44-1.66 s."""
from __future__ import annotations

import contextlib
import threading
from collections.abc import Callable, Iterator, Sequence
from typing import Any, TypeVar

T = TypeVar('T')

WORKERS = 2     # threads at most: the machines this targets have 2 cores (set_workers)


def set_workers(n: int) -> None:
    """At most ``n`` threads for :func:`map_threads` in this process (1: serial), e.g. a
    fleet worker given one thread while other workers use the other cores."""
    global WORKERS
    if n < 1:
        raise ValueError(f'workers: expected >= 1, got {n}')
    WORKERS = int(n)


def map_threads(fn: Callable[[Any], T], items: Sequence[Any]) -> list[T]:
    """``[fn(x) for x in items]`` in that order, ``WORKERS`` at a time in threads where there
    are several items; an exception of any call is raised here, as the loop would."""
    if len(items) < 2 or WORKERS < 2:
        return [fn(x) for x in items]
    from concurrent.futures import ThreadPoolExecutor
    with _blas_single_thread(), ThreadPoolExecutor(max_workers=min(WORKERS, len(items))) as pool:
        return list(pool.map(fn, items))


_controller: list[Any] = []     # threadpoolctl's controller, made once (it scans the libraries)
_blas_lock = threading.Lock()
_blas_limit: list[Any] = []     # the limit in force while map_threads calls run (any thread)


@contextlib.contextmanager
def _blas_single_thread() -> Iterator[None]:
    """The BLAS libraries loaded so far held to one thread each while any caller is inside
    (nothing where threadpoolctl is not installed): the first entrant sets the limit, the
    last one out restores the original, so that calls from several threads overlapping in any
    order cannot leave BLAS at one thread."""
    try:
        from threadpoolctl import ThreadpoolController
    except ImportError:
        yield
        return
    with _blas_lock:
        if not _controller:
            _controller.append(ThreadpoolController())
        if not _blas_limit:
            _blas_limit.append([_controller[0].limit(limits=1, user_api='blas'), 0])
        _blas_limit[0][1] += 1
    try:
        yield
    finally:
        with _blas_lock:
            _blas_limit[0][1] -= 1
            if _blas_limit[0][1] == 0:
                _blas_limit.pop()[0].restore_original_limits()
