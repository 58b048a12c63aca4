"""What both frame models share: the work of every (map, tile) pair and the frame it makes.

:func:`sram_resident` decides which maps a PE keeps in its SRAM: all of a PE's maps run tile
by tile, so they are resident together and share it. :func:`tile_work` turns a workload's
traversal counts into compute cycles and memory demand per map and tile (maps not resident
stream from DRAM, tile by tile); :func:`frame_report` turns per-PE busy and stall cycles and
the tiles' ready times into a :class:`FrameReport` (the gather's end, utilisation, SRAM and
DRAM bytes, energy). The analytic model (:mod:`hwsim.model`) and the discrete-event model
(:mod:`hwsim.events`) differ only in how they schedule the tiles between the two.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .config import HardwareConfig
from .networks import gather_cycles, gather_traffic

__all__ = ["FrameReport", "TileWork", "tile_work", "frame_report", "pipeline_end", "pe_maps",
           "sram_resident", "POSITION_BYTES"]

#: Bytes of a photon's position (float32 x, y, z): what a distance test reads.
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
    sram_bytes: np.ndarray         # bytes of the maps held in SRAM together, per PE
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
    in_sram: np.ndarray     # (n,) whether each map is resident in its PE's SRAM
    totals: tuple           # nodes visited, photons tested, photons found over all maps

    @property
    def time(self) -> np.ndarray:
        """(n, K) cycles of each (map, tile) with a private DRAM channel."""
        return np.maximum(self.compute, np.maximum(self.latency, self.transfer))


def pe_maps(n: int, pes: int) -> list[np.ndarray]:
    """The maps of each PE: m on PE m mod P."""
    return [np.arange(p, n, pes) for p in range(pes)]


def sram_resident(map_bytes, pes: int, sram_bytes: int) -> np.ndarray:
    """(n,) bool: which maps live in their PE's SRAM.

    A PE's maps share its ``sram_bytes``. Each PE takes its maps in map order (m, m + P,
    m + 2P, ...) and keeps a map in SRAM if it fits in the bytes that the maps kept before it
    left free (first fit); a map that does not fit streams from DRAM, and a later, smaller
    map may still fit. With one map per PE this is "the map fits the SRAM"."""
    sizes = np.asarray(map_bytes)
    resident = np.zeros(sizes.size, dtype=bool)
    for maps in pe_maps(sizes.size, pes):
        free = sram_bytes
        for m in maps:
            if sizes[m] <= free:
                resident[m] = True
                free -= sizes[m]
    return resident


def tile_work(config: HardwareConfig, workload) -> TileWork:
    """Per map and tile: compute cycles and the memory demand of the maps that are not
    resident in their PE's SRAM (:func:`sram_resident` on ``config.pe_count`` PEs; the bytes
    of a node and of a photon record are the workload's). Compute is the counts times the
    cycles of :meth:`HardwareConfig.compute_cycles` (assumed or fitted), and a map's
    per-map cycles in its first tile."""
    bytes_per_node, bytes_per_photon = workload.bytes_per_node, workload.bytes_per_photon
    nodes, tested, found, sizes = workload.tile_counts(config.tile_queries)
    cycles = config.compute_cycles()
    compute = nodes * cycles["node"] + tested * cycles["test"] + found * cycles["found"]
    if cycles["map"] and compute.shape[1]:
        compute[:, 0] += cycles["map"]          # a map's set-up, before its first tile
    mem = config.memory
    in_sram = sram_resident(workload.map_bytes, config.pe_count, mem.sram_bytes)
    touched = nodes * bytes_per_node + tested * POSITION_BYTES + \
        found * (bytes_per_photon - POSITION_BYTES)
    moved = np.ceil(touched / mem.dram_burst_bytes) * mem.dram_burst_bytes
    moved[in_sram] = 0.0
    transfer = moved / mem.dram_bytes_per_cycle
    latency = nodes * mem.dram_latency_cycles / config.outstanding_queries
    latency[in_sram] = 0.0
    return TileWork(compute, latency, transfer, moved, sizes, in_sram,
                    (float(nodes.sum()), float(tested.sum()), float(found.sum())))


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
    sram, dram = _pe_memory(workload, work, pes)
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


def _pe_memory(workload, work: TileWork, pes: int) -> tuple[np.ndarray, np.ndarray]:
    """(bytes held in SRAM, bytes read from DRAM per frame), per PE."""
    sram, dram = np.zeros(pes), np.zeros(pes)
    for p, maps in enumerate(pe_maps(workload.n, pes)):
        dram[p] = float(work.moved[maps].sum())
        sram[p] = float(np.asarray(workload.map_bytes)[maps][work.in_sram[maps]].sum())
    return sram, dram


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
