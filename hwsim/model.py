"""The analytic model: per-PE busy, stall and idle cycles, the gather, the frame's critical path.

n maps run on P PEs (map m on PE m mod P). The Q queries are cut into tiles of
``tile_queries``; a PE works tile by tile and, within a tile, map by map (tile-major order),
so that its partial results of a tile are complete as early as possible. A PE's maps are
therefore resident together and share its ``memory.sram_bytes``: in map order, a map is kept
in SRAM if it fits in what the PE's maps kept before it left free, and the others stream from
DRAM in every tile (:func:`hwsim.work.sram_resident`). For map m and tile k:

    compute  c_mk = sum_{q in k} nodes_q * cycles_per_node + tested_q * cycles_per_test
                                 + found_q * cycles_per_accumulate
                    (+ cycles_per_map in the map's first tile k = 0); the four costs are
                    assumed, or fitted to measured CPU times ([pe] costs, hwsim.config)
    memory   0 if the map is resident in its PE's SRAM, else the larger of
             bandwidth  bursts(bytes_mk) / dram_bytes_per_cycle
             latency    sum_{q in k} nodes_q * dram_latency_cycles / outstanding_queries
    time     t_mk = max(c_mk, memory)   (memory overlapped with compute; the excess is stall)

A PE's partial result of tile k is ready when its last map has done tile k (a running sum of
its t_mk); ready_k is the latest over the PEs and the compute phase ends at ready_K. The
gather of V = q * bytes_per_result bytes from P PEs is the network's (:mod:`hwsim.networks`:
a bus, a tree or a ring, pipelined or store-and-forward).

Schedule "after": frame = ready_K + gather of all Q results. Schedule "tiles": tile k is
gathered once it is ready and the network is free, so the frame ends at
max_k (ready_k + sum_{s >= k} g_s), the critical path of a two-stage pipeline.

This is exact as long as every PE has its own DRAM channel. When PEs share channels
(``memory.dram_channels``) their requests queue; :mod:`hwsim.events` simulates that, and with
private channels it reproduces this model to the last bit (tests/test_hwsim.py).
"""
from __future__ import annotations

import numpy as np

from .config import HardwareConfig
from .events import simulate_events
from .work import FrameReport, frame_report, pe_maps, tile_work

__all__ = ["simulate"]


def simulate(config: HardwareConfig, workload, model: str = "auto") -> FrameReport:
    """One frame of ``workload`` (a :class:`hwsim.workload.MapWorkloads`) on ``config``.

    ``model``: "analytic" (private DRAM channels only), "events" (the discrete-event model of
    :mod:`hwsim.events`) or "auto": events when PEs share DRAM channels, else analytic.
    """
    n, pes = workload.n, config.pe_count
    if pes > n:
        raise ValueError(f"pe_count must be <= the number of maps n = {n} (every PE holds "
                         f"whole maps), got {pes}")
    if model not in ("auto", "analytic", "events"):
        raise ValueError(f"model must be 'auto', 'analytic' or 'events', got {model!r}")
    contended = config.memory.contended(pes)
    if model == "analytic" and contended:
        raise ValueError(f"the analytic model has no DRAM contention but memory.dram_channels "
                         f"= {config.memory.dram_channels} < pe_count = {pes}: use "
                         f"model='events' (or 'auto')")
    work = tile_work(config, workload)
    if model == "events" or (model == "auto" and contended):
        return simulate_events(config, workload, work)
    time = work.time
    busy, stall, channel_busy = np.zeros(pes), np.zeros(pes), np.zeros(pes)
    ready = np.zeros(work.tile_sizes.size)
    for p, maps in enumerate(pe_maps(n, pes)):
        busy[p] = float(work.compute[maps].sum())
        channel_busy[p] = float(work.transfer[maps].sum())     # a private channel per PE
        # Tile-major running sum, added in the same order as the event model's clock.
        ends = np.cumsum(time[maps].T.ravel()).reshape(-1, maps.size)
        stall[p] = (ends[-1, -1] if ends.size else 0.0) - busy[p]
        ready = np.maximum(ready, ends[:, -1])
    return frame_report(config, workload, work, "analytic", busy, stall, ready, channel_busy)
