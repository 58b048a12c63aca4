"""The fixed-radius query over a forest: the walk behind eq. (2)'s density estimate.

One lane per query point walks the implicit trees of the maps it is asked for, one tree after
the other (a tree that several maps share is walked once, and the runs of those maps in each
leaf it reaches are scanned in turn: :class:`~.forest.Forest`), with no per-lane stack: it
descends into every child whose half-space its walking ball reaches and climbs back through
parents. The walk is "while-while": an inner loop moves
to the next leaf the ball reaches, a second inner loop tests that leaf's photons, so the lanes
of a SIMD packet test photons together instead of interleaving node steps and photon tests.
Every photon within the radius is passed to a callback with its squared distance, and the
callback's results are summed.

Queries are put in Morton order first (:func:`order_queries`), and the results come back in
the caller's order. Lanes side by side in that order then walk as a group
(:func:`group_balls`): they choose nodes by one ball around all of their balls, so a SIMD
packet descends and scans its leaves together instead of waiting for each lane's own path,
and each lane tests the photons against its own ball. A leaf whose bounding box the walking
ball misses is passed over like a subtree (:func:`leaf_reached`), and a lane whose own ball
misses the box of a leaf its group scans tests none of its photons: a packet scans a leaf
only for the lanes that need it, and none at all when no lane does.
"""
from __future__ import annotations

import functools
import platform
from contextlib import contextmanager
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from .forest import RECORD_FLOATS, Forest, as_points, check_coordinates, morton_codes

__all__ = ["radius_query", "QueryStats", "order_queries", "group_balls", "group_lanes",
           "radius_array", "ORDERS", "WALKS", "CallbackError", "ResultTypeError"]

#: Query orders: "morton" sorts the query points along a Z-order curve before the walk (and
#: returns results in the caller's order); "given" walks them as they come.
ORDERS = ("morton", "given")

#: Photons tested per iteration of a leaf's scan loop: fewer iterations, each testing that
#: many photons side by side, spend less on the loop's own bookkeeping per photon.
SCAN_UNROLL = 2

#: Below this many queries the sort costs more than it saves.
SORT_FROM = 4096

#: Walks: "group", lanes side by side walk the trees with one ball around their balls
#: (:func:`group_balls`); "own", every lane walks with its own ball (the traversal one query
#: alone makes: what a scalar processing element runs, the workloads hwsim replays).
WALKS = ("group", "own")

#: Lanes that walk one tree path together, per backend: a warp on CUDA; on the LLVM backend
#: None, one SIMD packet (:func:`packet_lanes`). On the room workload of ``partpm bench``,
#: Morton-sorted, with AVX-512 packets of 16 lanes, groups of 4 / 8 / 16 lanes answered in
#: 0.39 / 0.35 / 0.31 s; with AVX2 packets of 8, groups of 8 beat 4 and 16 (0.67 against 0.80
#: and 0.75 s): lanes of one packet that walk two paths wait for each other.
GROUP_LANES = {"llvm": None, "cuda": 32}

#: A group walks together while its ball, around all of its queries' balls, has a radius of
#: at most this many times the largest of theirs; a wider group's lanes walk on their own.
GROUP_SPREAD = 2.0

#: A group's radius is widened by this factor, so that the float32 rounding of the distances
#: it is made of (a few units in the last place) never leaves a member's ball sticking out:
#: the group's plane and box tests then pass wherever the member's own would.
GROUP_MARGIN = 1.0 + 2.0 ** -20


@dataclass
class QueryStats:
    """Traversal counts per query point: the workload of one query on all maps searched."""

    nodes_visited: object
    photons_tested: object
    photons_found: object


def coordinate(p, axis):
    """The ``axis`` coordinate (0, 1 or 2, per lane) of the points ``p``."""
    return dr.select(axis == 0, p.x, dr.select(axis == 1, p.y, p.z))


def photon_record(forest: Forest, index, active=True):
    """Positions and 32-bit payloads (``mi.UInt32``) of the photons at tree-order ``index``
    (one 16-byte load each)."""
    rec = dr.gather(mi.Vector4f, forest.records, index, active)
    return mi.Point3f(rec.x, rec.y, rec.z), dr.reinterpret_array(mi.UInt32, rec.w)


def photon_position(forest: Forest, index, active=True) -> mi.Point3f:
    """Positions of the photons at tree-order ``index`` (one 16-byte load each)."""
    return photon_record(forest, index, active)[0]


def photon_payload(forest: Forest, index, active=True):
    """The 32-bit payloads (``mi.UInt32``) of the photons at tree-order ``index``."""
    return dr.reinterpret_array(mi.UInt32, dr.gather(mi.Float, forest.records,
                                                     RECORD_FLOATS * index + 3, active))


def check_queries(p, name: str = "p", active=True) -> mi.Point3f:
    """The query points ``p`` as ``mi.Point3f`` (array-like (Q, 3) too,
    :func:`~.forest.as_points`), every ``active`` one finite with coordinates within
    +-:data:`~.forest.MAX_COORD`: a ValueError naming ``name`` otherwise (an inactive lane may
    hold anything)."""
    p = as_points(p, name)
    check_coordinates(p, name, active)
    return p


#: The least nonzero radius: a squared distance is the sum of three squared float32
#: differences, and where those leave float32's normal range (below 1.2e-38) they flush to
#: zero. At 1e-15 that error is below 1e-7 of r^2; at 1e-18, where r^2 itself was still
#: normal, photons up to 1.0001 r were found.
MIN_RADIUS = 1e-15


def below_min_radius() -> str:
    """How the messages that refuse a radius below :data:`MIN_RADIUS` say why."""
    return f"below {MIN_RADIUS:g}, the least radius whose squared distances float32 resolves"


def check_per_query(value, name: str, width: int, radius: bool = True, active=True):
    """A scalar or one value per query (``width``, or 1): a radius (``radius``: 0 or in
    [:data:`MIN_RADIUS`, inf], NaN not, in every ``active`` lane) or a mask. Raises a
    ValueError naming ``name``."""
    bound = f"{name} must be 0 or in [{MIN_RADIUS:g}, inf] (inf for no bound)"
    if isinstance(value, (bool, int, float, np.integer, np.floating, np.bool_)):
        is_bool = isinstance(value, (bool, np.bool_))
        if not radius:                       # a mask: true or false
            if not is_bool:
                raise ValueError(f"{name} must be true or false, or one bool per query point, "
                                 f"got {value!r}")
            return value
        if is_bool:
            raise ValueError(f"{bound}, got {value!r} (a bool is no radius)")
        try:
            ok = float(value) == 0 or float(value) >= MIN_RADIUS
        except OverflowError:                # an int beyond a float: not a radius
            raise ValueError(f"{bound}, got an integer too large for a float") from None
        if not ok:
            raise ValueError(f"{bound}, got {value!r}")
        return value
    if not dr.is_array_v(value):             # NumPy arrays, lists
        host = np.asarray(value)
        kinds = "iuf" if radius else "b"
        if host.dtype.kind not in kinds or host.ndim > 1:
            want = "a number or one per query point (shape (Q,))" if radius else \
                "true or false, or one bool per query point (shape (Q,))"
            got = f"shape {host.shape}, dtype {host.dtype}" if host.ndim else repr(value)
            raise ValueError(f"{name} must be {want}, got {got:.80}")
        value = (mi.Float if radius else mi.Bool)(host.reshape(-1))
    elif not radius and not isinstance(value, mi.Bool):
        raise ValueError(f"{name} must be true or false, or a mi.Bool per query point, got "
                         f"{type(value).__name__}")
    elif radius and (dr.depth_v(value) != 1 or dr.type_v(value) == dr.VarType.Bool):
        raise ValueError(f"{name} must be a number or one per query point (a mi.Float), got "
                         f"{type(value).__name__}")
    n = dr.width(value)
    if n not in (1, width):
        raise ValueError(f"{name} has {n} entries for {width} query points (give one, or "
                         f"one per query)")
    if radius and n and width:
        r = mi.Float(value)
        if not bool(dr.all((r == 0) | (r >= MIN_RADIUS) | ~mi.Bool(active))[0]):
            raise ValueError(f"{bound} for every query; a negative, NaN or smaller radius "
                             f"was given")
    return value


class CallbackError(TypeError):
    """A query's callback cannot be called as the query calls it (its arguments), or what it
    returned cannot be used."""


class ResultTypeError(CallbackError):
    """A query's ``contribution`` returned a value that its ``result_type`` cannot hold."""


def _arguments_fit(f, args, name: str):
    """A :class:`CallbackError` naming ``name`` unless ``f`` takes ``args`` (checked on the
    first call only: the walk calls it with the same arguments every time)."""
    import inspect
    try:
        signature = inspect.signature(f)
    except (TypeError, ValueError):          # a builtin without a signature: just call it
        return
    try:
        signature.bind(*args)
    except TypeError as e:
        raise CallbackError(f"{name} is called with {len(args)} arguments ({CALLBACK_ARGS[name]}"
                            f"{', payload' if len(args) == 5 else ''}), and cannot take "
                            f"them: {e}") from None


#: What the callbacks are given, by name.
CALLBACK_ARGS = {"contribution": "index, dist2, active, state", "accept": "index, active, state"}


def checked_callback(f, name: str):
    """``f`` (None stays None), refused at once unless callable, and on its first call
    unless it takes the arguments the walk gives it (:class:`CallbackError`)."""
    if f is None:
        return None
    check_callable(f, name)
    checked = []

    def call(*args):
        if not checked:
            _arguments_fit(f, args, name)
            checked.append(True)
        return f(*args)
    return call


def typed_contribution(contribution, result_type):
    """``contribution``, checking that each value it returns adds to ``result_type`` (a
    vector, e.g. a colour, does not add to a scalar total): a :class:`ResultTypeError` naming
    ``result_type`` otherwise, which :func:`result_type_errors` passes on out of the walk's
    loop (inside, Dr.Jit reported only that the loop's state changed type)."""
    contribution = checked_callback(contribution, "contribution")

    def call(*args):
        value = contribution(*args)
        if dr.is_array_v(value) and type(value) is not result_type and \
                dr.depth_v(value) > dr.depth_v(result_type):
            raise ResultTypeError(
                f"contribution returned {type(value).__name__}, which result_type = "
                f"{result_type.__name__} cannot hold: pass result_type="
                f"{type(value).__name__} (or return {result_type.__name__})")
        return value
    return call


@contextmanager
def result_type_errors():
    """Raise the :class:`CallbackError` (a :class:`ResultTypeError`, or a callback that
    cannot take its arguments) that a walk's loop met as itself, not wrapped in Dr.Jit's
    error of the loop."""
    try:
        yield
    except RuntimeError as e:
        cause, seen = e, set()
        while cause is not None and id(cause) not in seen and \
                not isinstance(cause, CallbackError):
            seen.add(id(cause))
            cause = cause.__cause__ or cause.__context__
        if isinstance(cause, CallbackError):
            raise type(cause)(str(cause)) from None
        raise


def check_forest(forest):
    """A TypeError unless ``forest`` is a :class:`~.forest.Forest`."""
    if not isinstance(forest, Forest):
        raise TypeError(f"forest must be a Forest (made by build_forest), got "
                        f"{type(forest).__name__}")


def check_order(order: str):
    """A ValueError unless ``order`` is one of :data:`ORDERS`."""
    if order not in ORDERS:
        raise ValueError(f"order must be one of {', '.join(repr(o) for o in ORDERS)}, got "
                         f"{order!r}")


def order_queries(p, width: int, order: str):
    """The permutation that puts the queries in walking order, or None to keep theirs."""
    check_order(order)
    if order == "given" or width < SORT_FROM:
        return None
    return dr.argsort(morton_codes(p))


def permute(value, perm, width):
    """``value`` (an array of ``width`` lanes, a PyTree of them, a scalar or None) in the
    order ``perm``; anything that is not per-lane passes through."""
    if perm is None or value is None or isinstance(value, (bool, int, float)):
        return value
    if dr.is_array_v(value) and dr.width(value) != width:
        return value
    if dr.is_array_v(value):
        return dr.gather(type(value), value, perm)
    if hasattr(value, "DRJIT_STRUCT"):
        if type(value).__module__.startswith("mitsuba"):
            return dr.gather(type(value), value, perm)      # a struct Mitsuba binds
        out = type(value)()
        for k in value.DRJIT_STRUCT:
            setattr(out, k, permute(getattr(value, k), perm, width))
        return out
    if isinstance(value, (tuple, list)):
        return type(value)(permute(v, perm, width) for v in value)
    if isinstance(value, dict):
        return {k: permute(v, perm, width) for k, v in value.items()}
    return value


def packet_lanes(cpu_flags=None) -> int:
    """Lanes of a SIMD packet of Dr.Jit's LLVM backend on this machine, by the rule Dr.Jit
    applies to the host CPU's features: 16 with AVX-512VL, 8 with AVX, 4 with SSE 4.2 or
    on ARM. ``cpu_flags``: the flags to read (default: this machine's, from
    ``/proc/cpuinfo``; 8 where they cannot be read)."""
    if cpu_flags is None:
        if platform.machine().lower() in ("arm64", "aarch64"):
            return 4
        try:
            with open("/proc/cpuinfo") as f:
                line = next((ln for ln in f if ln.startswith("flags")), "")
        except OSError:
            return 8
        cpu_flags = line.partition(":")[2].split()
        if not cpu_flags:
            return 8
    flags = set(cpu_flags)
    return 16 if "avx512vl" in flags else 8 if "avx" in flags else 4


def group_lanes(p) -> int:
    """Lanes in a group (:data:`GROUP_LANES`) on the backend of the arrays ``p``."""
    if dr.backend_v(p) == dr.JitBackend.CUDA:
        return GROUP_LANES["cuda"]
    return GROUP_LANES["llvm"] or _packet_lanes()


@functools.lru_cache(maxsize=None)
def _packet_lanes() -> int:
    return packet_lanes()


def radius_array(r) -> mi.Float:
    """``r`` as a Dr.Jit float: a Python number becomes an opaque value, so that a kernel
    that uses it compiles once for every radius (a literal would be a new kernel per
    value: a progressive final gather compiled each pass)."""
    return dr.opaque(mi.Float, float(r)) if isinstance(r, (int, float)) else mi.Float(r)


def group_balls(p, r, active, width):
    """The ball each lane walks with: the ball around its group's balls (the group: the
    :data:`GROUP_LANES` lanes side by side, in walking order), or its own.

    Lanes that walk one ball make the same choice at every node and reach the same leaves at
    the same time, so a SIMD packet scans a leaf in one run instead of waiting for each lane's
    own walk (on 2 x 10^5 random points with Morton-sorted queries, a packet of distinct
    queries took 5.3 ns per photon tested, one whose 8 lanes shared a point 2.1 ns). A lane
    still tests photons against its own ball, so the result is the same. A group keeps it
    only while its ball is at most :data:`GROUP_SPREAD` times the radius of its largest
    member's (incoherent queries walk their own); a lane that is inactive or not finite takes
    no part and walks its own.

    Returns ``(centre, radius)`` per lane."""
    size = group_lanes(p)
    r = radius_array(r) + dr.zeros(mi.Float, width)
    ok = mi.Bool(active) & dr.isfinite(p.x) & dr.isfinite(p.y) & dr.isfinite(p.z) & \
        dr.isfinite(r) & (r >= 0)
    groups = -(-width // size)
    if width % size == 0:
        member, at, own = ok, p, r
    else:                                   # the last group is padded with its last lane
        # the count is opaque: a literal would compile anew for every count of queries
        lane = dr.minimum(dr.arange(mi.UInt32, groups * size), dr.opaque(mi.UInt32, width - 1))
        member, at = dr.gather(mi.Bool, ok, lane), dr.gather(mi.Point3f, p, lane)
        own = dr.gather(mi.Float, r, lane)
    lo = dr.block_reduce(dr.ReduceOp.Min, dr.select(member, at, dr.inf), size)
    hi = dr.block_reduce(dr.ReduceOp.Max, dr.select(member, at, -dr.inf), size)
    centre = 0.5 * (lo + hi)
    reach = dr.norm(at - dr.gather(mi.Point3f, centre,
                                   dr.arange(mi.UInt32, groups * size) // size)) + own
    radius = dr.block_reduce(dr.ReduceOp.Max, dr.select(member, reach, 0.0), size) * \
        GROUP_MARGIN
    largest = dr.block_reduce(dr.ReduceOp.Max, dr.select(member, own, 0.0), size)
    together = (radius <= GROUP_SPREAD * largest) & dr.isfinite(radius)
    group = dr.arange(mi.UInt32, width) // size
    shared = ok & dr.gather(mi.Bool, together, group)
    return (dr.select(shared, dr.gather(mi.Point3f, centre, group), p),
            dr.select(shared, dr.gather(mi.Float, radius, group), r))


def unpermute(value, perm, width):
    """The inverse of :func:`permute` for per-lane results."""
    if perm is None or value is None:
        return value
    out = dr.zeros(type(value), width)
    dr.scatter(out, value, perm)
    return out


def radius_query(forest: Forest, p, r, contribution, result_type=None, active=True,
                 maps=None, with_stats: bool = False, accept=None, state=None,
                 order: str = "morton", walk: str = "group", with_payload: bool = False):
    """Sum, over the photons within distance ``r`` of each query point, ``contribution``.

    Parameters
    ----------
    forest : Forest
        The photon maps.
    p : mi.Point3f
        Query points, one per lane.
    r : float or mi.Float
        Search radius: one for all (eq. (2) needs the same radius in every map) or one per
        query (a progressive render's shrinking radii).
    contribution : callable(index, dist2, active, state) -> result_type
        Called for each photon found, with its tree-order index into the forest's photon
        arrays, its squared distance to the query point (what a density kernel weighs) and
        ``state`` in the walk's lane order; its results are summed. With ``with_payload``
        it takes a fifth argument, the photon's 32-bit payload (``mi.UInt32``).
    result_type : Dr.Jit array type
        Type of ``contribution``'s results, e.g. ``mi.Spectrum`` (default: ``mi.Float``).
    active : mi.Bool
        Lanes to query.
    maps : tuple (first, stop), optional
        Search only maps ``first .. stop-1`` (default: all). The sum over all maps is the
        gathered estimate of eq. (2); one map alone is its partial term.
    with_stats : bool
        Also return a :class:`QueryStats` with per-lane traversal counts.
    accept : callable(index, active, state) -> mi.Bool, optional
        Which photons may count at all (e.g. those of few enough bounces); a photon it
        rejects is tested but not found. Default: every photon.
    state : PyTree of per-query arrays, optional
        What the callbacks need per query (a BSDF, a normal, ...). The queries are walked in
        another order than the caller's: ``state`` is put in that order with them, so the
        callbacks must read per-query data from it, not from arrays they close over.
    order : str
        "morton" (default): walk the queries in Morton order of ``p``, results in the
        caller's order; "given": walk them as they come (the caller has ordered them).
    walk : str
        "group" (default): lanes side by side in walking order choose nodes and leaves
        together, by a ball around all their balls, and each tests photons against its own
        (:func:`group_balls`); "own": each lane walks with its own ball. Both find the same
        photons; the counts of ``with_stats`` are those of the walk that ran.
    with_payload : bool
        Pass ``contribution`` each photon's payload (the direction of a photon map's
        photons), read with its position by the load of the distance test: no second
        read per photon found.

    Returns
    -------
    total, or (total, QueryStats), per query in the caller's order.
    """
    result_type = mi.Float if result_type is None else result_type
    check_callable(contribution, "contribution")
    accept = checked_callback(accept, "accept")
    walked = _walk_setup(forest, p, r, active, maps, order, walk)
    if walked is None:
        # No photon anywhere: nothing to walk (and no array to gather from).
        width = dr.width(as_points(p, "p"))
        zeros = dr.zeros(mi.UInt32, width)
        total = dr.zeros(result_type, width)
        return (total, QueryStats(zeros, mi.UInt32(zeros), mi.UInt32(zeros))) \
            if with_stats else total
    p, r, active, perm, ball, table, width = walked
    contribution = typed_contribution(contribution, result_type)
    with result_type_errors():
        total, stats = _walk(forest, p, r * r, ball, contribution, result_type, active,
                             table, with_stats, accept,
                             permute(state, perm, width), with_payload=with_payload)
    total = unpermute(total, perm, width)
    if not with_stats:
        return total
    return total, QueryStats(*[unpermute(v, perm, width) for v in (
        stats.nodes_visited, stats.photons_tested, stats.photons_found)])


#: The most photon indices :func:`radius_indices` writes at once (one UInt32 array).
MAX_INDICES = (1 << 32) - 2
#: What a slot of :func:`radius_indices` holds until a photon is written there.
UNWRITTEN = 0xFFFFFFFF


def _walk_setup(forest, p, r, active, maps, order, walk):
    """Every argument of a radius walk checked, and the queries put in walking order:
    ``(p, r, active, perm, ball, table, width)``, or None where there is nothing to walk
    (no photon, or no query)."""
    check_forest(forest)
    if walk not in WALKS:
        raise ValueError(f"walk must be one of {', '.join(repr(w) for w in WALKS)}, got "
                         f"{walk!r}")
    p = as_points(p, "p")
    width = dr.width(p)
    active = check_per_query(active, "active", width, radius=False)
    r = check_per_query(r, "r", width, active=active)
    p = check_queries(p, "p", active)
    check_order(order)
    table = forest.walk_table(maps)    # refuses a bad range, an empty forest's too
    if forest.size == 0 or width == 0:
        return None
    perm = order_queries(p, width, order)
    active = dr.full(mi.Bool, True, width) & mi.Bool(active)
    r = radius_array(r)
    p, r, active = permute(p, perm, width), permute(r, perm, width), permute(active, perm, width)
    ball = group_balls(p, r, active, width) if walk == "group" else (p, r)
    return p, r, active, perm, ball, table, width


def radius_indices(forest: Forest, p, r, lengths, maps=None) -> np.ndarray:
    """The tree-order indices of the photons within ``r`` of each query, as one flat host
    array, query after query in the caller's order, each query's in the order its walk met
    them; ``lengths`` are the queries' counts (one :func:`radius_query` of ones, over the
    same ``maps``). One more walk writes every photon found at its query's next slot."""
    lengths = np.asarray(lengths, dtype=np.int64)
    total = int(lengths.sum())
    if total > MAX_INDICES:
        raise ValueError(f"the queries find {total:,} photons in all, more than the "
                         f"{MAX_INDICES:,} one index array holds: give return_length=True for "
                         f"the counts, fewer queries at a time, or a smaller r")
    walked = _walk_setup(forest, p, r, True, maps, "morton", "group")
    if walked is None or total == 0:
        return np.zeros(0, np.int64)
    p, r, active, perm, ball, table, width = walked
    starts = np.concatenate([[0], np.cumsum(lengths)[:-1]])
    out = dr.full(mi.UInt32, UNWRITTEN, total)       # no photon index is that large
    dr.make_opaque(out)
    sink = (out, permute(mi.UInt32(starts.astype(np.uint32)), perm, width),
            permute(mi.UInt32(lengths.astype(np.uint32)), perm, width))
    _walk(forest, p, r * r, ball, None, mi.UInt32, active, table, False, None, None,
          sink=sink)
    dr.eval(out)
    found = out.numpy()
    if (found == UNWRITTEN).any():
        raise RuntimeError("the second walk of a radius query found fewer photons than the "
                           "first counted: some lists would be short")
    return found.astype(np.int64)


def check_callable(f, name: str):
    """A :class:`CallbackError` naming ``name`` unless ``f`` can be called (a callback)."""
    if not callable(f):
        raise CallbackError(f"{name} must be a function (a callback), got "
                            f"{type(f).__name__}")


def tree_row(table, k, bounds, active=True):
    """What a walk over the maps ``bounds`` = (first, stop) reads of tree ``k`` (per lane; the
    table of :meth:`~.forest.Forest.walk_table`): node base, the leaf-table entry of its first
    map in the range in leaf 0, internal-node count, leaf-table entries per leaf, and the
    number of its maps in the range."""
    node_base, leaf_base, n_int, stride, f = (dr.gather(mi.UInt32, table, 5 * k + c, active)
                                              for c in range(5))
    lo = dr.maximum(bounds[0], f) - f
    hi = dr.minimum(bounds[1], f + stride) - f
    return node_base, leaf_base + lo, n_int, stride, hi - lo


def walk_start(walk, width):
    """The walk's first tree per lane, one past its last, and its map bounds (opaque, so
    every range runs the same kernel)."""
    table, t0, t1, first, stop = walk
    return (table, dr.zeros(mi.UInt32, width) + dr.opaque(mi.UInt32, t0),
            dr.opaque(mi.UInt32, t1), (dr.opaque(mi.UInt32, first), dr.opaque(mi.UInt32, stop)))


def leaf_box(forest: Forest, tree, node_base, n_int, node):
    """The lower and upper corners of leaf ``node`` of ``tree``
    (:attr:`~.forest.Forest.leaf_boxes`; one 16-byte load each)."""
    leaf = node_base + tree + (node - n_int)
    lo = dr.gather(mi.Vector4f, forest.leaf_boxes, 2 * leaf)
    hi = dr.gather(mi.Vector4f, forest.leaf_boxes, 2 * leaf + 1)
    return mi.Point3f(lo.x, lo.y, lo.z), mi.Point3f(hi.x, hi.y, hi.z)


def box_reached(box, p, r2):
    """Whether the ball of squared radius ``r2`` around ``p`` reaches ``box`` (lo, hi)."""
    outside = dr.maximum(dr.maximum(box[0] - p, p - box[1]), 0.0)
    return dr.squared_norm(outside) <= r2


def leaf_reached(forest: Forest, tree, node_base, n_int, node, p, r2):
    """Whether the ball of squared radius ``r2`` around ``p`` reaches the box of leaf
    ``node`` of ``tree`` (:attr:`~.forest.Forest.leaf_boxes`). A walk passes over a leaf it
    does not reach as over a subtree: on the Cornell box and room workloads of ``partpm
    bench`` that skips a quarter of the photons it would test, and the lanes of a packet
    scan only leaves they need."""
    return box_reached(leaf_box(forest, tree, node_base, n_int, node), p, r2)


def leaf_run(forest: Forest, leaf_base, stride, span, n_int, node, active=True):
    """[first, end) of the photons the walk scans in leaf ``node`` (its maps' runs)."""
    entry = leaf_base + (node - n_int) * stride
    i = dr.gather(mi.UInt32, forest.leaf_table, entry, active)
    end = dr.select(active, dr.gather(mi.UInt32, forest.leaf_table, entry + span, active), i)
    return i, end


def split_of(forest: Forest, node, active=True):
    """(split value, split axis) of the internal node ``node`` (global index)."""
    rec = dr.gather(mi.Point2f, forest.nodes, node, active)
    return rec.x, dr.reinterpret_array(mi.UInt32, rec.y)


@dr.syntax
def _walk(forest, p, r2, ball, contribution, result_type, active, walk, with_stats, accept,
          state, collect=None, with_payload=False, sink=None):
    """The while-while walk behind :func:`radius_query`, one lane per query point, over the
    trees of ``walk`` (:meth:`~.forest.Forest.walk_table`): nodes and leaves are chosen by
    the lane's walking ``ball`` (centre, radius: :func:`group_balls`), photons by its own
    squared radius ``r2``. ``collect``: two local arrays (squared distances, indices) that
    keep the photons found, as many as they hold; ``photons_found`` then counts them, and a
    lane that finds more than they hold stops after that leaf (its count is then only a
    lower bound). ``with_payload``: ``contribution`` takes the photon's payload too.
    ``sink``: (out, first, count), a UInt32 array and each lane's first slot of it and its
    count of slots: the photons found are written there in turn (:func:`radius_indices`)."""
    width = dr.width(p)
    c, cr = ball
    cr2 = cr * cr
    total = dr.zeros(result_type, width)
    table, k, stop_u, bounds = walk_start(walk, width)
    active = mi.Bool(active) & (k < stop_u)        # a new array: the caller's stays
    node_base, leaf_base, n_int, stride, span = tree_row(table, k, bounds, active)
    node = dr.zeros(mi.UInt32, width)
    going_down = dr.full(mi.Bool, True, width)
    nodes_visited = dr.zeros(mi.UInt32, width)
    photons_tested = dr.zeros(mi.UInt32, width)
    photons_found = dr.zeros(mi.UInt32, width)

    while dr.hint(active, label="partpm_radius_query"):
        # To the next leaf the ball reaches (or past the last map).
        at_leaf = mi.Bool(False)
        searching = mi.Bool(active)
        while dr.hint(searching, label="partpm_radius_descend"):
            if going_down:
                if dr.hint(with_stats, mode="scalar"):
                    nodes_visited += 1
                if node < n_int:
                    split, axis = split_of(forest, node_base + node)
                    node = dr.select(coordinate(c, axis) - cr <= split, 2 * node + 1,
                                     2 * node + 2)
                else:
                    box = leaf_box(forest, k, node_base, n_int, node)
                    if box_reached(box, c, cr2):
                        # A lane of a group whose own ball misses the box scans nothing.
                        at_leaf = box_reached(box, p, r2)
                        searching = mi.Bool(False)
                    else:
                        going_down = mi.Bool(False)  # passed over, as a subtree it misses
            elif node == 0:
                # This tree is done: the root of the next one, or the end.
                k += 1
                if k < stop_u:
                    node_base, leaf_base, n_int, stride, span = tree_row(table, k, bounds)
                    going_down = mi.Bool(True)
                else:
                    searching = mi.Bool(False)
                    active = mi.Bool(False)
            else:
                parent = (node - 1) >> 1
                to_sibling = mi.Bool(False)
                if (node & 1) == 1:
                    # Up from a left child: the right one is next if the ball reaches it.
                    split, axis = split_of(forest, node_base + parent)
                    to_sibling = coordinate(c, axis) + cr >= split
                node = dr.select(to_sibling, node + 1, parent)
                going_down = to_sibling

        # Test the leaf's photons (of the maps asked for).
        i, end = leaf_run(forest, leaf_base, stride, span, n_int, node, at_leaf)
        while dr.hint(i < end, label="partpm_radius_scan"):
            for u in range(SCAN_UNROLL):
                j = i + u
                valid = j < end
                if dr.hint(with_stats, mode="scalar"):
                    photons_tested += mi.UInt32(valid)
                at, payload = photon_record(forest, j, valid)
                dist2 = dr.squared_norm(at - p)
                found = valid & (dist2 <= r2)
                if dr.hint(accept is not None, mode="scalar"):
                    found &= accept(j, found, state)
                if found:
                    if dr.hint(collect is not None, mode="scalar"):
                        # Kept for a later selection (the grouped kNN), while there is room.
                        keep = photons_found < len(collect[0])
                        collect[0].write(dist2, photons_found, keep)
                        collect[1].write(j, photons_found, keep)
                    if dr.hint(sink is not None, mode="scalar"):
                        dr.scatter(sink[0], j, sink[1] + photons_found,
                                   found & (photons_found < sink[2]))
                    if dr.hint(with_stats or collect is not None or sink is not None,
                               mode="scalar"):
                        photons_found += 1
                    if dr.hint(contribution is not None and with_payload, mode="scalar"):
                        total += contribution(j, dist2, found, state, payload)
                    elif dr.hint(contribution is not None, mode="scalar"):
                        total += contribution(j, dist2, found, state)
            i += SCAN_UNROLL
        going_down = mi.Bool(False)
        if dr.hint(collect is not None, mode="scalar"):
            active &= photons_found <= len(collect[0])      # more than it keeps: stop

    return total, QueryStats(nodes_visited, photons_tested, photons_found)
