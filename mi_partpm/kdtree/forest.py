"""The forest: one balanced kd-tree per photon map, in flat device arrays, and its build.

A *forest* holds the n partial photon maps of eq. (2) of the paper. It has two layouts
(:data:`LAYOUTS`):

- ``"separate"``: one kd-tree per map, each built from its own photons alone, as a processing
  element of the paper builds the map it holds;
- ``"shared"``: consecutive maps share one tree's split planes (a group of at most
  :data:`GROUP_PHOTONS` photons), each leaf holding the photons of every map of the group, map
  after map. Each map keeps its own photons and its own run of every leaf (a walk over one
  map reads only its photons), but a walk over several maps descends once and scans their
  runs of a leaf in turn, instead of descending every map's tree from its root.

Every tree is balanced and implicit: node ``j`` of a tree has children ``2j+1`` and ``2j+2``;
nodes ``0 .. I-1`` are internal (``I = 2**D - 1``) and nodes ``I .. 2I`` are the ``2**D``
leaves, each holding a contiguous run of at most ``leaf_size`` photons (a shared tree's:
:func:`shared_leaf_size`). A node at level ``d`` covering ``c`` photons is split at their
median along the longest axis of the node's bounding box (paper, section 2.1), so all leaves
of a tree sit at the same depth.

Everything lives on the device (Dr.Jit arrays of the active variant):

- ``records``: 4 floats per photon in tree order, its position and a 32-bit payload (the
  photon map keeps the photon's direction code there), so a distance test and the payload
  are one 16-byte load;
- ``nodes``: 2 floats per internal node, the split value and the split axis (its bits);
- ``leaf_table``: per tree, the first photon of every leaf (of every map's run of a leaf, in
  a shared tree) and the tree's end;
- ``leaf_boxes``: per leaf, the bounding box of its photons (of all its maps), so a walk
  skips a leaf its query ball misses without testing a photon.

The build (:func:`build_forest`) sorts the points once per axis on the device (Dr.Jit's radix
sort), then splits one tree level at a time over all maps at once, with a handful of
whole-array kernels per level and no host sort; one more kernel bounds every leaf. The
queries over a forest are in :mod:`.radius` and :mod:`.knn`. :func:`tree_bytes` is the one
place that counts a tree's bytes.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import drjit as dr
import mitsuba as mi
import numpy as np

__all__ = ["Forest", "build_forest", "as_points", "shared_leaf_size", "morton_codes", "morton_order",
           "tree_bytes", "tree_depth", "check_coordinates", "MAX_MAPS", "MAX_COORD", "LEAF_SIZE",
           "NODE_BYTES", "LEAF_ENTRY_BYTES", "MIN_EXTENT", "check_extent", "check_span",
           "LEAF_BOX_BYTES", "RECORD_FLOATS", "LAYOUTS", "rows_in_order"]

#: Default most photons per leaf of a tree of one map (a shared tree's: :func:`shared_leaf_size`);
#: a tree of more photons than that has leaves of between half of it and all of it.
#: With the while-while walk of :mod:`.radius` large leaves pay: on 200,000 Morton-ordered
#: hit points of the Cornell box (r = 1/20, 460 photons found per query) one map answered in
#: 0.41 / 0.27 / 0.20 / 0.20 s with leaves of 8 / 16 / 24 / 32, and on a room of 200,000
#: photons (900 found per query) in 0.64 / 0.43 / 0.41 / 0.28 s (AVX2, before group walks
#: and leaf boxes). With both, on AVX-512, 32 / 64 / 96 / 128 gave power sums in 0.235 /
#: 0.207-0.214 / 0.206 / 0.206 s (Cornell box) and 0.298 / 0.275-0.278 / 0.272 / 0.276 s
#: (room), kNN and the integrator's estimate within 5%, and a build of 1.2 x 10^6 photons
#: in 0.16 / 0.13-0.15 / 0.11 / 0.11 s (a level fewer per doubling). ``partpm bench``
#: measures the current value against scipy.
LEAF_SIZE = 64

#: The largest ``leaf_size``: a forest's photon indices are 32-bit, so a larger leaf would
#: hold no more photons.
MAX_LEAF_SIZE = 1 << 32

#: The most maps a forest holds (its per-map tables are host arrays of one entry per map; the
#: paper's PE array has at most 1024).
MAX_MAPS = 1 << 20
#: The largest magnitude of a coordinate, of a photon or a query point: distances are
#: compared squared, in float32, and the square of a distance beyond 1.8 x 10^19 overflows.
MAX_COORD = 1e18
#: The least span of a forest's points (unless they all sit at one point): squared distances
#: below float32's normal range flush to zero, so distances below 1e-15 are not resolved
#: (the queries' least radius), and points that span 1e-12 are that far apart even when 10^9
#: of them fill the box evenly.
MIN_EXTENT = 1e-12

#: Bytes of one internal node: the split value (float32) and the split axis (uint32).
NODE_BYTES = 8
#: Bytes of one entry of the leaf table (uint32 first photon of a leaf).
LEAF_ENTRY_BYTES = 4
#: Bytes of one leaf's bounding box: its lower and upper corners, 4 float32 each (the fourth
#: unused), so each corner is one 16-byte load.
LEAF_BOX_BYTES = 32
#: Floats per photon record: x, y, z and a 32-bit payload.
RECORD_FLOATS = 4

#: Forest layouts: one tree per map, or groups of maps sharing one tree's split planes.
LAYOUTS = ("separate", "shared")

#: A shared tree of s maps has leaves of at most max(leaf_size, SHARED_LEAF_PER_MAP * s)
#: photons, so its leaf table (one 4-byte entry per map and leaf) stays under two bytes per
#: photon (the leaves hold more than half that many photons each).
SHARED_LEAF_PER_MAP = 4


def tree_depth(counts, leaf_size=LEAF_SIZE) -> np.ndarray:
    """Depth D of the tree of ``counts`` photons: the smallest D with
    ceil(c / 2**D) <= leaf_size (per tree; ``leaf_size`` may be one per tree)."""
    counts = _integers(counts, "counts", 0)
    leaf_size = _integers(leaf_size, "leaf_size", 1)
    leaves_needed = np.maximum(1, -(-counts // leaf_size))
    return np.ceil(np.log2(leaves_needed)).astype(np.int64)


def _integers(values, name: str, least: int) -> np.ndarray:
    """``values`` (a number or array-like) as int64, each an integer >= ``least`` (not a
    bool): a ValueError naming ``name`` otherwise."""
    host = np.asarray(values)
    if host.dtype.kind not in "iu" or np.any(host < least):
        raise ValueError(f"{name} must be integers >= {least}, got {values!r:.80}")
    return host.astype(np.int64)


def tree_bytes(counts, leaf_size: int = LEAF_SIZE) -> np.ndarray:
    """Bytes of the separate tree of a map of ``counts`` photons (per map): ``2**D - 1``
    internal nodes of :data:`NODE_BYTES`, a leaf table of ``2**D + 1`` entries and ``2**D``
    leaf boxes of :data:`LEAF_BOX_BYTES`."""
    depth = tree_depth(counts, leaf_size)
    return ((1 << depth) - 1) * NODE_BYTES + ((1 << depth) + 1) * LEAF_ENTRY_BYTES + \
        (1 << depth) * LEAF_BOX_BYTES


def shared_leaf_size(leaf_size: int, maps_in_tree) -> np.ndarray:
    """The most photons a leaf of a tree shared by ``maps_in_tree`` maps holds (per tree):
    ``leaf_size`` for a tree of one map, at least :data:`SHARED_LEAF_PER_MAP` per map else."""
    s = np.asarray(maps_in_tree, dtype=np.int64)
    return np.where(s > 1, np.maximum(leaf_size, SHARED_LEAF_PER_MAP * s), leaf_size)


@dataclass
class Forest:
    """The n partial photon maps, as kd-trees on the device (one per map, or one per group
    of maps sharing split planes: :data:`LAYOUTS`).

    Photons are in tree order: tree 0's photons first, each tree's photons ordered so that
    every leaf is a contiguous run and, in a shared tree, every map's part of a leaf too.
    ``tree_order`` maps a tree-order index back to the caller's photon index.

    Attributes
    ----------
    records : mi.Float, 4 N entries
        Per photon in tree order: x, y, z and a 32-bit payload (float bits).
    nodes : mi.Float, 2 I entries (at least 2)
        Per internal node, tree after tree: the split value and the split axis (0, 1, 2, as
        float bits).
    leaf_table : mi.UInt32
        For tree t of s maps (its first map f), entry ``leaf_base[t] + j s + (m - f)`` is the
        first photon of map m's run of leaf j, and entry ``leaf_base[t] + L_t s`` the end of
        the tree's photons (global tree-order indices): map m's run of leaf j ends where the
        next entry starts. A separate tree has s = 1.
    leaf_boxes : mi.Float, 8 entries per leaf
        Leaf j of tree t (leaf ``node_base[t] + t + j`` of the forest: a tree of I internal
        nodes has I + 1 leaves) is bounded by the lower corner in entries 0-2 of its 8 and the
        upper corner in entries 4-6 (an empty leaf: +inf and -inf).
    tree_order : mi.UInt32, N entries
        ``records`` entry t holds the caller's photon ``tree_order[t]``.
    node_base, leaf_base, internal_count : (T,) int64 NumPy arrays
        Per tree: offsets into ``nodes`` and ``leaf_table``, and its internal-node count.
    tree_first_map, tree_map_count : (T,) int64 NumPy arrays
        Per tree: its first map and its number of maps (1 in the separate layout).
    map_tree, photon_count : (n,) int64 NumPy arrays
        Per map: its tree and the number of photons stored in it.
    leaf_size : int
        The most photons a leaf of a separate tree holds (a shared tree's leaves:
        :func:`shared_leaf_size`).
    layout : str
        "separate" or "shared".

    The NumPy properties :attr:`points`, :attr:`order`, :attr:`split_value`,
    :attr:`split_axis` and :attr:`leaf_start` copy the device arrays to the host, for
    inspection and tests.
    """

    records: object
    nodes: object
    leaf_table: object
    leaf_boxes: object
    tree_order: object
    node_base: np.ndarray
    leaf_base: np.ndarray
    internal_count: np.ndarray
    photon_count: np.ndarray
    leaf_size: int
    tree_first_map: np.ndarray = None
    tree_map_count: np.ndarray = None
    map_tree: np.ndarray = None
    layout: str = "separate"
    _tables: dict = field(default_factory=dict, repr=False)

    def __post_init__(self):
        n = self.photon_count.shape[0]
        if self.map_tree is None:                 # one tree per map
            self.map_tree = np.arange(n, dtype=np.int64)
            self.tree_first_map = np.arange(n, dtype=np.int64)
            self.tree_map_count = np.ones(n, dtype=np.int64)

    @property
    def map_count(self) -> int:
        return int(self.photon_count.shape[0])

    @property
    def tree_count(self) -> int:
        return int(self.tree_first_map.shape[0])

    @property
    def size(self) -> int:
        """Photons over all maps."""
        return int(self.photon_count.sum())

    @property
    def tree_nbytes(self) -> np.ndarray:
        """Bytes of each tree: its nodes, its leaf table and its leaf boxes, photons not
        included."""
        return self.internal_count * NODE_BYTES + \
            ((self.internal_count + 1) * self.tree_map_count + 1) * LEAF_ENTRY_BYTES + \
            (self.internal_count + 1) * LEAF_BOX_BYTES

    @property
    def map_nbytes(self) -> np.ndarray:
        """Bytes of each map's tree (nodes, leaf table, boxes), photons not included; a shared
        tree's bytes are split over its maps by their photons."""
        tree_photons = np.zeros(self.tree_count, dtype=np.int64)
        np.add.at(tree_photons, self.map_tree, self.photon_count)
        t = self.map_tree
        share = np.where(tree_photons[t] > 0, self.photon_count / np.maximum(tree_photons[t], 1),
                         1.0 / self.tree_map_count[t])
        return np.round(self.tree_nbytes[t] * share).astype(np.int64)

    @property
    def nbytes(self) -> int:
        """Bytes of all trees (nodes, leaf tables and boxes), photons not included."""
        return int(self.tree_nbytes.sum())

    def depth(self, m: int) -> int:
        """Depth D of map m's tree (0 for a tree that is a single leaf)."""
        return int(np.log2(int(self.internal_count[self.map_tree[m]]) + 1))

    def walk_table(self, maps=None):
        """What a walk over maps ``first .. stop-1`` (default all) reads: ``(table, t0, t1,
        first, stop)``. ``table`` is the forest's one device array of 5 entries per tree (node
        base, leaf-table base, internal-node count, entries per leaf s = the tree's maps, its
        first map f), made once; the walk visits trees ``t0 .. t1-1``, and in each the maps
        [max(first, f), min(stop, f + s)): their runs of leaf j are one run of the leaf table,
        from entry ``base + j s + max(first, f) - f`` to the entry ``span`` = their count
        later. One array for every range: a device array per range, all kept, slowed every
        later Dr.Jit call down (per-map walks of 128 maps: 11 -> 57 ms each)."""
        if maps is None:
            first, stop = 0, self.map_count
        else:
            try:
                first, stop = maps
                if not all(isinstance(v, (int, np.integer)) and not isinstance(v, (bool, np.bool_))
                           for v in (first, stop)):
                    raise TypeError
                first, stop = int(first), int(stop)
            except (TypeError, ValueError):
                raise ValueError(f"maps must be (first, stop) with 0 <= first <= stop <= "
                                 f"map_count = {self.map_count}, got {maps!r}") from None
        if not 0 <= first <= stop <= self.map_count:
            raise ValueError(f"maps must be (first, stop) with 0 <= first <= stop <= "
                             f"map_count = {self.map_count}, got ({first}, {stop})")
        if "walk" not in self._tables:
            rows = np.stack([self.node_base, self.leaf_base, self.internal_count,
                             self.tree_map_count, self.tree_first_map], axis=1)
            self._tables["walk"] = mi.UInt32(rows.astype(np.uint32).reshape(-1)
                                              if rows.size else np.zeros(5, np.uint32))
        if stop == first:
            return self._tables["walk"], 0, 0, first, stop
        return (self._tables["walk"], int(self.map_tree[first]),
                int(self.map_tree[stop - 1]) + 1, first, stop)

    # ---------------------------------------------------------------- host views

    @property
    def points(self) -> np.ndarray:
        """(N, 3) float32 positions in tree order."""
        return self.records.numpy().reshape(-1, RECORD_FLOATS)[: self.size, :3]

    @property
    def order(self) -> np.ndarray:
        """(N,) int64: ``points[t] == input_points[order[t]]``."""
        return self.tree_order.numpy().astype(np.int64)

    @property
    def split_value(self) -> np.ndarray:
        return self.nodes.numpy().reshape(-1, 2)[: int(self.internal_count.sum()), 0]

    @property
    def split_axis(self) -> np.ndarray:
        return self.nodes.numpy().reshape(-1, 2)[: int(self.internal_count.sum()), 1].view(
            np.uint32)

    @property
    def leaf_start(self) -> np.ndarray:
        return self.leaf_table.numpy()


def as_points(points, name: str = "points") -> mi.Point3f:
    """``points`` as ``mi.Point3f`` (float32, as everything here computes): a ``mi.Point3f``
    as it is, another Dr.Jit 3-vector (``Vector3f``, ``Point3d``, ...) converted, or
    array-like of shape (N, 3) (one point: (3,)). Anything else, e.g. (3, N) or (N, 2), is a
    ValueError naming ``name`` (NumPy would otherwise pair the wrong numbers into points)."""
    if isinstance(points, mi.Point3f):
        return points
    if dr.is_array_v(points) and not dr.is_tensor_v(points) and dr.depth_v(points) == 2:
        if dr.size_v(points) != 3:
            raise ValueError(f"{name} must be a Dr.Jit 3-vector such as mi.Point3f, or an "
                             f"array of shape (N, 3); got {type(points).__name__}")
        return mi.Point3f(mi.Float(points.x), mi.Float(points.y), mi.Float(points.z))
    try:                                     # NumPy, lists, tensors, one scalar point
        is_complex = np.iscomplexobj(points)  # itself fails on a ragged list
        pts = None if is_complex else np.asarray(points, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be numbers of shape (N, 3)") from None
    if is_complex:
        raise ValueError(f"{name} must be real numbers of shape (N, 3), got complex ones")
    if pts.ndim == 1 and pts.shape[0] == 3:
        pts = pts.reshape(1, 3)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"{name} must have shape (N, 3), got {pts.shape}")
    pts = pts.astype(np.float32)
    return mi.Point3f(*[np.ascontiguousarray(pts[:, a]) for a in range(3)])


def check_coordinates(p, name: str, active=True):
    """A ValueError naming ``name`` unless every ``active`` point of ``p`` is finite with
    coordinates within +-:data:`MAX_COORD` (one reduction on the device)."""
    if dr.width(p) == 0:
        return
    largest = dr.maximum(dr.maximum(dr.abs(p.x), dr.abs(p.y)), dr.abs(p.z))
    ok = dr.isfinite(largest) & (largest <= MAX_COORD)
    if not bool(dr.all(ok | ~mi.Bool(active))[0]):
        raise ValueError(f"{name} must be finite with coordinates within +-{MAX_COORD:g} "
                         f"(distances are compared squared in float32); NaN, inf or a larger "
                         f"coordinate found")


def _spread_bits(x):
    """The low 10 bits of ``x`` spread to every third bit (bit i to bit 3 i)."""
    x = (x | (x << 16)) & 0x030000FF
    x = (x | (x << 8)) & 0x0300F00F
    x = (x | (x << 4)) & 0x030C30C3
    return (x | (x << 2)) & 0x09249249


def morton_codes(p, box=None) -> mi.UInt32:
    """30-bit Morton (Z-order) codes of ``p`` (a ``mi.Point3f`` or anything
    :func:`as_points` takes) over its bounding box, or over ``box`` (a bounding box known
    beforehand, e.g. a scene's: no reductions), on the device."""
    p = as_points(p)
    code = dr.zeros(mi.UInt32, dr.width(p))
    for a, c in enumerate((p.x, p.y, p.z)):
        if box is None:
            lo, hi = dr.min(c), dr.max(c)        # 1-wide arrays: no round trip to the host
        else:
            lo, hi = mi.Float(box.min[a]), mi.Float(box.max[a])   # the same float32 steps
        q = mi.UInt32(dr.clip((c - lo) * (1023.0 / dr.maximum(hi - lo, 1e-30)), 0.0, 1023.0))
        code |= _spread_bits(q) << a
    return code


def morton_order(points) -> np.ndarray:
    """The permutation that sorts ``points`` (K, 3) along a Z-order (Morton) curve.

    Queries that are close in space and close in this order walk the same nodes, side by side
    in a SIMD packet and one after another in the caches. The queries of :mod:`.radius` and
    :mod:`.knn` put their query points in this order themselves.
    """
    p = as_points(points)
    if dr.width(p) == 0:
        return np.zeros(0, dtype=np.int64)
    check_coordinates(p, "points")
    return dr.argsort(morton_codes(p)).numpy().astype(np.int64)


#: Bits per pass of the presort's radix sort on the LLVM backend: two passes of 16 bits sort
#: 4 x 10^6 floats in 68 ms, Dr.Jit's argsort (three of 11 bits) in 105 ms.
SORT_BITS = 16


def _sorted_by_map_then(key, map_ids, map_count):
    """The stable order of the points by map, then by ``key`` (floats) within a map: radix
    sort passes of :data:`SORT_BITS` bits over the key's order-preserving bits, then one
    pass over the map ids (Dr.Jit's permutation of each pass; its argsort, three passes of
    11 bits and three more for the maps, where that primitive is missing or on a GPU)."""
    n = dr.width(key)
    mkperm = getattr(dr.detail, "block_mkperm", None)
    if mkperm is None or dr.backend_v(key) != dr.JitBackend.LLVM or n < 2 or \
            map_count > 1 << SORT_BITS:
        order = dr.argsort(key)
        if map_count > 1:
            order = dr.gather(mi.UInt32, order, dr.argsort(dr.gather(mi.UInt32, map_ids, order)))
        return order
    bits = dr.reinterpret_array(mi.UInt32, key)  # order-preserving: flip negatives' bits
    bits = bits ^ ((0 - (bits >> 31)) | 0x80000000)
    order = None
    for shift in range(0, 32, SORT_BITS):
        digit = (bits >> shift) & ((1 << SORT_BITS) - 1)
        dr.eval(digit)
        perm = mkperm(digit, n, 1 << SORT_BITS)
        order = perm if order is None else dr.gather(mi.UInt32, order, perm)
        if shift + SORT_BITS < 32:
            bits = dr.gather(mi.UInt32, bits, perm)
        dr.eval(order, bits)
    if map_count > 1:
        digit = dr.gather(mi.UInt32, map_ids, order)
        dr.eval(digit)
        order = dr.gather(mi.UInt32, order, mkperm(digit, n, 1 << int(map_count - 1).bit_length()))
    return order


def _presort(coord, map_ids, map_count):
    """The three sorted orders of the points, by map then by x, y and z (radix sorts on the
    device, :func:`_sorted_by_map_then`), as ``(ids, rel)``: ``ids`` the points in the x
    order, and ``rel[1]``, ``rel[2]`` the y and z orders as positions in the x order
    (``rel[0]`` is None: the x order itself). Positions rather than point ids keep the
    partition's reads and writes inside a node's run once nodes are small."""
    orders = []
    for axis in range(3):
        order = _sorted_by_map_then(coord[axis], map_ids, map_count)
        dr.eval(order)
        orders.append(order)
    n = dr.width(orders[0])
    where = dr.empty(mi.UInt32, n)               # each point's position in the x order
    dr.scatter(where, dr.arange(mi.UInt32, n), orders[0])
    rel = [None]
    for a in (1, 2):                             # a kernel each: measured faster than one
        rel.append(dr.gather(mi.UInt32, where, orders[a]))
        dr.eval(rel[-1])
        orders[a] = None
    return orders[0], rel


def _point_at(ids, rel, a, pos):
    """The point at position ``pos`` of the order along axis ``a``."""
    return dr.gather(mi.UInt32, ids, pos if a == 0 else dr.gather(mi.UInt32, rel[a], pos))


def _split_level(coord, ids, rel, first, stop, median):
    """Split axis and value of each node of a level, from its runs ``[first, stop)`` in the
    three sorted orders: the longest extent, and the coordinate of the ``median`` entry (of
    the node's last entry when the node holds one photon and its median is its end: its
    photon goes left and must lie on the plane's left, not under the next node's first)."""
    def at(a, pos):
        return dr.gather(mi.Float, coord[a], _point_at(ids, rel, a, pos))
    extent = [at(a, stop - 1) - at(a, first) for a in range(3)]
    axis = mi.UInt32(dr.select((extent[0] >= extent[1]) & (extent[0] >= extent[2]), 0,
                               dr.select(extent[1] >= extent[2], 1, 2)))
    at_median = dr.minimum(median, stop - 1)    # only the split axis's order is read there
    on = [axis == a for a in range(3)]
    x_position = dr.select(on[0], at_median,
                           dr.select(on[1], dr.gather(mi.UInt32, rel[1], at_median, on[1]),
                                     dr.gather(mi.UInt32, rel[2], at_median, on[2])))
    point = dr.gather(mi.UInt32, ids, x_position)
    split = dr.select(on[0], dr.gather(mi.Float, coord[0], point, on[0]),
                      dr.select(on[1], dr.gather(mi.Float, coord[1], point, on[1]),
                                dr.gather(mi.Float, coord[2], point, on[2])))
    dr.eval(axis, split)
    return axis, split


def _partition_level(ids, rel, node_first, node_median, node_axis, level_node, in_level,
                     node_in_map, position, last=False, packed=False):
    """Stable partition of the three sorted orders into every node's two halves.

    ``level_node`` is each position's node in the level's node arrays; a position at or
    right of its node's median (in the order of the node's axis) goes right. Every point's side is
    written at its position in the x order (one scatter) and the x order partitioned with
    one prefix sum and one scatter. An entry of the y or z order then reads its point's new
    position in the x order (one gather, the only random access per order): that is both
    the entry's new name and its side (right of the median or not); a prefix sum per order
    and one kernel of targets and scatters partition the two orders (not after the ``last``
    level: only the tree order is left to find). With ``packed`` (every node of the level
    holds fewer than 2**16 photons) the two orders share one prefix sum: their right-goer
    flags are the low and high 16 bits of one 32-bit count, and within a node the difference
    of two counts splits into the two exact counts. ``node_in_map`` is each position's node
    within its map's level. Kernels that can share their reads are fused: the sides with each
    position's next node, the targets with the x order's scatter, each order's renaming with
    its right-goer flags (with ``packed``, the second order's with both orders' flags): a
    level is five kernels over the photons (two at the ``last``), and two prefix sums (three
    when not ``packed``, one at the ``last``). A build of 3.7 x 10^6 random points took 0.91
    of the unfused one's time, of 3 x 10^5 0.94-0.98 (timed in turn in one process). Returns
    the new ``(ids, rel)`` and each position's node at the next level (2k, or 2k + 1 where
    it went right; unchanged outside the level; None after the ``last``)."""
    n = dr.width(position)
    first = dr.gather(mi.UInt32, node_first, level_node, in_level)
    median = dr.gather(mi.UInt32, node_median, level_node, in_level)
    axis = dr.gather(mi.UInt32, node_axis, level_node, in_level)
    right_of_median = mi.UInt32(position >= median)
    side = dr.empty(mi.UInt32, n)   # per x-order position: its point's side (every position
                                    # of a node of the level is written; others are not read)
    dr.scatter(side, right_of_median,
               dr.select(axis == 0, position, dr.select(axis == 1, rel[1], rel[2])), in_level)
    child = None if last else dr.select(in_level, 2 * node_in_map + right_of_median,
                                        node_in_map)
    dr.eval(side, child)            # one kernel: the side and each position's next node

    def targets(right, rank_right):
        """Where each position of an order goes: right-goers after the median, in order."""
        rank_left = (position - first) - rank_right
        return dr.select(in_level, dr.select(right == 1, median + rank_right,
                                             first + rank_left), position)

    def rights_in_node(right):
        """Right-goers of the node before each position (one exclusive prefix sum)."""
        rights_before = dr.prefix_sum(right)
        dr.eval(rights_before)
        return rights_before - dr.gather(mi.UInt32, rights_before, first)
    to = targets(side, rights_in_node(side))
    new_ids = dr.empty(mi.UInt32, n)
    dr.scatter(new_ids, ids, to)
    if last:
        dr.eval(new_ids)
        return new_ids, [None], child
    dr.eval(to, new_ids)            # one kernel: the targets, and the x order moved there
    del side
    renamed, right = [], []
    for a in (1, 2):               # a kernel each: both gathers in one ran 2-3 times slower
        renamed.append(dr.gather(mi.UInt32, to, rel[a]))
        right.append(mi.UInt32(renamed[-1] >= median))
        rel[a] = None                             # free the old order
        if not packed:             # the entry's new name, and the prefix sum's input
            dr.eval(renamed[-1], right[-1])
    if packed:
        flags = right[0] | (right[1] << 16)
        dr.eval(renamed[0])
        dr.eval(renamed[1], flags)                # the second name and both flags
        counts = rights_in_node(flags)
        ranks = (counts & 0xFFFF, counts >> 16)
    else:
        ranks = [rights_in_node(r) for r in right]
    out = [dr.empty(mi.UInt32, n) for _ in right]
    for k in (0, 1):
        dr.scatter(out[k], renamed[k], targets(right[k], ranks[k]))
    dr.eval(out)
    return new_ids, [None] + out, child


def _partition_levels(coord, map_ids, counts, starts, depth, node_base, nodes):
    """Split every node of every level; fill ``nodes``; return the tree order (device).

    Presorted build: for each axis, the points sorted along that axis within every map, the
    y and z orders held as positions in the x order (:func:`_presort`). A node's bounds are
    then the first and last entries of its runs and its median the middle entry of the run
    of its longest axis, found by one small kernel over the level's nodes
    (:func:`_split_level`). Then every position looks up its node (it tracks its node's index
    within its map's level, which becomes 2k or 2k+1 at the next level) and the three orders
    are partitioned stably into the left and right halves (:func:`_partition_level`): a
    handful of whole-array kernels per level, over all maps at once, with no division and no
    sort after the first; below the top levels their reads and writes stay inside a node's
    run (3 x 10^7 photons on 2 cores: 19 s, against 25-27 s when every order held point
    ids).
    """
    n = dr.width(coord[0])
    n_maps = counts.shape[0]
    ids, rel = _presort(coord, map_ids, n_maps)
    position = dr.arange(mi.UInt32, n)
    point_map = None                             # map of each position (runs of maps)
    if n_maps > 1:
        point_map = dr.gather(mi.UInt32, map_ids, ids)
        dr.eval(point_map)
    node_in_map = dr.zeros(mi.UInt32, n)         # each position's node within its map's level
    for level in range(int(depth.max(initial=0))):
        per_map = 1 << level
        maps = np.nonzero(depth > level)[0]      # maps whose trees are deeper than this level
        # The level's nodes, map after map: their runs [first, stop) and medians.
        node_map = np.repeat(maps, per_map)
        node_index = np.tile(np.arange(per_map, dtype=np.int64), maps.shape[0])
        c = counts[node_map]
        first = starts[node_map] + (node_index * c) // per_map
        stop = starts[node_map] + ((node_index + 1) * c) // per_map
        median = starts[node_map] + ((2 * node_index + 1) * c) // (2 * per_map)
        first, stop, median = (mi.UInt32(v.astype(np.uint32)) for v in (first, stop, median))
        axis, split = _split_level(coord, ids, rel, first, stop, median)
        node = mi.UInt32((node_base[node_map] + (per_map - 1) + node_index).astype(np.uint32))
        dr.scatter(nodes, split, 2 * node)
        dr.scatter(nodes, dr.reinterpret_array(mi.Float, axis), 2 * node + 1)

        # Where each map's nodes start in the level's arrays (none: the map is finished).
        if n_maps == 1:                          # every position is in the one tree's level
            level_node, in_level = node_in_map, mi.Bool(True)
        else:
            level_offset = np.full(n_maps, 0xFFFFFFFF, dtype=np.uint32)
            level_offset[maps] = (np.arange(maps.shape[0]) * per_map).astype(np.uint32)
            offset = dr.gather(mi.UInt32, mi.UInt32(level_offset), point_map)
            level_node = dr.select(offset != 0xFFFFFFFF, offset + node_in_map, 0xFFFFFFFF)
            dr.eval(level_node)
            in_level = level_node != 0xFFFFFFFF
        last = level + 1 == int(depth.max(initial=0))
        largest = int((-(-counts[maps] // per_map)).max())   # photons of the largest node
        ids, rel, node_in_map = _partition_level(ids, rel, first, median, axis, level_node,
                                                 in_level, node_in_map, position, last,
                                                 largest < 1 << 16)
    return ids


#: Photons built together at most: maps are built in groups of consecutive maps of about
#: this many photons, because the partition's scatters slow down once the arrays outgrow the
#: caches (measured: one map of 3 x 10^6 photons builds in 1.3 s, of 3 x 10^7 in 36 s; eight
#: maps of 3.7 x 10^6 in one group in 2.5 times the time of eight groups). Small maps share
#: a group, so 1024 maps do not cost 1024 times the kernel launches.
GROUP_PHOTONS = 1 << 22


def _groups(counts: np.ndarray) -> list:
    """Runs of consecutive maps of at most :data:`GROUP_PHOTONS` photons (a larger map alone)."""
    groups, current, total = [], [], 0
    for m, c in enumerate(counts):
        if current and total + c > GROUP_PHOTONS:
            groups.append(current)
            current, total = [], 0
        current.append(m)
        total += int(c)
    groups.append(current)
    return groups


def _build_groups(p, ids, counts, starts, depth, node_base, nodes):
    """Split every tree, group of maps after group (:data:`GROUP_PHOTONS`); fill ``nodes``;
    return the tree order (indices of ``p``)."""
    coord = [p.x, p.y, p.z]
    groups = _groups(counts)
    if len(groups) == 1:
        return _partition_levels(coord, ids, counts, starts, depth, node_base, nodes)
    # The photons of each map as one run, maps in order (the tracer already gives them so;
    # a stable sort otherwise).
    n = dr.width(ids)
    grouped = n < 2 or bool(dr.all(dr.gather(mi.UInt32, ids, dr.arange(mi.UInt32, n - 1) + 1)
                                   >= dr.gather(mi.UInt32, ids, dr.arange(mi.UInt32, n - 1))))
    by_map = None if grouped else dr.argsort(ids)
    order = dr.empty(mi.UInt32, n)
    internal = (1 << depth) - 1
    for group in groups:
        first, stop = group[0], group[-1] + 1
        c = counts[first:stop]
        total = int(c.sum())
        if total == 0:
            continue
        span = dr.arange(mi.UInt32, total) + dr.opaque(mi.UInt32, int(starts[first]))
        source = span if by_map is None else dr.gather(mi.UInt32, by_map, span)
        local_coord = [dr.gather(mi.Float, a, source) for a in coord]
        local_ids = dr.gather(mi.UInt32, ids, source) - dr.opaque(mi.UInt32, first)
        local_nodes = dr.zeros(mi.Float, 2 * max(1, int(internal[first:stop].sum())))
        dr.eval(local_coord, local_ids)
        local_base = node_base[first:stop] - node_base[first]
        local = _partition_levels(local_coord, local_ids, c, starts[first:stop] - starts[first],
                                  depth[first:stop], local_base, local_nodes)
        dr.scatter(order, dr.gather(mi.UInt32, source, local), span)
        node_count = int(internal[first:stop].sum())
        if node_count:
            dr.scatter(nodes, dr.gather(mi.Float, local_nodes, dr.arange(mi.UInt32,
                                                                         2 * node_count)),
                       dr.arange(mi.UInt32, 2 * node_count)
                       + dr.opaque(mi.UInt32, 2 * int(node_base[first])))
        dr.eval(order, nodes)
    return order


def _host_uint32(values, name: str, allowed: str, largest: int) -> mi.UInt32:
    """Array-like ``values`` as ``mi.UInt32``: integers of shape (N,) in [0, ``largest``];
    anything else a ValueError saying that ``name`` must be ``allowed``."""
    host = np.asarray(values)
    if host.ndim != 1 or not (np.issubdtype(host.dtype, np.integer) or host.size == 0):
        raise ValueError(f"{name} must be {allowed}, one per point (shape (N,)); got dtype "
                         f"{host.dtype}, shape {host.shape}")
    if host.size and (host.min() < 0 or host.max() > largest):
        raise ValueError(f"{name} must be {allowed}; got values from {host.min()} to "
                         f"{host.max()}")
    return mi.UInt32(host.astype(np.uint32))


def _as_payload(payload, n_points):
    """``payload`` as ``mi.UInt32`` of one entry per point, or None: a ``mi.UInt32`` as it
    is, integers of shape (N,) converted; anything else a ValueError naming ``payload``."""
    if payload is None or isinstance(payload, mi.UInt32):
        pass
    elif dr.is_array_v(payload):
        raise ValueError(f"payload must be mi.UInt32 or integers of shape (N,), got "
                         f"{type(payload).__name__} (reinterpret other 32-bit values with "
                         f"dr.reinterpret_array)")
    else:
        payload = _host_uint32(payload, "payload", "integers in [0, 2^32)", 0xFFFFFFFF)
    if payload is not None and dr.width(payload) != n_points:
        raise ValueError(f"payload has {dr.width(payload)} entries for {n_points} points")
    return payload


def _check_input(p, ids, map_count, leaf_size, layout):
    if layout not in LAYOUTS:
        raise ValueError(f"layout must be one of {', '.join(repr(v) for v in LAYOUTS)}, got "
                         f"{layout!r}")
    n_points = dr.width(p)
    if dr.width(ids) != n_points:
        raise ValueError(f"map_ids has {dr.width(ids)} entries for {n_points} points")
    if not isinstance(leaf_size, (int, np.integer)) or isinstance(leaf_size, bool) or \
            not 1 <= leaf_size <= MAX_LEAF_SIZE:
        raise ValueError(f"leaf_size must be an integer in [1, {MAX_LEAF_SIZE}] (2^32: a forest "
                         f"holds fewer photons), got {leaf_size!r}")
    if n_points == 0:
        return
    check_coordinates(p, "photon positions")
    check_extent(p)


def check_extent(p):
    """A ValueError where the points span more than nothing but less than
    :data:`MIN_EXTENT` (the longest side of their bounding box): their distances cannot be
    told apart in float32 squares. Points all in one place are fine (every distance 0)."""
    span = dr.maximum(dr.maximum(dr.max(p.x) - dr.min(p.x), dr.max(p.y) - dr.min(p.y)),
                      dr.max(p.z) - dr.min(p.z))
    check_span(float(span[0]), "photon positions span {} (the longest side of their bounding "
               "box)", "scale the points and the queries up")


def check_span(extent: float, what: str, fix: str):
    """The one refusal of a set of points (or a scene) that spans ``extent``, more than
    nothing but less than :data:`MIN_EXTENT`: ``what`` says what spans it (``{}`` the
    extent), ``fix`` what to do."""
    if 0 < extent < MIN_EXTENT:
        raise ValueError(f"{what.format(f'{extent:.3g}')}, less than {MIN_EXTENT:g}: "
                         f"distances below 1e-15 are not resolved in float32 squares (those "
                         f"of points 1e-18 apart came out 0); {fix}")


def build_forest(points, map_ids=None, map_count: int | None = None,
                 leaf_size: int = LEAF_SIZE, payload=None, layout: str = "separate") -> Forest:
    """Build the kd-trees of the photon maps, on the device: one balanced tree per map, or
    with ``layout="shared"`` one per group of maps that share its split planes.

    Parameters
    ----------
    points : mi.Point3f, or array_like of shape (N, 3)
        Photon positions.
    map_ids : mi.UInt32 or array_like of int, shape (N,), optional
        The map each photon belongs to, in ``[0, map_count)``. Default: all in map 0.
    map_count : int, optional
        Number of maps n. Default: ``max(map_ids) + 1`` (1 for no photons). Maps that receive
        no photon are empty trees.
    leaf_size : int
        The most photons a leaf holds (>= 1).
    payload : mi.UInt32, optional
        A 32-bit value per photon, kept beside its position in :attr:`Forest.records`.
    layout : str
        "separate" (default): each map's tree is built from its photons alone, the paper's
        maps. "shared": consecutive maps of at most :data:`GROUP_PHOTONS` photons together
        share one tree, built over all their photons, whose leaves hold every map's photons
        map after map (leaves of at most :func:`shared_leaf_size` photons); a query over one
        map finds the photons its own tree would give (their sum may differ in the float
        rounding of its order), and a query over many maps descends once per group instead
        of once per map.

    Returns
    -------
    Forest

    Raises
    ------
    ValueError
        Mismatched sizes, map ids out of range, a map count outside [1, :data:`MAX_MAPS`], a
        leaf size that is not an integer >= 1, an unknown layout, a payload that is not
        32-bit integers, complex points, a position that is not finite or has a coordinate
        beyond +-:data:`MAX_COORD`, or points that span more than nothing but less than
        :data:`MIN_EXTENT`.

    Notes
    -----
    The points are sorted once per axis (Dr.Jit radix sorts); each level is then a few
    whole-array passes over every photon still in an unfinished tree
    (:func:`_partition_levels`): the bounding box of each node from its sorted runs, the
    longest axis, the median along it as the split, and a stable partition into the two
    halves. Node ``k`` of level ``d`` in a map of ``c`` photons covers the run
    ``[floor(k c / 2**d), floor((k+1) c / 2**d))``, so its two halves differ by at most one.
    """
    p = as_points(points)
    n_points = dr.width(p)
    if map_count is not None and (not isinstance(map_count, (int, np.integer))
                                  or isinstance(map_count, bool)
                                  or not 1 <= map_count <= MAX_MAPS):
        raise ValueError(f"map_count must be an integer in [1, {MAX_MAPS}], got {map_count!r}")
    if map_ids is None:
        ids = dr.zeros(mi.UInt32, n_points)
    elif isinstance(map_ids, mi.UInt32):
        ids = map_ids
    else:
        # The bound the ids may break: map_count's, or the most maps a forest holds.
        bound = f">= 0, < map_count = {map_count}" if map_count is not None else \
            f"in [0, {MAX_MAPS}) (a forest holds at most {MAX_MAPS} maps)"
        ids = _host_uint32(map_ids, "map_ids", f"integers {bound}", 0xFFFFFFFE)
    if map_count is None:
        map_count = int(dr.max(ids)[0]) + 1 if n_points and dr.width(ids) == n_points else 1
        if map_count > MAX_MAPS:
            raise ValueError(f"map_ids must lie in [0, {MAX_MAPS}) (a forest holds at most "
                             f"{MAX_MAPS} maps), got a maximum of {map_count - 1}")
    _check_input(p, ids, map_count, leaf_size, layout)
    payload = _as_payload(payload, n_points)
    counts = np.zeros(map_count, dtype=np.int64)
    if n_points:
        largest = int(dr.max(ids)[0])
        if largest >= map_count:
            raise ValueError(f"map_ids must lie in [0, {map_count}), got a maximum of {largest}")
        tally = dr.zeros(mi.UInt32, map_count)
        dr.scatter_reduce(dr.ReduceOp.Add, tally, 1, ids)
        counts = tally.numpy().astype(np.int64)
    first_map, maps_in_tree = _trees(counts, layout)
    map_tree = np.repeat(np.arange(first_map.shape[0]), maps_in_tree)
    tree_counts = np.add.reduceat(counts, first_map) if counts.size else counts
    starts = np.concatenate(([0], np.cumsum(tree_counts)))[:-1]
    depth = tree_depth(tree_counts, shared_leaf_size(leaf_size, maps_in_tree))
    internal, leaves = (1 << depth) - 1, 1 << depth
    entries = leaves * maps_in_tree + 1          # leaf-table entries per tree
    node_base = np.concatenate(([0], np.cumsum(internal)))[:-1]
    leaf_base = np.concatenate(([0], np.cumsum(entries)))[:-1]
    # One unused node when every tree is a single leaf: no empty arrays.
    nodes = dr.zeros(mi.Float, 2 * max(1, int(internal.sum())))

    one_map_trees = not np.any(maps_in_tree > 1)
    # Each photon's tree (its map's, when every tree holds one map).
    tree_ids = ids if one_map_trees else dr.gather(mi.UInt32, mi.UInt32(
        map_tree.astype(np.uint32)), ids)
    if n_points:
        order = _build_groups(p, tree_ids, tree_counts, starts, depth, node_base, nodes)
    else:
        order = dr.zeros(mi.UInt32, 0)
    del tree_ids
    leaf_first, leaf_tree, leaf_j = _leaf_starts(tree_counts, starts, leaves)
    if one_map_trees:
        leaf_start = mi.UInt32(leaf_first.astype(np.uint32))
    elif n_points:
        order, leaf_start = _shared_leaf_table(order, ids, leaf_first, leaf_tree, leaf_j,
                                               leaves, first_map, maps_in_tree, leaf_base,
                                               int(entries.sum()))
    else:
        leaf_start = dr.zeros(mi.UInt32, int(entries.sum()))
    records = _records(p, order, payload)
    is_leaf = leaf_j < leaves[leaf_tree]                    # not a tree's closing entry
    boxes = _leaf_boxes(records, leaf_start, leaf_base, leaf_tree[is_leaf], leaf_j[is_leaf],
                        maps_in_tree)
    return Forest(records=records, nodes=nodes, leaf_table=leaf_start, leaf_boxes=boxes,
                  tree_order=order, node_base=node_base, leaf_base=leaf_base,
                  internal_count=internal, photon_count=counts, leaf_size=int(leaf_size),
                  tree_first_map=first_map, tree_map_count=maps_in_tree, map_tree=map_tree,
                  layout=layout)


def _trees(counts: np.ndarray, layout: str):
    """(first map, maps) of every tree: one per map, or groups of consecutive maps of at
    most :data:`GROUP_PHOTONS` photons (a larger map alone) that share their split planes."""
    n = counts.shape[0]
    if layout == "separate" or n == 0:
        return np.arange(n, dtype=np.int64), np.ones(n, dtype=np.int64)
    groups = _groups(counts)
    return (np.array([g[0] for g in groups], dtype=np.int64),
            np.array([len(g) for g in groups], dtype=np.int64))


def _leaf_starts(tree_counts, starts, leaves):
    """The first position of every leaf of every tree and each tree's end, tree after tree
    (``leaves[t] + 1`` entries per tree; leaf j of a tree of c photons and L leaves starts c j
    / L, rounded down, after the tree's start), with each entry's tree and index j (j = L:
    the end). Host arrays, one entry per leaf: the separate layout's leaf table."""
    t = np.repeat(np.arange(tree_counts.shape[0]), leaves + 1)
    j = np.arange(t.shape[0]) - np.repeat(np.cumsum(leaves + 1) - (leaves + 1), leaves + 1)
    return starts[t] + (j * tree_counts[t]) // leaves[t], t, j


def _shared_leaf_table(order, ids, leaf_first, leaf_tree, leaf_j, leaves, first_map,
                       maps_in_tree, leaf_base, entries):
    """Put every leaf's photons map after map and make the leaf table of the trees (see
    :class:`Forest`). A position's leaf is the count of leaves (of all trees, in order) that
    start at or before it, less one (:func:`_leaf_starts`; an empty leaf starts where the
    next one does and is passed over); the photon's entry is leaf_base[t] + j s + (map -
    first map), and a stable sort by entry orders each leaf by map. An entry's first photon
    is the count of photons of the entries before it (a closing entry has none)."""
    n = dr.width(order)
    is_leaf = leaf_j < leaves[leaf_tree]                    # not a tree's closing entry
    first, t, j = leaf_first[is_leaf], leaf_tree[is_leaf], leaf_j[is_leaf]
    later = first[1:]                                       # every leaf start but the first
    later = later[later < n]                                # (empty leaves at the very end)
    count = dr.zeros(mi.UInt32, n)
    if later.size:
        dr.scatter_reduce(dr.ReduceOp.Add, count, 1, mi.UInt32(later.astype(np.uint32)),
                          mode=dr.ReduceMode.Local)      # (see below) empty leaves share
    leaf = dr.prefix_reduce(dr.ReduceOp.Add, count, exclusive=False)
    base = mi.UInt32((leaf_base[t] + j * maps_in_tree[t]).astype(np.uint32))
    first_of = mi.UInt32(first_map[t].astype(np.uint32))
    entry = dr.gather(mi.UInt32, base, leaf) + dr.gather(mi.UInt32, ids, order) - \
        dr.gather(mi.UInt32, first_of, leaf)
    perm = dr.argsort(entry)
    order = dr.gather(mi.UInt32, order, perm)
    count = dr.zeros(mi.UInt32, entries)
    # Not the default mode, which on the LLVM backend compiles the size of a target of up to
    # dr.expand_threshold() entries into the kernel (a kernel per photon count); the lanes
    # of a packet mostly share an entry, so they add up before the atomic add.
    dr.scatter_reduce(dr.ReduceOp.Add, count, 1, entry, mode=dr.ReduceMode.Local)
    dr.eval(order, count)
    return order, dr.prefix_sum(count)


@dr.syntax
def _leaf_boxes(records, leaf_table, leaf_base, tree, j, maps_in_tree):
    """The bounding box of every leaf, tree after tree (:attr:`Forest.leaf_boxes`; leaf
    ``j[l]`` of tree ``tree[l]``, as :func:`_leaf_starts` lists them): one lane per leaf runs
    over its photons, from the leaf-table entry of its first map's run to the entry of the
    next leaf's (the tree's closing entry, after its last leaf)."""
    total = int(tree.shape[0])
    if dr.hint(total == 0, mode="scalar"):
        return dr.zeros(mi.Float, 8)
    entry = leaf_base[tree] + j * maps_in_tree[tree]
    i = dr.gather(mi.UInt32, leaf_table, mi.UInt32(entry.astype(np.uint32)))
    end = dr.gather(mi.UInt32, leaf_table, mi.UInt32((entry + maps_in_tree[tree]).astype(
        np.uint32)))
    lo = dr.full(mi.Vector4f, dr.inf, total)
    hi = dr.full(mi.Vector4f, -dr.inf, total)
    while i < end:
        rec = dr.gather(mi.Vector4f, records, i)
        lo = dr.minimum(lo, rec)
        hi = dr.maximum(hi, rec)
        i += 1
    boxes = dr.empty(mi.Float, 8 * total)
    leaf = dr.arange(mi.UInt32, total)
    dr.scatter(boxes, mi.Vector4f(lo.x, lo.y, lo.z, 0.0), 2 * leaf)
    dr.scatter(boxes, mi.Vector4f(hi.x, hi.y, hi.z, 0.0), 2 * leaf + 1)
    dr.eval(boxes)
    return boxes


def _records(p, order, payload):
    """The 4-float records of the photons in tree ``order`` (at least one record): position
    and payload (0 without one), as :func:`rows_in_order` puts them."""
    if dr.width(order) == 0:
        return dr.zeros(mi.Float, RECORD_FLOATS)
    fourth = 0.0 if payload is None else dr.reinterpret_array(mi.Float, payload)
    return rows_in_order((p.x, p.y, p.z, fourth), order)


def rows_in_order(columns, order):
    """Four float columns (arrays, or a scalar for a constant column) at ``order``, as one
    flat array of 4-float rows: the rows are packed in their own order (sequential 16-byte
    stores), and each place of ``order`` reads its row with one 16-byte gather and writes it
    in turn. For 3.7 x 10^6 rows in random order this took 21 ms, against 62 ms for a scatter
    of each row to its place in the order (at random, into fresh memory) and 26-30 ms for a
    gather and a strided scatter per column; the packed copy costs 16 bytes per row while
    the result is made."""
    n = dr.width(order)
    own = dr.arange(mi.UInt32, n)
    packed = dr.empty(mi.Float, 4 * n)
    dr.scatter(packed, mi.Vector4f(*columns), own)
    dr.eval(packed)
    rows = dr.empty(mi.Float, 4 * n)
    dr.scatter(rows, dr.gather(mi.Vector4f, packed, order), own)
    dr.eval(rows)
    return rows
