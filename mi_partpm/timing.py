"""Timing Dr.Jit work: evaluate what was asked for, wait for the kernels, read the clock.

Dr.Jit records computations lazily and runs kernels asynchronously, so a timer must evaluate
the result and synchronise before it stops. Every timed phase and benchmark in the project
goes through :func:`timed`, :func:`median_time`, :func:`paired_times` or :class:`Stopwatch`.
"""
from __future__ import annotations

import time
from typing import Callable

import drjit as dr
import numpy as np

__all__ = ["sync", "timed", "median_time", "paired_times", "Stopwatch", "Heartbeat"]


def sync(*values):
    """Evaluate ``values`` (Dr.Jit arrays or PyTrees) and wait until every kernel is done."""
    if values:
        dr.eval(*values)
    dr.sync_thread()


def timed(fn: Callable, jit: bool = True):
    """``(fn(), seconds)``; with ``jit`` the result is evaluated inside the timed span."""
    t0 = time.perf_counter()
    out = fn()
    if jit:
        sync(out)
    return out, time.perf_counter() - t0


def median_time(fn: Callable, repeats: int, jit: bool = True, warmup: int = 1) -> float:
    """Median seconds of ``fn()`` over ``repeats`` runs after ``warmup`` untimed ones (the
    first run of a Dr.Jit kernel includes its compilation)."""
    for _ in range(warmup):
        timed(fn, jit)
    return float(np.median([timed(fn, jit)[1] for _ in range(repeats)]))


def paired_times(fns, repeats: int, warmup: int = 1) -> np.ndarray:
    """Seconds of every ``(fn, jit)`` in ``fns``, shape (len(fns), repeats), timed in rounds:
    every round runs each once, the first one rotating from round to round. A comparison of
    two codes then sees the same load on the machine in each round, so the per-round ratios
    show how far the load moved the comparison, and their median does not drift with it.
    ``warmup`` untimed rounds first (compilation)."""
    k = len(fns)
    for _ in range(warmup):
        for fn, jit in fns:
            timed(fn, jit)
    out = np.zeros((k, repeats))
    for rep in range(repeats):
        for j in range(k):
            i = (rep + j) % k
            fn, jit = fns[i]
            out[i, rep] = timed(fn, jit)[1]
    return out


class Stopwatch:
    """Seconds since the last :meth:`lap` (or since creation), after syncing Dr.Jit; and the
    process's CPU seconds over the same span (every thread's, Dr.Jit's pool included) in
    :attr:`cpu`, for models that share cores out (the MPI backend's prediction)."""

    def __init__(self):
        self._last = time.perf_counter()
        self._last_cpu = time.process_time()
        self.cpu = 0.0

    def lap(self, *values) -> float:
        sync(*values)
        now, now_cpu = time.perf_counter(), time.process_time()
        seconds, self._last = now - self._last, now
        self.cpu, self._last_cpu = now_cpu - self._last_cpu, now_cpu
        return seconds


class Heartbeat:
    """When a long phase should say where it is: :meth:`due` returns the seconds since the
    heartbeat began once every ``period`` seconds (None in between)."""

    def __init__(self, period: float = 10.0):
        self.start, self.period, self._said = time.perf_counter(), period, 0

    def due(self):
        elapsed = time.perf_counter() - self.start
        if elapsed < self.period * (self._said + 1):
            return None
        self._said = int(elapsed // self.period)
        return elapsed
