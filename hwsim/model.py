"""The analytic model: per-PE busy, stall and idle cycles, the gather, the frame's critical path.

n maps run on P PEs (map m on PE m mod P, one after another). For map m answering Q queries:

    compute  C_m = sum_q  nodes_q * cycles_per_node + tested_q * cycles_per_test
                          + found_q * cycles_per_accumulate
    memory   M_m = 0 if the map fits the PE's SRAM, else
           max( bytes_m / dram_bytes_per_cycle,                     (bandwidth)
                sum_q nodes_q * dram_latency_cycles / outstanding ) (dependent node loads)
    time     T_m = max(C_m, M_m)      (memory overlapped with compute; the excess is stall)

A PE's time is the sum over its maps; the compute phase ends with the slowest PE. The gather
sums P partial vectors of Q results (``bytes_per_result`` each) over the network:

    bus   P * V / link + hop + adder                       (one shared link)
    tree  L = ceil(log2 P) levels; store-and-forward L * (V / link + hop + adder),
          pipelined V / link + L * (hop + adder)
    ring  P - 1 steps; store-and-forward (P - 1) * (V / link + hop + adder),
          pipelined V / link + (P - 1) * (hop + adder)

with V = Q * bytes_per_result. Schedule "after": frame = compute + gather. Schedule "tiles":
each tile of ``tile_queries`` is gathered while the next is computed, so frame =
max(compute, gather) + the gather of one tile.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .config import HardwareConfig

__all__ = ["FrameReport", "simulate", "gather_cycles", "map_cycles"]

POSITION_BYTES = 12


@dataclass
class FrameReport:
    pe_count: int
    map_count: int
    queries: int
    frame_cycles: float
    compute_cycles: float
    gather_cycles: float
    exposed_gather_cycles: float
    seconds: float
    frames_per_second: float
    queries_per_second: float
    pe_busy: np.ndarray            # compute cycles per PE
    pe_stall: np.ndarray           # memory stall cycles per PE
    pe_idle: np.ndarray            # cycles a PE waits for the slowest one and the gather
    utilisation: np.ndarray        # busy / frame, per PE
    load_imbalance: float          # max / mean of busy + stall over PEs
    gather_share: float            # exposed gather / frame
    sram_bytes: np.ndarray         # bytes of maps held in SRAM, per PE (largest map)
    dram_bytes: np.ndarray         # bytes read from DRAM per frame, per PE
    dram_bandwidth: np.ndarray     # bytes per second from DRAM, per PE
    nodes_visited: float           # over all maps and queries

    def as_dict(self) -> dict:
        out = {}
        for k, v in self.__dict__.items():
            out[k] = v.tolist() if isinstance(v, np.ndarray) else v
        return out


def map_cycles(config: HardwareConfig, nodes, tested, found, map_bytes,
               bytes_per_node=8, bytes_per_photon=28):
    """(compute, memory, DRAM bytes) cycles of one map answering all its queries."""
    nodes, tested, found = (np.asarray(a, dtype=np.float64) for a in (nodes, tested, found))
    compute = float((nodes * config.cycles_per_node + tested * config.cycles_per_test
                     + found * config.cycles_per_accumulate).sum())
    if map_bytes <= config.memory.sram_bytes:
        return compute, 0.0, 0.0
    touched = float((nodes * bytes_per_node + tested * POSITION_BYTES
                     + found * (bytes_per_photon - POSITION_BYTES)).sum())
    burst = config.memory.dram_burst_bytes
    moved = math.ceil(touched / burst) * burst
    bandwidth = moved / config.memory.dram_bytes_per_cycle
    latency = float(nodes.sum()) * config.memory.dram_latency_cycles / config.outstanding_queries
    return compute, max(bandwidth, latency), float(moved)


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


def simulate(config: HardwareConfig, workload, bytes_per_node=8, bytes_per_photon=28) -> \
        FrameReport:
    """One frame of ``workload`` (a :class:`hwsim.workload.MapWorkloads`) on ``config``."""
    n = workload.n
    pes = config.pe_count
    if pes > n:
        raise ValueError(f"pe_count must be <= the number of maps n = {n} (every PE holds "
                         f"whole maps), got {pes}")
    queries = workload.queries
    busy, stall = np.zeros(pes), np.zeros(pes)
    sram, dram = np.zeros(pes), np.zeros(pes)
    for m in range(n):
        c, mem, moved = map_cycles(config, workload.nodes_visited[m],
                                   workload.photons_tested[m], workload.photons_found[m],
                                   int(workload.map_bytes[m]), bytes_per_node,
                                   bytes_per_photon)
        pe = m % pes
        busy[pe] += c
        stall[pe] += max(0.0, mem - c)
        dram[pe] += moved
        if workload.map_bytes[m] <= config.memory.sram_bytes:
            sram[pe] = max(sram[pe], float(workload.map_bytes[m]))
    work = busy + stall
    compute = float(work.max())
    gather = gather_cycles(config, pes, queries)
    if config.gather_schedule == "tiles" and pes > 1:
        tile = gather_cycles(config, pes, min(config.tile_queries, queries))
        frame = max(compute, gather) + tile
    else:
        frame = compute + gather
    exposed = frame - compute
    seconds = frame / config.clock_hz
    return FrameReport(
        pe_count=pes, map_count=n, queries=queries, frame_cycles=frame,
        compute_cycles=compute, gather_cycles=gather, exposed_gather_cycles=exposed,
        seconds=seconds, frames_per_second=1.0 / seconds if seconds > 0 else math.inf,
        queries_per_second=queries / seconds if seconds > 0 else math.inf,
        pe_busy=busy, pe_stall=stall, pe_idle=frame - work,
        utilisation=busy / frame if frame > 0 else np.zeros(pes),
        load_imbalance=float(work.max() / work.mean()) if work.mean() > 0 else 1.0,
        gather_share=exposed / frame if frame > 0 else 0.0,
        sram_bytes=sram, dram_bytes=dram,
        dram_bandwidth=dram / seconds if seconds > 0 else np.zeros(pes),
        nodes_visited=float(np.asarray(workload.nodes_visited, dtype=np.float64).sum()))
