"""The discrete-event model: PEs that share DRAM channels and queue for them.

Each PE runs the same (map, tile) items (:mod:`hwsim.work`) as the analytic model
(:mod:`hwsim.model`), in the same tile-major order, with the same maps resident in the PE's
shared SRAM (:func:`hwsim.work.sram_resident`). An item of a map that is not resident reads
DRAM: it sends one request of its bytes to its channel
(PE p on channel p mod ``memory.dram_channels``); the channel serves requests first come,
first served, each for bytes / ``dram_bytes_per_cycle`` cycles. The item ends when its compute,
its latency bound and its transfer are all done:

    end = max(start + compute, start + latency, transfer end),
    transfer end = max(start, channel free) + transfer.

Events are processed in time order (a heap of PE start times; ties by PE index), so requests
are served in the order they arrive. With a private channel per PE no request ever waits and
every item takes exactly the analytic model's time; the two models then agree to the last bit.
"""
from __future__ import annotations

import heapq

import numpy as np

from .work import TileWork, frame_report, pe_maps

__all__ = ["simulate_events"]


def simulate_events(config, workload, work: TileWork):
    """One frame on ``config`` with DRAM channel contention (see the module's text)."""
    n, pes = workload.n, config.pe_count
    channels = config.memory.channels(pes)
    tiles = work.tile_sizes.size
    maps = pe_maps(n, pes)
    # Per PE: its items in tile-major order, as (compute, latency, transfer, last-of-tile).
    items = []
    for p in range(pes):
        m = maps[p]
        seq = [(float(work.compute[i, k]), float(work.latency[i, k]),
                float(work.transfer[i, k]), k if j == m.size - 1 else -1)
               for k in range(tiles) for j, i in enumerate(m)]
        items.append(seq)
    busy, stall = np.zeros(pes), np.zeros(pes)
    ready = np.zeros(tiles)
    free = [0.0] * channels
    channel_busy = np.zeros(channels)
    position = [0] * pes
    heap = [(0.0, p) for p in range(pes) if items[p]]
    heapq.heapify(heap)
    while heap:
        start, p = heapq.heappop(heap)
        compute, latency, transfer, tile = items[p][position[p]]
        end = max(start + compute, start + latency)
        if transfer > 0.0:
            ch = p % channels
            served = max(start, free[ch]) + transfer
            free[ch] = served
            channel_busy[ch] += transfer
            end = max(end, served)
        busy[p] += compute
        stall[p] += end - start - compute
        if tile >= 0:
            ready[tile] = max(ready[tile], end)
        position[p] += 1
        if position[p] < len(items[p]):
            heapq.heappush(heap, (end, p))
    return frame_report(config, workload, work, "events", busy, stall, ready, channel_busy)
