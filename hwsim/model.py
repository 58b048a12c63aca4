"""The analytic model: per-PE busy, stall and idle cycles, the gather, the frame's critical path.

n maps run on P PEs (map m on PE m mod P). The Q queries are cut into tiles of
``tile_queries``; a PE works tile by tile and, within a tile, map by map (tile-major order),
so that its partial results of a tile are complete as early as possible. For map m and tile k:

    compute  c_mk = sum_{q in k} nodes_q * cycles_per_node + tested_q * cycles_per_test
                                 + found_q * cycles_per_accumulate
    memory   0 if the map fits the PE's SRAM, else the larger of
             bandwidth  bursts(bytes_mk) / dram_bytes_per_cycle
             latency    sum_{q in k} nodes_q * dram_latency_cycles / outstanding_queries
    time     t_mk = max(c_mk, memory)   (memory overlapped with compute; the excess is stall)

A PE's partial result of tile k is ready when its last map has done tile k (a running sum of
its t_mk); ready_k is the latest over the PEs and the compute phase ends at ready_K. The
gather of V = q * bytes_per_result bytes from P PEs takes

    bus   P * V / link + hop + adder                       (one shared link)
    tree  L = ceil(log2 P) levels; store-and-forward L * (V / link + hop + adder),
          pipelined V / link + L * (hop + adder)
    ring  P - 1 steps; store-and-forward (P - 1) * (V / link + hop + adder),
          pipelined V / link + (P - 1) * (hop + adder)

Schedule "after": frame = ready_K + gather of all Q results. Schedule "tiles": tile k is
gathered once it is ready and the network is free, so the frame ends at
max_k (ready_k + sum_{s >= k} g_s), the critical path of a two-stage pipeline.

This is exact as long as every PE has its own DRAM channel. When PEs share channels
(``memory.dram_channels``) their requests queue; :mod:`hwsim.events` simulates that, and with
private channels it reproduces this model to the last bit (tests/test_hwsim.py).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .config import HardwareConfig

__all__ = ["FrameReport", "TileWork", "tile_work", "simulate", "gather_cycles",
           "gather_traffic", "pipeline_end", "frame_report"]

POSITION_BYTES = 12


@dataclass
class FrameReport:
    pe_count: int
    map_count: int
    queries: int
    model: str                     # "analytic" or "events"
    frame_cycles: float
    compute_cycles: float
    gather_cycles: float           # the gather of all Q results, as if alone
    exposed_gather_cycles: float   # frame - compute: what the gather adds to the frame
    seconds: float
    frames_per_second: float
    queries_per_second: float
    pe_busy: np.ndarray            # compute cycles per PE
    pe_stall: np.ndarray           # memory stall cycles per PE (queueing included)
    pe_idle: np.ndarray            # cycles a PE waits for the slowest one and the gather
    utilisation: np.ndarray        # busy / frame, per PE
    load_imbalance: float          # max / mean of busy + stall over PEs
    gather_share: float            # exposed gather / frame
    sram_bytes: np.ndarray         # bytes of the largest map held in SRAM, per PE
    dram_bytes: np.ndarray         # bytes read from DRAM per frame, per PE
    dram_bandwidth: np.ndarray     # bytes per second from DRAM, per PE
    dram_channel_busy: np.ndarray  # cycles each DRAM channel transfers, per channel
    nodes_visited: float           # over all maps and queries
    energy_joules: float           # dynamic + static energy of the frame
    energy: dict                   # joules per kind of action

    def as_dict(self) -> dict:
        out = {}
        for k, v in self.__dict__.items():
            out[k] = v.tolist() if isinstance(v, np.ndarray) else v
        return out


@dataclass
class TileWork:
    """Cycles of every (map, tile) pair: what both models schedule."""

    compute: np.ndarray     # (n, K) compute cycles
    latency: np.ndarray     # (n, K) latency-bound memory cycles (0 for maps in SRAM)
    transfer: np.ndarray    # (n, K) cycles the DRAM channel is busy (0 for maps in SRAM)
    moved: np.ndarray       # (n, K) bytes moved from DRAM
    tile_sizes: np.ndarray  # (K,) queries per tile
    in_sram: np.ndarray     # (n,) whether each map fits its PE's SRAM
    totals: tuple           # nodes visited, photons tested, photons found over all maps

    @property
    def time(self) -> np.ndarray:
        """(n, K) cycles of each (map, tile) with a private DRAM channel."""
        return np.maximum(self.compute, np.maximum(self.latency, self.transfer))


def tile_work(config: HardwareConfig, workload, bytes_per_node=8, bytes_per_photon=28) -> \
        TileWork:
    """Per map and tile: compute cycles and the memory demand of maps that spill to DRAM."""
    nodes, tested, found, sizes = workload.tile_counts(config.tile_queries)
    compute = (nodes * config.cycles_per_node + tested * config.cycles_per_test
               + found * config.cycles_per_accumulate)
    mem = config.memory
    in_sram = np.asarray(workload.map_bytes) <= mem.sram_bytes
    touched = nodes * bytes_per_node + tested * POSITION_BYTES + \
        found * (bytes_per_photon - POSITION_BYTES)
    moved = np.ceil(touched / mem.dram_burst_bytes) * mem.dram_burst_bytes
    moved[in_sram] = 0.0
    transfer = moved / mem.dram_bytes_per_cycle
    latency = nodes * mem.dram_latency_cycles / config.outstanding_queries
    latency[in_sram] = 0.0
    return TileWork(compute, latency, transfer, moved, sizes, in_sram,
                    (float(nodes.sum()), float(tested.sum()), float(found.sum())))


def gather_cycles(config: HardwareConfig, pe_count: int, queries: int) -> float:
    """Cycles to sum ``pe_count`` vectors of ``queries`` results onto one PE."""
    if pe_count <= 1 or queries == 0:
        return 0.0
    g = config.gather
    transfer = queries * config.bytes_per_result / g.link_bytes_per_cycle
    step = g.hop_latency_cycles + g.adder_latency_cycles
    if g.topology == "bus":
        return pe_count * transfer + step
    hops = math.ceil(math.log2(pe_count)) if g.topology == "tree" else pe_count - 1
    if g.pipelined:
        return transfer + hops * step
    return hops * (transfer + step)


def gather_traffic(config: HardwareConfig, pe_count: int, queries: int) -> tuple[float, float]:
    """(byte-hops moved, results added) by one gather of ``queries`` results."""
    if pe_count <= 1:
        return 0.0, 0.0
    volume = queries * config.bytes_per_result
    # bus: every PE but the root drives the one bus once; tree and ring: every PE but the root
    # sends its (partially summed) vector over one link once.
    return (pe_count - 1) * volume, (pe_count - 1) * float(queries)


def pipeline_end(ready: np.ndarray, gathers: np.ndarray) -> float:
    """End of a two-stage pipeline: tile k enters the gather when it is ready and the gather
    of tile k - 1 is done; ``max_k (ready_k + sum_{s >= k} g_s)``."""
    if ready.size == 0:
        return 0.0
    suffix = np.cumsum(gathers[::-1])[::-1]
    return float(np.max(ready + suffix))


def _gather_end(config, pes, work: TileWork, compute_end, ready, queries):
    whole = gather_cycles(config, pes, queries)
    if config.gather_schedule == "tiles" and pes > 1:
        tiles = np.array([gather_cycles(config, pes, int(s)) for s in work.tile_sizes])
        return pipeline_end(ready, tiles), whole
    return compute_end + whole, whole


def frame_report(config, workload, work: TileWork, model, busy, stall, ready,
                 channel_busy) -> FrameReport:
    """The frame from per-PE busy and stall cycles and the tiles' ready times (both models)."""
    pes, n, queries = config.pe_count, workload.n, workload.queries
    work_cycles = busy + stall
    compute = float(work_cycles.max())
    frame, gather = _gather_end(config, pes, work, compute, ready, queries)
    seconds = frame / config.clock_hz
    sram, dram = np.zeros(pes), np.zeros(pes)
    for m in range(n):
        pe = m % pes
        dram[pe] += float(work.moved[m].sum())
        if work.in_sram[m]:
            sram[pe] = max(sram[pe], float(workload.map_bytes[m]))
    energy = _energy(config, work, dram, seconds, queries)
    return FrameReport(
        pe_count=pes, map_count=n, queries=queries, model=model, frame_cycles=frame,
        compute_cycles=compute, gather_cycles=gather, exposed_gather_cycles=frame - compute,
        seconds=seconds, frames_per_second=1.0 / seconds if seconds > 0 else math.inf,
        queries_per_second=queries / seconds if seconds > 0 else math.inf,
        pe_busy=busy, pe_stall=stall, pe_idle=frame - work_cycles,
        utilisation=busy / frame if frame > 0 else np.zeros(pes),
        load_imbalance=float(work_cycles.max() / work_cycles.mean())
        if work_cycles.mean() > 0 else 1.0,
        gather_share=(frame - compute) / frame if frame > 0 else 0.0,
        sram_bytes=sram, dram_bytes=dram,
        dram_bandwidth=dram / seconds if seconds > 0 else np.zeros(pes),
        dram_channel_busy=channel_busy,
        nodes_visited=work.totals[0],
        energy_joules=sum(energy.values()), energy=energy)


def _energy(config, work: TileWork, dram_bytes, seconds, queries) -> dict:
    e = config.energy
    pj = 1e-12
    nodes, tested, found = work.totals
    link_bytes, adds = gather_traffic(config, config.pe_count, queries)
    return {"nodes": nodes * e.pj_per_node * pj,
            "tests": tested * e.pj_per_test * pj,
            "accumulates": found * e.pj_per_accumulate * pj,
            "dram": float(dram_bytes.sum()) * e.pj_per_dram_byte * pj,
            "gather": (link_bytes * e.pj_per_link_byte + adds * e.pj_per_add) * pj,
            "static": config.pe_count * e.static_watts_per_pe * seconds}


def pe_maps(n: int, pes: int) -> list[np.ndarray]:
    """The maps of each PE: m on PE m mod P."""
    return [np.arange(p, n, pes) for p in range(pes)]


def simulate(config: HardwareConfig, workload, bytes_per_node=8, bytes_per_photon=28,
             model: str = "auto") -> FrameReport:
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
    work = tile_work(config, workload, bytes_per_node, bytes_per_photon)
    if model == "events" or (model == "auto" and contended):
        from .events import simulate_events
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
