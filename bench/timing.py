"""Timing and memory for the benchmarks: the best of several runs, by wall clock or by CPU time, and a
process's own peak resident memory."""

from __future__ import annotations

import resource
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


def peak_gib() -> float:
    """This process's peak resident memory (GiB) since it started or since :func:`reset_peak`. Linux's
    ``ru_maxrss`` carries the forking parent's high-water mark over exec (a child of a 2.5 GiB parent
    reports >= 2.5 GiB); ``VmHWM`` belongs to the process's own address space."""
    try:
        with open("/proc/self/status") as f:
            return next(int(line.split()[1]) for line in f if line.startswith("VmHWM:")) / 2**20  # KiB
    except (OSError, StopIteration):
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20  # not Linux: KiB on most systems


def reset_peak() -> None:
    """Start :func:`peak_gib` afresh from the current resident memory (Linux; elsewhere a no-op), so a
    bench run in a process that ran others before it measures its own peak."""
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
    except OSError:
        pass
