"""Alpha-beta(-gamma) cost of the gather over MPI, fitted to a reduction micro-benchmark.

A message of m bytes between two ranks costs alpha + beta * m (start-up latency, seconds per
byte moved); summing it into the receiver's buffer adds gamma * m. MPI_Reduce over P ranks as
a binomial tree takes ceil(log2 P) such steps:

    T_reduce(P, m) = ceil(log2 P) * (alpha + (beta + gamma) * m)

MPI libraries switch protocol and algorithm with the message size (eager vs rendezvous, short
vs long reductions), and caches stop holding the buffers, so one line does not fit 4 B to
16 MiB. Each fit is therefore two lines, short and long messages, split at the measured size
that fits best (the standard two-regime alpha-beta model). alpha and beta come from the
ping-pong, gamma is what the reduction adds per byte over the ping-pong, and a reduction at P
ranks is the benchmark's reduction line scaled by the number of tree steps. All fits weigh
relative errors, so small and large messages count alike.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.optimize import nnls

__all__ = ["Line", "TwoRegimes", "Collective", "fit_line", "fit_regimes", "fit_collective",
           "tree_steps"]


@dataclass
class Line:
    """``seconds = start + per_byte * bytes``, with the fit's largest relative error."""

    start: float
    per_byte: float
    max_rel_error: float

    def __call__(self, nbytes) -> float:
        return self.start + self.per_byte * nbytes


def fit_line(sizes, seconds) -> Line:
    """Non-negative start and per-byte cost minimising the relative error."""
    m = np.asarray(sizes, dtype=np.float64)
    t = np.asarray(seconds, dtype=np.float64)
    if m.size < 2 or np.any(t <= 0):
        raise ValueError(f"need >= 2 sizes with positive times to fit, got {m.size} sizes and "
                         f"times {t.tolist()}")
    a = np.stack([1.0 / t, m / t], axis=1)
    scale = a.max(axis=0)
    coef, _ = nnls(a / scale, np.ones_like(t))
    start, per_byte = (coef / scale).tolist()
    return Line(start, per_byte, float(np.max(np.abs(start + per_byte * m - t) / t)))


@dataclass
class TwoRegimes:
    """Short messages (``bytes < split``) on one line, long ones on another."""

    split: float
    short: Line
    long: Line

    def line(self, nbytes) -> Line:
        return self.short if nbytes < self.split else self.long

    def __call__(self, nbytes) -> float:
        return self.line(nbytes)(nbytes)

    @property
    def max_rel_error(self) -> float:
        return max(self.short.max_rel_error, self.long.max_rel_error)

    def as_dict(self) -> dict:
        return {"split_bytes": self.split, "short": self.short.__dict__,
                "long": self.long.__dict__}


def fit_regimes(sizes, seconds, min_points=3) -> TwoRegimes:
    """The split (one of the measured sizes) whose two lines have the smallest worst
    relative error; each regime keeps at least ``min_points`` sizes."""
    m = np.asarray(sizes, dtype=np.float64)
    t = np.asarray(seconds, dtype=np.float64)
    order = np.argsort(m)
    m, t = m[order], t[order]
    if m.size < 2 * min_points:
        raise ValueError(f"need >= {2 * min_points} message sizes for two regimes, got {m.size}")
    best = None
    for k in range(min_points, m.size - min_points + 1):
        fit = TwoRegimes(float(m[k]), fit_line(m[:k], t[:k]), fit_line(m[k:], t[k:]))
        if best is None or fit.max_rel_error < best.max_rel_error:
            best = fit
    return best


def tree_steps(ranks: int) -> int:
    """Steps of a binomial-tree reduction over ``ranks`` ranks."""
    return math.ceil(math.log2(ranks)) if ranks > 1 else 0


@dataclass
class Collective:
    """The fitted cost of the backend's one collective, from a run on ``ranks`` >= 2 ranks."""

    ranks: int
    pingpong: TwoRegimes
    reduce: TwoRegimes

    def alpha_beta_gamma(self, nbytes) -> tuple[float, float, float]:
        """(alpha, beta, gamma) of the regime that holds a message of ``nbytes``."""
        pp = self.pingpong.line(nbytes)
        red = self.reduce.line(nbytes)
        return pp.start, pp.per_byte, max(0.0, red.per_byte / tree_steps(self.ranks)
                                          - pp.per_byte)

    def reduce_seconds(self, ranks: int, nbytes: float) -> float:
        """MPI_Reduce of ``nbytes`` over ``ranks`` ranks (binomial tree, >= 2 ranks)."""
        return tree_steps(ranks) / tree_steps(self.ranks) * self.reduce(nbytes)

    def as_dict(self) -> dict:
        return {"ranks": self.ranks, "pingpong": self.pingpong.as_dict(),
                "reduce": self.reduce.as_dict()}


def fit_collective(bench: dict) -> Collective:
    """Fit a micro-benchmark run (``mi_partpm.experiments.reducebench`` JSON) on >= 2 ranks."""
    if bench["ranks"] < 2 or any(p is None for p in bench["pingpong"]):
        raise ValueError(f"alpha and beta need a micro-benchmark on >= 2 ranks, got "
                         f"{bench['ranks']}")
    return Collective(bench["ranks"], fit_regimes(bench["sizes"], bench["pingpong"]),
                      fit_regimes(bench["sizes"], bench["reduce"]))
