"""The fixed-radius query over a forest: the stackless walk of eq. (2)'s density estimate.

One lane per query point walks the implicit trees of the maps it is asked for, one map after
the other: it descends into every child whose half-space the query ball reaches and climbs
back through parents, so it needs no per-lane stack. Every photon within the radius is passed
to a callback with its squared distance, and the callback's results are summed.
"""
from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

from .forest import Forest

__all__ = ["radius_query", "QueryStats"]

# Walk states of the stackless traversal (shared with the kNN walk).
DESCEND, SCAN, ASCEND = 0, 1, 2


@dataclass
class QueryStats:
    """Traversal counts per query point: the workload of one query on all maps searched."""

    nodes_visited: object
    photons_tested: object
    photons_found: object


def coordinate(p, axis):
    """The ``axis`` coordinate (0, 1 or 2, per lane) of the points ``p``."""
    return dr.select(axis == 0, p.x, dr.select(axis == 1, p.y, p.z))


def radius_query(forest: Forest, p, r, contribution, result_type=None, active=True,
                 maps=None, with_stats: bool = False, accept=None):
    """Sum, over the photons within distance ``r`` of each query point, ``contribution``.

    Parameters
    ----------
    forest : Forest
        The photon maps.
    p : mi.Point3f
        Query points, one per lane.
    r : float or mi.Float
        Search radius (the same for every map, as eq. (2) requires).
    contribution : callable(index: mi.UInt32, dist2: mi.Float, active: mi.Bool) -> Spectrum-like
        Called for each photon found, with its tree-order index into the forest's photon
        arrays and its squared distance to the query point (what a density kernel weighs);
        its results are summed.
    result_type : Dr.Jit array type
        Type of ``contribution``'s results, e.g. ``mi.Spectrum`` (default: ``mi.Float``).
    active : mi.Bool
        Lanes to query.
    maps : tuple (first, stop), optional
        Search only maps ``first .. stop-1`` (default: all). The sum over all maps is the
        gathered estimate of eq. (2); one map alone is its partial term.
    with_stats : bool
        Also return a :class:`QueryStats` with per-lane traversal counts.
    accept : callable(index, active) -> mi.Bool, optional
        Which photons may count at all (e.g. those of few enough bounces); a photon it
        rejects is tested but not found. Default: every photon.

    Returns
    -------
    total, or (total, QueryStats)
    """
    first, stop = (0, forest.map_count) if maps is None else maps
    result_type = mi.Float if result_type is None else result_type
    if forest.points.shape[0] == 0:
        # No photon anywhere: nothing to walk (and no array to gather from).
        width = dr.width(p)
        zeros = mi.UInt32(0) if width == 1 else dr.zeros(mi.UInt32, width)
        stats = QueryStats(zeros, mi.UInt32(zeros), mi.UInt32(zeros))
        total = dr.zeros(result_type, width)
        return (total, stats) if with_stats else total
    return _walk(forest, p, r, contribution, result_type, active, first, stop, with_stats,
                 accept)


def walk_start(dev, width, first, stop, active):
    """Initial state of a walk over maps first .. stop-1: at the root of map ``first``.

    Every state variable has the query's width (a literal would make a 1-wide kernel).
    Returns active, map, node, mode, photon index, leaf end, the map's node base, leaf base
    and internal-node count, and the two traversal counters.
    """
    active = dr.full(mi.Bool, first < stop, width) & mi.Bool(active)
    # Opaque: the map range must not be baked into the kernel (one compile for every map).
    m = dr.zeros(mi.UInt32, width) + dr.opaque(mi.UInt32, first)
    zero = dr.zeros(mi.UInt32, width)
    return (active, m, mi.UInt32(zero), dr.full(mi.UInt32, DESCEND, width), mi.UInt32(zero),
            mi.UInt32(zero),
            dr.gather(mi.UInt32, dev["node_base"], m, active),
            dr.gather(mi.UInt32, dev["leaf_base"], m, active),
            dr.gather(mi.UInt32, dev["internal_count"], m, active),
            mi.UInt32(zero), mi.UInt32(zero))


@dr.syntax
def _walk(forest, p, r, contribution, result_type, active, first, stop, with_stats, accept):
    """The stackless traversal behind :func:`radius_query`, one lane per query point."""
    dev = forest.device()
    width = dr.width(p)
    r = dr.opaque(mi.Float, r) if isinstance(r, (int, float)) else mi.Float(r)
    r2 = r * r
    total = dr.zeros(result_type, width)

    (active, m, node, mode, i, end, node_base, leaf_base, n_int, nodes_visited,
     photons_tested) = walk_start(dev, width, first, stop, active)
    photons_found = dr.zeros(mi.UInt32, width)
    stop_u = dr.opaque(mi.UInt32, stop)

    while dr.hint(active, label="partpm_radius_query"):
        if mode == DESCEND:
            nodes_visited += 1
            if node < n_int:
                axis = dr.gather(mi.UInt32, dev["split_axis"], node_base + node)
                split = dr.gather(mi.Float, dev["split_value"], node_base + node)
                node = dr.select(coordinate(p, axis) - r <= split, 2 * node + 1, 2 * node + 2)
            else:
                leaf = leaf_base + (node - n_int)
                i = dr.gather(mi.UInt32, dev["leaf_start"], leaf)
                end = dr.gather(mi.UInt32, dev["leaf_start"], leaf + 1)
                mode = mi.UInt32(SCAN)
        elif mode == SCAN:
            if i < end:
                photons_tested += 1
                q = dr.gather(mi.Point3f, dev["points"], i)
                dist2 = dr.squared_norm(q - p)
                found = dist2 <= r2
                if dr.hint(accept is not None, mode="scalar"):
                    found &= accept(i, found)
                if found:
                    photons_found += 1
                    total += contribution(i, dist2, found)
                i += 1
            else:
                mode = mi.UInt32(ASCEND)
        else:
            if node == 0:
                # This map is done: restart at the root of the next one, or finish.
                m += 1
                if m < stop_u:
                    node_base = dr.gather(mi.UInt32, dev["node_base"], m)
                    leaf_base = dr.gather(mi.UInt32, dev["leaf_base"], m)
                    n_int = dr.gather(mi.UInt32, dev["internal_count"], m)
                    mode = mi.UInt32(DESCEND)
                else:
                    active = mi.Bool(False)
            else:
                parent = (node - 1) >> 1
                to_sibling = mi.Bool(False)
                if (node & 1) == 1:
                    # Coming up from a left child: the right one is next if the ball reaches it.
                    axis = dr.gather(mi.UInt32, dev["split_axis"], node_base + parent)
                    split = dr.gather(mi.Float, dev["split_value"], node_base + parent)
                    to_sibling = coordinate(p, axis) + r >= split
                node = dr.select(to_sibling, node + 1, parent)
                mode = dr.select(to_sibling, mi.UInt32(DESCEND), mi.UInt32(ASCEND))

    stats = QueryStats(nodes_visited, photons_tested, photons_found)
    return (total, stats) if with_stats else total


