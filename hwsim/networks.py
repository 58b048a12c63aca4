"""Gather networks: how the PEs' partial results are summed onto one PE (the gather of eq. 2).

Each network is one function of (PE count P, cycles to send one vector over one link, cycles
of one hop plus one add, pipelined or not) returning the gather's cycles, and one function of P
returning how many times a vector crosses a link (for the energy). :data:`NETWORKS` lists
them; the configuration's ``gather.topology``, the reports' sweep and the energy model all read
it, so a new network is a new entry here (and its test).

- **bus**: one shared link, every PE's vector but the root's in turn: ``(P - 1) * V/link +
  hop + adder``.
- **tree**: a binary adder tree of ``L = ceil(log2 P)`` levels; store-and-forward
  ``L * (V/link + hop + adder)``, pipelined ``V/link + L * (hop + adder)``.
- **ring**: ``P - 1`` steps around a ring; store-and-forward ``(P - 1) * (V/link + hop +
  adder)``, pipelined ``V/link + (P - 1) * (hop + adder)``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

__all__ = ["Network", "NETWORKS", "TOPOLOGIES", "SWEEP", "gather_cycles", "gather_traffic"]


def _bus(pes: int, transfer: float, step: float, pipelined: bool) -> float:
    return (pes - 1) * transfer + step      # the root's own vector stays on the root


def _levels(hops: int, transfer: float, step: float, pipelined: bool) -> float:
    """``hops`` hops in a row: streamed (pipelined) or each waiting for the whole vector."""
    return transfer + hops * step if pipelined else hops * (transfer + step)


def _tree(pes: int, transfer: float, step: float, pipelined: bool) -> float:
    return _levels(math.ceil(math.log2(pes)), transfer, step, pipelined)


def _ring(pes: int, transfer: float, step: float, pipelined: bool) -> float:
    return _levels(pes - 1, transfer, step, pipelined)


def _every_pe_but_the_root_sends_once(pes: int) -> int:
    return pes - 1


@dataclass(frozen=True)
class Network:
    """A gather network: its cycles and its link transfers per gather of one vector."""

    name: str
    cycles: Callable[[int, float, float, bool], float]
    link_transfers: Callable[[int], int]
    pipelines: bool        # whether a pipelined variant differs from store-and-forward


#: The gather networks, by the name ``gather.topology`` takes.
NETWORKS = {
    "bus": Network("bus", _bus, _every_pe_but_the_root_sends_once, pipelines=False),
    "tree": Network("tree", _tree, _every_pe_but_the_root_sends_once, pipelines=True),
    "ring": Network("ring", _ring, _every_pe_but_the_root_sends_once, pipelines=True),
}

TOPOLOGIES = tuple(NETWORKS)

#: The variants a report sweeps: (label, topology, pipelined).
SWEEP = tuple(v for name, net in NETWORKS.items()
              for v in (((name, name, True), (f"{name} s&f", name, False)) if net.pipelines
                        else ((name, name, False),)))


def gather_cycles(config, pe_count: int, queries: int) -> float:
    """Cycles to sum ``pe_count`` vectors of ``queries`` results onto one PE."""
    if pe_count <= 1 or queries == 0:
        return 0.0
    g = config.gather
    transfer = queries * config.bytes_per_result / g.link_bytes_per_cycle
    step = g.hop_latency_cycles + g.adder_latency_cycles
    return NETWORKS[g.topology].cycles(pe_count, transfer, step, g.pipelined)


def gather_traffic(config, pe_count: int, queries: int) -> tuple[float, float]:
    """(byte-hops moved, results added) by one gather of ``queries`` results."""
    if pe_count <= 1:
        return 0.0, 0.0
    sends = NETWORKS[config.gather.topology].link_transfers(pe_count)
    return sends * queries * config.bytes_per_result, sends * float(queries)
