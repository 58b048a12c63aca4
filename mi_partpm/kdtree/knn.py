"""The k-nearest-neighbour query over a forest: the conventional estimate of eq. (1).

The walk is the stackless while-while traversal of :mod:`.radius`, visiting the nearer child
first and passing over leaves whose box lies beyond the current radius, with a per-lane
max-heap of the k best candidates in local memory. Each lane walks with its own ball (its
radius shrinks as its heap fills, so lanes cannot share one as the fixed-radius walk's do).
Queries are walked in Morton order and answered in the caller's.
"""
from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from .forest import Forest
from .radius import (QueryStats, coordinate, leaf_reached, leaf_run, order_queries, permute,
                     photon_position, split_of, tree_row, unpermute, walk_start)

__all__ = ["knn_query", "KnnResult", "knn_neighbours"]


@dataclass
class KnnResult:
    """Result of :func:`knn_query`, one entry per query point.

    Attributes
    ----------
    total : result_type
        Sum of ``contribution`` over the neighbours found.
    radius2 : mi.Float
        Squared search radius at the end: the squared distance to the k-th nearest photon when
        k were found; with fewer, ``max_radius**2`` when a cap was given, else the squared
        distance to the farthest photon found (0 when none was).
    count : mi.UInt32
        Neighbours found (k, or fewer when fewer lie within ``max_radius``).
    stats : QueryStats or None
        Traversal counts, when asked for.
    """

    total: object
    radius2: object
    count: object
    stats: object = None


def knn_query(forest: Forest, p, k: int, contribution=None, result_type=None,
              max_radius=None, active=True, maps=None, with_stats: bool = False,
              neighbours: bool = False, accept=None, state=None, order: str = "morton"):
    """The ``k`` photons nearest to each query point, and the sum of their contributions.

    Parameters
    ----------
    forest : Forest
        The photon maps; with several maps, the k nearest over all of them (or ``maps``).
    p : mi.Point3f
        Query points, one per lane.
    k : int
        Neighbours wanted, >= 1.
    contribution : callable(index, dist2, active, state) -> result_type, optional
        Summed over the neighbours found, as in :func:`~.radius.radius_query`, after the
        walk; when ``state`` has a ``radius2`` field it is set to each query's final squared
        radius first (what a density kernel weighs by).
    result_type : Dr.Jit array type
        Type of ``contribution``'s results (default: ``mi.Float``).
    max_radius : float or mi.Float, optional
        Only photons within this distance count (Jensen's cap). Default: unbounded.
    active : mi.Bool
        Lanes to query.
    maps : tuple (first, stop), optional
        Search only maps ``first .. stop-1`` (default: all).
    with_stats : bool
        Also record the traversal counts (:class:`QueryStats`).
    accept : callable(index, active, state) -> mi.Bool, optional
        Which photons may be neighbours at all (default: every photon).
    state : PyTree of per-query arrays, optional
        Per-query data for the callbacks, put in the walk's order with the queries (see
        :func:`~.radius.radius_query`).
    order : str
        "morton" (default) or "given", as for :func:`~.radius.radius_query`.
    neighbours : bool
        Also return the neighbours: two lists of k arrays, squared distances and tree-order
        indices; unused entries hold ``inf`` and ``0xFFFFFFFF``.

    Returns
    -------
    KnnResult, or (KnnResult, dist2 list, index list) with ``neighbours=True`` (the lists in
    heap order; :func:`knn_neighbours` sorts them).

    Notes
    -----
    The walk is the stackless traversal of :func:`~.radius.radius_query`, visiting the nearer
    child
    first, with a per-lane max-heap of the k best candidates in local memory. The search
    radius starts at ``max_radius`` and shrinks to the heap's largest distance once it holds
    k photons, so far subtrees are skipped as in Jensen's ``locate_photons``. Photons at
    exactly the current radius are not taken once the heap is full (the first found stays).
    """
    if not isinstance(k, (int, np.integer)) or isinstance(k, bool) or k < 1:
        raise ValueError(f"k must be an integer >= 1, got {k!r}")
    result_type = mi.Float if result_type is None else result_type
    width = dr.width(p)
    if max_radius is None:
        r2max = dr.inf
    elif isinstance(max_radius, (int, float)):
        r2max = dr.opaque(mi.Float, float(max_radius) ** 2)   # no recompile per value
    else:
        r2max = dr.square(mi.Float(max_radius))
    if forest.size == 0 or width == 0:
        zeros = dr.zeros(mi.UInt32, width)
        stats = QueryStats(zeros, mi.UInt32(zeros), mi.UInt32(zeros)) if with_stats else None
        res = KnnResult(dr.zeros(result_type, width), dr.zeros(mi.Float, width) + r2max,
                        mi.UInt32(zeros), stats)
        if neighbours:
            return (res, [dr.full(mi.Float, dr.inf, width)] * k,
                    [dr.full(mi.UInt32, 0xFFFFFFFF, width)] * k)
        return res
    perm = order_queries(p, width, order)
    active = dr.full(mi.Bool, True, width) & mi.Bool(active)
    if not isinstance(r2max, float):
        r2max = permute(dr.zeros(mi.Float, width) + r2max, perm, width)
    res, d2, idx = _knn_walk(forest, permute(p, perm, width), int(k), contribution,
                             result_type, r2max, permute(active, perm, width),
                             forest.walk_table(maps), neighbours, accept,
                             permute(state, perm, width))
    res = KnnResult(*[unpermute(v, perm, width) for v in (res.total, res.radius2, res.count)],
                    QueryStats(*[unpermute(v, perm, width) for v in (
                        res.stats.nodes_visited, res.stats.photons_tested,
                        res.stats.photons_found)]) if with_stats else None)
    if neighbours:
        return res, [unpermute(v, perm, width) for v in d2], \
            [unpermute(v, perm, width) for v in idx]
    return res


@dr.syntax
def _heap_insert(heap_d, heap_i, count, ku, d2, i, push, replace):
    """Put ``(d2, i)`` into each lane's max-heap of k entries (``count`` of them used).

    ``push``: the heap has room, sift up from the end; ``replace``: the new entry replaces the
    root (the farthest), sift down from it. Each moves parents (children) over the hole until
    the new entry fits.
    """
    take = push | replace
    pos = dr.select(push, count, 0)
    moving = mi.Bool(take)
    while moving:
        up_parent = (pos - 1) >> 1
        up = push & (pos > 0)
        parent_d = heap_d.read(up_parent, up)
        up = up & (parent_d < d2)
        child = 2 * pos + 1
        down = replace & (child < ku)
        child_d = heap_d.read(child, down)
        has_second = down & (child + 1 < ku)
        second_d = heap_d.read(child + 1, has_second)
        second = has_second & (second_d > child_d)
        child = dr.select(second, child + 1, child)
        child_d = dr.select(second, second_d, child_d)
        down = down & (child_d > d2)
        source = dr.select(up, up_parent, child)
        move = moving & (up | down)
        heap_d.write(heap_d.read(source, move), pos, move)
        heap_i.write(heap_i.read(source, move), pos, move)
        pos = dr.select(move, source, pos)
        moving = move
    heap_d.write(d2, pos, take)
    heap_i.write(i, pos, take)


@dr.syntax
def _knn_walk(forest, p, k, contribution, result_type, r2max, active, walk, neighbours,
              accept, state):
    """Near-first while-while walk with a bounded max-heap per lane (see
    :func:`knn_query`). Returns (KnnResult with stats, dist2 list, index list)."""
    width = dr.width(p)
    heap_d = dr.alloc_local(mi.Float, k, dr.full(mi.Float, dr.inf, width))
    heap_i = dr.alloc_local(mi.UInt32, k, dr.full(mi.UInt32, 0xFFFFFFFF, width))
    r2 = dr.zeros(mi.Float, width) + r2max
    count = dr.zeros(mi.UInt32, width)
    ku = mi.UInt32(k)
    table, t, stop_u, bounds = walk_start(walk, width)
    active &= t < stop_u
    node_base, leaf_base, n_int, stride, span = tree_row(table, t, bounds, active)
    node = dr.zeros(mi.UInt32, width)
    going_down = dr.full(mi.Bool, True, width)
    nodes_visited = dr.zeros(mi.UInt32, width)
    photons_tested = dr.zeros(mi.UInt32, width)

    while dr.hint(active, label="partpm_knn_query"):
        # To the next leaf: nearer child first; the farther one if the ball still reaches it.
        at_leaf = mi.Bool(False)
        searching = mi.Bool(active)
        while dr.hint(searching, label="partpm_knn_descend"):
            if going_down:
                nodes_visited += 1
                if node < n_int:
                    split, axis = split_of(forest, node_base + node)
                    right = coordinate(p, axis) > split
                    node = 2 * node + 1 + dr.select(right, 1, 0)
                elif leaf_reached(forest, t, node_base, n_int, node, p, r2):
                    at_leaf = mi.Bool(True)
                    searching = mi.Bool(False)
                else:
                    going_down = mi.Bool(False)      # passed over, as a subtree the ball misses
            elif node == 0:
                t += 1
                if t < stop_u:
                    node_base, leaf_base, n_int, stride, span = tree_row(table, t, bounds)
                    going_down = mi.Bool(True)
                else:
                    searching = mi.Bool(False)
                    active = mi.Bool(False)
            else:
                parent = (node - 1) >> 1
                split, axis = split_of(forest, node_base + parent)
                diff = coordinate(p, axis) - split
                from_near = (node & 1) == dr.select(diff > 0, 0, 1)
                to_far = from_near & (dr.square(diff) <= r2)
                node = dr.select(to_far, dr.select((node & 1) == 1, node + 1, node - 1),
                                 parent)
                going_down = to_far

        # Test the leaf's photons: keep one if it beats the heap's worst (or there is room).
        i, end = leaf_run(forest, leaf_base, stride, span, n_int, node, at_leaf)
        while dr.hint(i < end, label="partpm_knn_scan"):
            photons_tested += 1
            d2 = dr.squared_norm(photon_position(forest, i) - p)
            room = count < ku
            take = dr.select(room, d2 <= r2, d2 < r2)
            if dr.hint(accept is not None, mode="scalar"):
                take &= accept(i, take, state)
            _heap_insert(heap_d, heap_i, count, ku, d2, i, take & room, take & ~room)
            count = dr.select(take & room, count + 1, count)
            r2 = dr.select(take & (count == ku), heap_d.read(0, take), r2)
            i += 1
        going_down = mi.Bool(False)

    if dr.hint(isinstance(r2max, float), mode="scalar"):
        # No cap: fewer than k photons exist, and r is the distance to the farthest found
        # (the heap's root), as Jensen's estimate with fewer than k photons has it.
        r2 = dr.select(count < ku, dr.select(count > 0, heap_d.read(0, count > 0), 0.0), r2)
    total = dr.zeros(result_type, width)
    if dr.hint(hasattr(state, "radius2"), mode="scalar"):
        # The callbacks see each query's final radius (a density kernel weighs by it).
        state.radius2 = mi.Float(r2)
    if dr.hint(contribution is not None, mode="scalar"):
        j = mi.UInt32(0)
        while j < count:
            total += contribution(heap_i.read(j, j < count), heap_d.read(j, j < count),
                                  mi.Bool(True), state)
            j += 1
    res = KnnResult(total, r2, count, QueryStats(nodes_visited, photons_tested,
                                                 mi.UInt32(count)))
    # The heap's entries are read only when asked for (k lazy variables each otherwise).
    dist2 = [heap_d.read(j) for j in range(k)] if neighbours else None
    index = [heap_i.read(j) for j in range(k)] if neighbours else None
    return res, dist2, index


def knn_neighbours(forest: Forest, points, k: int, max_radius=None):
    """NumPy front end of :func:`knn_query`, shaped like ``scipy.spatial.cKDTree.query``.

    Returns ``(distance, index)``, both ``(Q, k)`` and sorted by distance: ``index`` refers
    to the caller's photon order (the ``points`` given to :func:`build_forest`); a missing
    neighbour (fewer than k within ``max_radius``) has distance ``inf`` and index N.
    """
    q = np.asarray(points, dtype=np.float32).reshape(-1, 3)
    p = mi.Point3f(q[:, 0], q[:, 1], q[:, 2])
    _, d2, idx = knn_query(forest, p, k, max_radius=max_radius, neighbours=True)
    dr.eval(d2, idx)
    d2 = np.stack([a.numpy() for a in d2], axis=1).reshape(-1, k).astype(np.float64)
    idx = np.stack([a.numpy() for a in idx], axis=1).reshape(-1, k).astype(np.int64)
    order = np.argsort(d2, axis=1, kind="stable")
    d2 = np.take_along_axis(d2, order, axis=1)
    idx = np.take_along_axis(idx, order, axis=1)
    n = forest.size
    missing = ~np.isfinite(d2)
    idx = np.where(missing, n, forest.order[np.minimum(idx, max(n - 1, 0))] if n else n)
    return np.sqrt(d2), idx
