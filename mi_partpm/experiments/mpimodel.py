"""The MPI backend's render time on P ranks, predicted from one P = 1 run and the reduction
micro-benchmark alone.

What a rank does (:mod:`mi_partpm.backends`): every rank follows every eye path (the eye
pass is replicated, so every rank draws the same samples), traces, builds and queries only
the maps it owns (rank j owns maps j, j + P, ...), and one reduction per pass sums the eye
paths' flux and photon counts. A P = 1 run measures, per phase, the wall time and the CPU
seconds of all its threads (``cpu_*`` in the stats). The CPU seconds are the work; the model
splits it out:

- work of one rank = eye work + (trace + build + estimate work) x (maps it owns / n);
- the ranks share the node's C cores: with P ranks each runs on C / P cores when P <= C and
  on a 1 / (P / C) share of one core when P > C (the scheduler time-slices);
- a rank's work runs at the parallel efficiency Dr.Jit reached at P = 1 when it has more than
  one core (wall = work / (cores x efficiency), efficiency = P = 1's work / (C x its wall)),
  and at efficiency 1 on one core or less (nothing left to run in parallel);
- plus the reduction's time at P from the micro-benchmark's fit, once per pass;
- plus what the P = 1 render spent outside the phases (setting up the camera, developing
  the film), which rank 0 does alone whatever P.

The slowest rank's time (the one owning the most maps) is the render's. Nothing of the
P > 1 runs enters the prediction; :func:`predict` is checked against them afterwards.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

__all__ = ["PhaseWork", "predict", "PHASES"]

#: The phases whose work is split over the ranks' maps; the eye pass is replicated.
PHASES = ("trace", "build", "estimate")


@dataclass
class PhaseWork:
    """What a P = 1 render measured: CPU seconds per phase, its wall time over the phases,
    the maps, the passes and the cores it ran on."""

    cpu: dict            # phase -> CPU seconds (all threads), "eye" included
    wall: float          # trace + build + eye + estimate, wall seconds
    maps: int
    passes: int
    cores: int
    overhead: float = 0.0   # the render's wall time outside the phases

    @classmethod
    def from_stats(cls, stats: dict, cores: int) -> "PhaseWork":
        """From a rank's stats of a P = 1 run (``partpm render --stats-json``)."""
        cpu = {ph: float(stats[f"cpu_{ph}"]) for ph in (*PHASES, "eye")}
        wall = sum(float(stats[f"time_{ph}"]) for ph in (*PHASES, "eye"))
        render = float(stats.get("time_render", wall))
        return cls(cpu=cpu, wall=wall, maps=int(stats["map_count"]),
                   passes=max(1, int(stats.get("passes", 1))), cores=int(cores),
                   overhead=max(0.0, render - wall))

    @property
    def efficiency(self) -> float:
        """Dr.Jit's parallel efficiency at P = 1: work / (cores x wall), at most 1."""
        total = sum(self.cpu.values())
        return min(1.0, total / (self.cores * self.wall)) if self.wall > 0 else 1.0


def predict(work: PhaseWork, ranks: int, reduce_seconds: Callable[[int], float],
            reduce_bytes: int) -> dict:
    """The predicted render time on ``ranks`` ranks of one node of ``work.cores`` cores:
    the slowest rank's compute (see the module's text) plus one reduction of
    ``reduce_bytes`` per pass (``reduce_seconds(bytes)``, the micro-benchmark's fit at that
    P). Returns the parts and the total."""
    owned_max = -(-work.maps // ranks)                  # maps of the rank that owns the most
    split = sum(work.cpu[ph] for ph in PHASES) * owned_max / work.maps
    rank_work = work.cpu["eye"] + split
    cores_per_rank = work.cores / ranks
    if cores_per_rank > 1:
        compute = rank_work / (cores_per_rank * work.efficiency)
    else:
        compute = rank_work / cores_per_rank            # time-sliced: a share of one core
    reduction = work.passes * reduce_seconds(reduce_bytes) if ranks > 1 else 0.0
    return {"ranks": ranks, "owned_max": owned_max, "rank_work": rank_work,
            "cores_per_rank": cores_per_rank, "efficiency_p1": work.efficiency,
            "compute": compute, "reduce": reduction, "overhead": work.overhead,
            "render": compute + reduction + work.overhead}
