"""Timing for the benchmarks: the best of several runs, by wall clock or by CPU time."""

from __future__ import annotations

import time
from collections.abc import Callable


def best_time(fn: Callable[[], object], repeats: int = 3, clock: Callable[[], float] = time.perf_counter):
    """(fastest of ``repeats`` calls in seconds of ``clock``, the last call's result).

    ``clock=time.process_time`` measures CPU time of all this process's threads, which other jobs on a
    shared machine disturb less than wall time.
    """
    best, out = float("inf"), None
    for _ in range(repeats):
        t0 = clock()
        out = fn()
        best = min(best, clock() - t0)
    return best, out
