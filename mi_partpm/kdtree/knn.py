"""The k-nearest-neighbour query over a forest: the conventional estimate of eq. (1).

Two walks find the same neighbours. The own walk is the stackless while-while traversal of
:mod:`.radius`, visiting the nearer child first and passing over leaves whose box lies beyond
the current radius, with a per-lane max-heap of the k best candidates in local memory; each
lane walks alone, its radius shrinking as its heap fills. The grouped walk (the default)
gives the lanes of a packet one ball to share: a leader per group makes the own walk, its
k-th distance bounds its neighbours' first balls, the group walks those balls as the
fixed-radius query does while each lane keeps the photons inside its own, and a count per
distance bin picks the k nearest of those; lanes it cannot settle so walk on their own.
Queries are walked in Morton order and answered in the caller's.
"""
from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from .forest import Forest, as_points
from .radius import (GROUP_MARGIN, WALKS, QueryStats, _walk, check_callable, check_forest,
                     check_order, check_per_query, check_queries, checked_callback, coordinate,
                     group_balls, group_lanes, leaf_reached, leaf_run, order_queries, permute,
                     photon_payload, photon_position, radius_indices, radius_query,
                     result_type_errors, split_of, tree_row, typed_contribution, unpermute,
                     walk_start)

__all__ = ["knn_query", "KnnResult", "knn_neighbours", "radius_neighbours", "KNN_KEEP",
           "KNN_REACH", "KNN_SPREAD", "KNN_BINS"]

#: The grouped walk keeps up to this many times k of the photons within a lane's bound; a
#: lane that finds more is walked again on its own.
KNN_KEEP = 4
#: The largest k: Dr.Jit's local arrays hold fewer than 65536 entries (65536 is refused), and
#: a grouped walk keeps up to KNN_KEEP x k candidates per query.
MAX_K = 65536 // KNN_KEEP - 1
#: Bytes of the grouped walk's local arrays per lane, at most: on the LLVM backend they live
#: on the stack of the thread that runs the kernel, for every lane of a packet (16 on
#: AVX-512), and a thread's stack is 8 MB by default on Linux. With KNN_KEEP x k kept
#: candidates and the k nearest (40 bytes per k and lane), pm's kernel at k = 14,000 (9 MB)
#: ended the process with a segfault; this bound (4 MB for 16 lanes) keeps fewer candidates
#: for k above 6,553, and a lane that finds more walks again on its own.
LOCAL_BYTES = 1 << 18


def kept_candidates(k: int) -> int:
    """Candidates a lane of the grouped walk keeps for ``k`` neighbours: KNN_KEEP x k, fewer
    where the k nearest and they would exceed :data:`LOCAL_BYTES` (never fewer than k)."""
    return max(k, min(KNN_KEEP * k, LOCAL_BYTES // 8 - k))

#: A member's ball in the grouped walk: a leader's k-th distance plus this share of the way
#: to it. With 1 (and an accept test the same for every lane) the ball surely holds k
#: photons, by the triangle inequality; less usually does too and holds fewer photons to
#: sort, and a lane whose ball holds fewer than k walks again on its own.
KNN_REACH = 0.5

#: A lane whose first ball in the grouped walk is wider than this many times its leader's
#: k-th distance walks on its own straight away: its group's queries lie farther apart than
#: their neighbours, and its ball would hold too many photons to sort. (On the bench's
#: workloads 2 was faster than 1.5 and 3, and not slower than the own walk on queries ten
#: times sparser.)
KNN_SPREAD = 2.0

#: Distance bins of the grouped walk's selection: the k-th distance's bin is found by
#: counting, and only that bin's photons go through a heap.
KNN_BINS = 32


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


def check_k(k):
    """A ValueError unless ``k`` is an integer in [1, :data:`MAX_K`]."""
    if not isinstance(k, (int, np.integer)) or isinstance(k, bool) or not 1 <= k <= MAX_K:
        raise ValueError(f"k must be an integer in [1, {MAX_K}], got {k!r} (a query keeps up "
                         f"to {KNN_KEEP} k candidates in a local array of fewer than 65536)")


def knn_query(forest: Forest, p, k: int, contribution=None, result_type=None,
              max_radius=None, active=True, maps=None, with_stats: bool = False,
              neighbours: bool = False, accept=None, state=None, order: str = "morton",
              walk: str = "group", with_payload: bool = False):
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
        radius first (what a density kernel weighs by), and the object passed in holds
        them afterwards, in the caller's order (as the result's ``radius2``), at any count
        and order of queries. With ``with_payload`` it takes a
        fifth argument, the photon's 32-bit payload (``mi.UInt32``), as for
        :func:`~.radius.radius_query` (read per neighbour: the neighbours are chosen
        before any contribution is evaluated).
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
    walk : str
        "group" (default): a leader's bound first, then a fixed-radius walk in groups and a
        selection (see Notes); "own": each lane walks alone with its shrinking heap (what
        one query alone runs). Both find the same neighbours but where several lie at
        exactly the k-th distance (which of them is taken depends on the order they are
        met). Below :data:`~.radius.SORT_FROM` queries with ``order="morton"`` (which are
        then not sorted, so a group's lanes lie apart) take the own walk.

    Returns
    -------
    KnnResult, or (KnnResult, dist2 list, index list) with ``neighbours=True`` (the lists
    unsorted: a heap, or for the grouped walk the photons of the nearer bins and then a heap;
    :func:`knn_neighbours` sorts them). With ``with_stats``, the counts are those of the
    walks that ran for the lane: for a lane the group walk settled, the shared ball's nodes
    and the photons it tested; for a lane that walked again on its own, both walks'.

    Notes
    -----
    The own walk is the stackless traversal of :func:`~.radius.radius_query`, visiting the
    nearer child first, with a per-lane max-heap of the k best candidates in local memory.
    The search radius starts at ``max_radius`` and shrinks to the heap's largest distance
    once it holds k photons, so far subtrees are skipped as in Jensen's ``locate_photons``.
    Photons at exactly the current radius are not taken once the heap is full (the first
    found stays).

    The grouped walk (:func:`_knn_grouped`) gives the lanes a ball to share. One query per
    group (:data:`~.radius.GROUP_LANES` side by side in walking order), its leader, makes
    the own walk, and its answer is final. A leader's k-th distance plus a member's distance
    to it would bound the member's k-th distance (the triangle inequality, where every lane
    accepts the same photons); the member's first ball takes :data:`KNN_REACH` of that
    distance instead, the least over its group's leader and those of the groups on either
    side, or its cap where that is less. A member whose ball is more than
    :data:`KNN_SPREAD` times that leader's radius walks on its own straight away. The others
    walk their balls with the group, as :func:`~.radius.radius_query` does, and keep the
    photons inside; counting them in :data:`KNN_BINS` distance bins finds the bin of the
    k-th, and a heap sorts only that bin. A lane whose ball holds fewer than k photons
    (below its cap) or more than it keeps (:func:`kept_candidates`: :data:`KNN_KEEP` x k up
    to k = 6,553) walks again on its own, so the neighbours are exact either way.
    """
    check_forest(forest)
    check_k(k)
    if walk not in WALKS:
        raise ValueError(f"walk must be one of {', '.join(repr(w) for w in WALKS)}, got "
                         f"{walk!r}")
    result_type = mi.Float if result_type is None else result_type
    if contribution is not None:
        check_callable(contribution, "contribution")
    accept = checked_callback(accept, "accept")
    p = as_points(p, "p")
    width = dr.width(p)
    active = check_per_query(active, "active", width, radius=False)
    if max_radius is not None:
        max_radius = check_per_query(max_radius, "max_radius", width, active=active)
    p = check_queries(p, "p", active)
    check_order(order)
    table = forest.walk_table(maps)    # refuses a bad range, an empty forest's too
    if max_radius is None:
        r2max = dr.inf
    elif isinstance(max_radius, (int, float)):
        # Squared in float32, as the radius query squares its radius (in float64 and then
        # rounded, a photon at exactly r could be in one query and not the other).
        r2max = dr.square(dr.opaque(mi.Float, float(max_radius)))   # no recompile per value
    else:
        r2max = dr.square(mi.Float(max_radius))
    if forest.size == 0 or width == 0:
        zeros = dr.zeros(mi.UInt32, width)
        stats = QueryStats(zeros, mi.UInt32(zeros), mi.UInt32(zeros)) if with_stats else None
        radius2 = dr.zeros(mi.Float, width)
        if width and max_radius is not None:     # the cap, as when fewer than k are found
            radius2 = radius2 + r2max
        res = KnnResult(dr.zeros(result_type, width), radius2, mi.UInt32(zeros), stats)
        _hand_back_radii(state, radius2)
        if neighbours:
            return (res, [dr.full(mi.Float, dr.inf, width)] * k,
                    [dr.full(mi.UInt32, 0xFFFFFFFF, width)] * k)
        return res
    if with_payload and contribution is not None:
        own = checked_callback(contribution, "contribution")

        def contribution(i, d2, a, s):
            return own(i, d2, a, s, photon_payload(forest, i, a))
    perm = order_queries(p, width, order)
    active = dr.full(mi.Bool, True, width) & mi.Bool(active)
    if not isinstance(r2max, float):
        r2max = permute(dr.zeros(mi.Float, width) + r2max, perm, width)
    run = _knn_grouped if walk == "group" and (perm is not None or order == "given") \
        else _knn_walk
    if contribution is not None:
        contribution = typed_contribution(contribution, result_type)
    with result_type_errors():
        res, d2, idx = run(forest, permute(p, perm, width), int(k), contribution, result_type,
                           r2max, permute(active, perm, width), table,
                           neighbours, accept, permute(state, perm, width))
    res = KnnResult(*[unpermute(v, perm, width) for v in (res.total, res.radius2, res.count)],
                    QueryStats(*[unpermute(v, perm, width) for v in (
                        res.stats.nodes_visited, res.stats.photons_tested,
                        res.stats.photons_found)]) if with_stats else None)
    if perm is not None:
        # The walk set the radii on the sorted copy of the state: the caller's gets them too.
        _hand_back_radii(state, res.radius2)
    if neighbours:
        return res, [unpermute(v, perm, width) for v in d2], \
            [unpermute(v, perm, width) for v in idx]
    return res


def _hand_back_radii(state, radius2):
    """Set the caller's ``state.radius2`` (a state of Python's own with that field)."""
    if hasattr(state, "radius2") and not type(state).__module__.startswith("mitsuba"):
        state.radius2 = mi.Float(radius2)


@dr.syntax
def _heap_insert(heap_d, heap_i, count, ku, d2, i, push, replace, base=0):
    """Put ``(d2, i)`` into each lane's max-heap of ``ku`` entries (``count`` of them used),
    held in the local arrays from entry ``base`` on.

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
        parent_d = heap_d.read(base + up_parent, up)
        up = up & (parent_d < d2)
        child = 2 * pos + 1
        down = replace & (child < ku)
        child_d = heap_d.read(base + child, down)
        has_second = down & (child + 1 < ku)
        second_d = heap_d.read(base + child + 1, has_second)
        second = has_second & (second_d > child_d)
        child = dr.select(second, child + 1, child)
        child_d = dr.select(second, second_d, child_d)
        down = down & (child_d > d2)
        source = dr.select(up, up_parent, child)
        move = moving & (up | down)
        heap_d.write(heap_d.read(base + source, move), base + pos, move)
        heap_i.write(heap_i.read(base + source, move), base + pos, move)
        pos = dr.select(move, source, pos)
        moving = move
    heap_d.write(d2, base + pos, take)
    heap_i.write(i, base + pos, take)


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
    active = mi.Bool(active) & (t < stop_u)        # a new array: the caller's stays
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
    stats = QueryStats(nodes_visited, photons_tested, mi.UInt32(count))
    return _answer(heap_d, heap_i, count, r2, stats, k, contribution, result_type,
                   neighbours, state)


@dr.syntax
def _answer(near_d, near_i, count, r2, stats, k, contribution, result_type, neighbours,
            state):
    """The walks' result from the ``count`` neighbours in the local arrays ``near_d``,
    ``near_i``: (KnnResult, dist2 list, index list)."""
    width = dr.width(count)
    total = dr.zeros(result_type, width)
    if dr.hint(hasattr(state, "radius2"), mode="scalar"):
        # The callbacks see each query's final radius (a density kernel weighs by it).
        state.radius2 = mi.Float(r2)
    if dr.hint(contribution is not None, mode="scalar"):
        j = dr.zeros(mi.UInt32, width)
        while j < count:
            total += contribution(near_i.read(j, j < count), near_d.read(j, j < count),
                                  mi.Bool(True), state)
            j += 1
    res = KnnResult(total, r2, count, stats)
    # The entries are read only when asked for (k lazy variables each otherwise).
    dist2 = [near_d.read(j) for j in range(k)] if neighbours else None
    index = [near_i.read(j) for j in range(k)] if neighbours else None
    return res, dist2, index


def _bin(d2, scale):
    """The selection's distance bin of the squared distances ``d2``."""
    return mi.UInt32(dr.minimum(d2 * scale, KNN_BINS - 1))


def _kth_bin(kept_d, kept, scale, k):
    """The bin of the k-th smallest of each lane's ``kept`` squared distances, and how many
    lie in the bins before it; (KNN_BINS, all of them) where fewer than k were kept. The
    counts are kept in registers (a local array indexed per lane costs a scatter each)."""
    width = dr.width(kept)

    def body(j, counts):
        b = _bin(kept_d.read(j, j < kept), scale)
        return j + 1, tuple(c + dr.select(b == u, 1, 0) for u, c in enumerate(counts))

    _, counts = dr.while_loop(
        (dr.zeros(mi.UInt32, width), tuple(dr.zeros(mi.UInt32, width)
                                           for _ in range(KNN_BINS))),
        lambda j, counts: j < kept, body, label="partpm_knn_bins")
    star = dr.full(mi.UInt32, KNN_BINS, width)
    below = dr.zeros(mi.UInt32, width)
    before = dr.zeros(mi.UInt32, width)
    for u, c in enumerate(counts):
        here = (star == KNN_BINS) & (before + c >= k)
        star = dr.select(here, u, star)
        below = dr.select(here, before, below)
        before += c
    return star, dr.select(star == KNN_BINS, before, below)


@dr.syntax
def _select(kept_d, kept_i, found, keep, walk2, k, capped, cap2, contribution, result_type,
            neighbours, state):
    """The k nearest of the photons a lane kept (``found`` of them within ``walk2``, the
    first ``keep`` kept), and the result: counts per distance bin find the k-th's bin
    (:func:`_kth_bin`); a heap takes the nearest of that bin's photons, the bins before it
    are all taken. Returns (KnnResult without stats, dist2 list, index list), the lists (with
    ``neighbours``) the bins before in their order, then the heap."""
    width = dr.width(found)
    kept = dr.minimum(found, keep)
    scale = dr.select(walk2 > 0, KNN_BINS / walk2, 0.0)
    star, below = _kth_bin(kept_d, kept, scale, k)
    room = dr.select(star < KNN_BINS, k - below, 0)
    near_d = dr.alloc_local(mi.Float, k, dr.full(mi.Float, dr.inf, width))
    near_i = dr.alloc_local(mi.UInt32, k, dr.full(mi.UInt32, 0xFFFFFFFF, width))
    heaped = dr.zeros(mi.UInt32, width)
    j = dr.zeros(mi.UInt32, width)
    while (j < kept) & (star < KNN_BINS):
        d2 = kept_d.read(j)
        if _bin(d2, scale) == star:
            push = heaped < room
            replace = ~push & (d2 < near_d.read(dr.minimum(below, k - 1)))
            _heap_insert(near_d, near_i, heaped, room, d2, kept_i.read(j), push, replace,
                         below)
            heaped = dr.select(push, heaped + 1, heaped)
        j += 1
    count = below + heaped
    r2 = dr.select(star < KNN_BINS, near_d.read(dr.minimum(below, k - 1)),
                   cap2 if capped else dr.zeros(mi.Float, width))
    if dr.hint(hasattr(state, "radius2"), mode="scalar"):
        state.radius2 = mi.Float(r2)            # what a density kernel weighs by
    total = dr.zeros(result_type, width)
    taken = dr.zeros(mi.UInt32, width)
    j = dr.zeros(mi.UInt32, width)
    while j < kept:
        d2 = kept_d.read(j)
        if _bin(d2, scale) < star:
            i = kept_i.read(j)
            if dr.hint(contribution is not None, mode="scalar"):
                total += contribution(i, d2, mi.Bool(True), state)
            if dr.hint(neighbours, mode="scalar"):
                near_d.write(d2, taken)
                near_i.write(i, taken)
                taken += 1
        j += 1
    if dr.hint(contribution is not None, mode="scalar"):
        j = mi.UInt32(below)
        while j < count:
            total += contribution(near_i.read(j), near_d.read(j), mi.Bool(True), state)
            j += 1
    dist2 = [near_d.read(j) for j in range(k)] if neighbours else None
    index = [near_i.read(j) for j in range(k)] if neighbours else None
    return KnnResult(total, r2, count), dist2, index


def _knn_grouped(forest, p, k, contribution, result_type, r2max, active, walk, neighbours,
                 accept, state):
    """The grouped walk of :func:`knn_query` (its Notes): each group's leader walks on its
    own (its answer is final), a bound from the leaders, a fixed-radius walk in groups that
    keeps the photons within it, a selection, and the own walk for the lanes it did not
    settle. Returns what :func:`_knn_walk` does."""
    width = dr.width(p)
    size = group_lanes(p)
    capped = not isinstance(r2max, float)
    cap2 = dr.zeros(mi.Float, width) + r2max
    finite = dr.isfinite(p.x) & dr.isfinite(p.y) & dr.isfinite(p.z)

    # The leaders: the first active lane with a finite point of each group; their own walk.
    groups = -(-width // size)
    lane = dr.arange(mi.UInt32, groups * size)
    last = dr.opaque(mi.UInt32, width - 1)       # a literal would compile anew per width
    usable = dr.gather(mi.Bool, active & finite, dr.minimum(lane, last)) & (lane <= last)
    first = dr.block_reduce(dr.ReduceOp.Min, dr.select(usable, lane, 0xFFFFFFFF), size)
    led = first <= last
    leader = dr.minimum(first, last)
    lead = _knn_walk(forest, dr.gather(mi.Point3f, p, leader), k, contribution, result_type,
                     dr.gather(mi.Float, r2max, leader) if capped else r2max, mi.Bool(led),
                     walk, neighbours, accept, permute(state, leader, width))
    full = led & (lead[0].count >= k)             # its radius is a k-th distance
    dr.eval(lead, full)

    # Each member's first ball: a leader's k-th distance plus a share of the way to it, the
    # least of its group's leader and those of the groups on either side (leaders that found
    # k), or its cap where that is less. A lane whose ball is more than KNN_SPREAD times
    # that leader's radius walks on its own straight away; a ball at the cap is walked as
    # it is.
    g = dr.arange(mi.UInt32, width) // size
    lead_r = dr.sqrt(lead[0].radius2)
    bound = dr.full(mi.Float, dr.inf, width)
    near_r = dr.zeros(mi.Float, width)
    for h in (g, dr.maximum(g, 1) - 1, dr.minimum(g + 1, groups - 1)):
        r_h = dr.gather(mi.Float, lead_r, h)
        via = r_h + KNN_REACH * dr.norm(p - dr.gather(mi.Point3f, p,
                                                        dr.gather(mi.UInt32, leader, h)))
        better = dr.gather(mi.Bool, full, h) & (via < bound)
        bound = dr.select(better, via, bound)
        near_r = dr.select(better, r_h, near_r)
    bound *= GROUP_MARGIN
    is_leader = (dr.gather(mi.UInt32, leader, g) == dr.arange(mi.UInt32, width)) & \
        dr.gather(mi.Bool, led, g)
    walk2 = dr.minimum(dr.square(bound), cap2)
    at_cap = dr.square(bound) >= cap2
    grouped = active & finite & ~is_leader & dr.isfinite(walk2) & \
        (at_cap | (walk2 <= dr.square(KNN_SPREAD * near_r)))
    dr.eval(walk2, at_cap, grouped, is_leader)   # once, not in each of group_balls' kernels
    ball = group_balls(p, dr.sqrt(walk2) * GROUP_MARGIN, grouped, width)

    # The walk of the bound, in groups, keeping the photons inside; the selection.
    keep = kept_candidates(k)
    kept_d = dr.alloc_local(mi.Float, keep)
    kept_i = dr.alloc_local(mi.UInt32, keep)
    _, walked = _walk(forest, p, walk2, ball, None, mi.Float, grouped, walk, True, accept,
                      state, collect=(kept_d, kept_i))
    found = walked.photons_found
    settled = grouped & (found <= keep) & ((found >= k) | at_cap)
    # Lanes that will walk again select nothing (no contribution is evaluated for them).
    res, dist2, index = _select(kept_d, kept_i, dr.select(settled, found, 0), keep, walk2, k,
                                capped, cap2, contribution, result_type, neighbours, state)
    res.stats = QueryStats(walked.nodes_visited, walked.photons_tested, res.count)
    rest = active & ~settled & ~is_leader
    dr.eval(res.total, res.radius2, res.count, res.stats.nodes_visited,
            res.stats.photons_tested, rest, dist2, index)

    # The leaders' answers, and the own walk of the lanes the group walk did not settle.
    _put((res, dist2, index), lead, leader, active=led)
    lanes = dr.compress(rest)
    if dr.width(lanes) > 0:
        _put((res, dist2, index), _knn_walk(
            forest, dr.gather(mi.Point3f, p, lanes), k, contribution, result_type,
            dr.gather(mi.Float, r2max, lanes) if capped else r2max,
            dr.full(mi.Bool, True, dr.width(lanes)), walk, neighbours, accept,
            permute(state, lanes, width)), lanes)
    res.stats.photons_found = res.count
    if hasattr(state, "radius2"):
        state.radius2 = mi.Float(res.radius2)     # as the own walk leaves it
    return res, dist2, index


def _put(into, other, lanes, active=True):
    """Write the answers ``other`` (a walk's (KnnResult, dist2, index)) into the lanes
    ``lanes`` of ``into``, where ``active``; the traversal counts add up."""
    (res, dist2, index), (theirs, d2, idx) = into, other
    for name in ("total", "radius2", "count"):
        dr.scatter(getattr(res, name), getattr(theirs, name), lanes, active)
    dr.scatter_add(res.stats.nodes_visited, theirs.stats.nodes_visited, lanes, active,
                   mode=dr.ReduceMode.NoConflicts)
    dr.scatter_add(res.stats.photons_tested, theirs.stats.photons_tested, lanes, active,
                   mode=dr.ReduceMode.NoConflicts)
    for mine, value in zip((dist2 or []) + (index or []), (d2 or []) + (idx or [])):
        dr.scatter(mine, value, lanes, active)
    dr.eval(res.total, res.radius2, res.count, res.stats.nodes_visited,
            res.stats.photons_tested, dist2, index)


def knn_neighbours(forest: Forest, points, k: int, max_radius=None):
    """NumPy front end of :func:`knn_query`, answering as ``scipy.spatial.cKDTree.query``
    with an integer k does, but always shaped ``(Q, k)``: scipy drops the k axis for k = 1
    and the query axis for one (3,) point, and takes a list of k; this does neither.

    Returns ``(distance, index)``, both ``(Q, k)`` and sorted by distance: ``index`` refers
    to the caller's photon order (the ``points`` given to :func:`build_forest`); a missing
    neighbour (fewer than k within ``max_radius``) has distance ``inf`` and index N.

    Differences from scipy: ``points`` must be finite, with coordinates within +-1e18 (a
    ValueError otherwise: squared float32 distances overflow beyond); a neighbour
    at exactly ``max_radius`` counts (scipy's ``distance_upper_bound`` is strict); positions
    are float32, so points closer than float32 resolves (about 1e-7 of their magnitude)
    coincide. The k neighbours are k separate device arrays: their cost grows faster than k
    (k = 1000 took seconds for 10 queries); sums over them (:func:`knn_query` with a
    ``contribution``) do not, and neither maps, masks nor the walking order are taken here
    (:func:`knn_query` with ``neighbours=True`` takes them). A k above the forest's N
    photons costs what k = N does: the query asks for N and the rest is padding (asking
    for all of 100 photons with k = 3400 took 12.6 s before it did).
    """
    p = check_queries(points, "points")
    return _sorted_neighbours(forest, p, k, max_radius)


def _sorted_neighbours(forest, p, k, max_radius, maps=None):
    """The k nearest photons of every query (within ``max_radius``), as NumPy (distance,
    index) arrays of shape (Q, k), nearest first; index in the caller's photon order, N
    (and distance inf) for a missing one. No more than the forest's photons are asked for:
    the walk's cost follows the k it keeps, and the columns past them are missing ones."""
    check_forest(forest)
    check_k(k)
    kept = max(1, min(int(k), forest.size))
    _, d2, idx = knn_query(forest, p, kept, max_radius=max_radius, neighbours=True, maps=maps)
    dr.eval(d2, idx)
    d2 = np.stack([a.numpy() for a in d2], axis=1).reshape(-1, kept).astype(np.float64)
    idx = np.stack([a.numpy() for a in idx], axis=1).reshape(-1, kept).astype(np.int64)
    if kept < k:
        pad = ((0, 0), (0, int(k) - kept))
        d2 = np.pad(d2, pad, constant_values=np.inf)
        idx = np.pad(idx, pad, constant_values=0xFFFFFFFF)
    order = np.argsort(d2, axis=1, kind="stable")
    d2 = np.take_along_axis(d2, order, axis=1)
    idx = np.take_along_axis(idx, order, axis=1)
    n = forest.size
    missing = ~np.isfinite(d2)
    idx = np.where(missing, n, forest.order[np.minimum(idx, max(n - 1, 0))] if n else n)
    return np.sqrt(d2), idx


def radius_neighbours(forest: Forest, points, r, return_length: bool = False, maps=None):
    """NumPy front end of the fixed-radius query, as ``scipy.spatial.cKDTree.query_ball_point``
    answers: for each of the Q ``points``, the photons within ``r`` (a scalar or one radius
    per point; a photon at exactly r is in), as a list of Q int64 arrays of indices into the
    caller's photon order (the ``points`` given to :func:`build_forest`), each sorted (scipy
    answers with an object array of lists); with ``return_length``, their counts (a (Q,)
    int64 array), which are the lists' lengths. ``maps``: only maps
    ``first .. stop-1``, as for :func:`~.radius.radius_query`.

    The counts are one :func:`~.radius.radius_query`; a second walk writes each query's
    photons into its run of one array (:func:`~.radius.radius_indices`), so the cost is
    that of two sums plus the photons found, however many one query finds. Unlike scipy:
    positions are float32 (a photon within float32 rounding of the sphere may be in or out);
    one (3,) point is taken as a (1, 3) array and answered with a list of one.
    """
    check_forest(forest)
    p = check_queries(points, "points")
    width = dr.width(p)
    counts = radius_query(forest, p, r, lambda i, d2, a, s: mi.UInt32(1),
                          result_type=mi.UInt32, maps=maps)
    lengths = counts.numpy().astype(np.int64) if width else np.zeros(0, np.int64)
    if return_length:
        return lengths
    if not lengths.any():
        return [np.zeros(0, np.int64) for _ in range(width)]
    found = forest.order[radius_indices(forest, p, r, lengths, maps)]
    query = np.repeat(np.arange(width), lengths)
    found = found[np.lexsort((found, query))]          # each query's run, sorted
    return np.split(found, np.cumsum(lengths)[:-1])
