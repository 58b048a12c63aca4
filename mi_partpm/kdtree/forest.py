"""The forest: one balanced kd-tree per photon map, in flat device arrays, and its build.

A *forest* holds the n partial photon maps of eq. (2) of the paper, one kd-tree per map. Every
tree is balanced and implicit: node ``j`` of a map has children ``2j+1`` and ``2j+2``; nodes
``0 .. I-1`` are internal (``I = 2**D - 1``) and nodes ``I .. 2I`` are the ``2**D`` leaves,
each holding a contiguous run of at most ``leaf_size`` photons. A node at level ``d`` covering
``c`` photons is split at their median along the longest axis of the node's bounding box
(paper, section 2.1), so all leaves of a map sit at the same depth.

Everything lives on the device (Dr.Jit arrays of the active variant):

- ``records``: 4 floats per photon in tree order, its position and a 32-bit payload (the
  photon map keeps the photon's direction code there), so a distance test and the payload
  are one 16-byte load;
- ``nodes``: 2 floats per internal node, the split value and the split axis (its bits);
- ``leaf_start``: per map, the first photon of every leaf and the map's end.

The build (:func:`build_forest`) sorts the points once per axis on the device (Dr.Jit's radix
sort), then splits one tree level at a time over all maps at once, with a handful of
whole-array kernels per level and no host sort. The queries over a forest are in
:mod:`.radius` and :mod:`.knn`. :func:`tree_bytes` is the one place that counts a tree's bytes.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import drjit as dr
import mitsuba as mi
import numpy as np

__all__ = ["Forest", "build_forest", "morton_codes", "morton_order", "tree_bytes",
           "tree_depth", "LEAF_SIZE", "NODE_BYTES", "LEAF_ENTRY_BYTES", "RECORD_FLOATS"]

#: Default number of photons per leaf. With the while-while walk of :mod:`.radius` large
#: leaves pay: on 200,000 Morton-ordered hit points of the Cornell box (r = 1/20, 460 photons
#: found per query) one map answers in 0.41 / 0.27 / 0.20 / 0.20 s with leaves of
#: 8 / 16 / 24 / 32, and on a room of 200,000 photons (900 found per query) in 0.64 / 0.43 /
#: 0.41 / 0.28 s (``partpm bench`` measures the current value against scipy).
LEAF_SIZE = 32

#: Bytes of one internal node: the split value (float32) and the split axis (uint32).
NODE_BYTES = 8
#: Bytes of one entry of the leaf table (uint32 first photon of a leaf).
LEAF_ENTRY_BYTES = 4
#: Floats per photon record: x, y, z and a 32-bit payload.
RECORD_FLOATS = 4


def tree_depth(counts, leaf_size: int = LEAF_SIZE) -> np.ndarray:
    """Depth D of the tree of a map of ``counts`` photons: the smallest D with
    ceil(c / 2**D) <= leaf_size (per map)."""
    counts = np.asarray(counts, dtype=np.int64)
    leaves_needed = np.maximum(1, -(-counts // leaf_size))
    return np.ceil(np.log2(leaves_needed)).astype(np.int64)


def tree_bytes(counts, leaf_size: int = LEAF_SIZE) -> np.ndarray:
    """Bytes of the tree of a map of ``counts`` photons (per map): ``2**D - 1`` internal
    nodes of :data:`NODE_BYTES` and a leaf table of ``2**D + 1`` entries."""
    depth = tree_depth(counts, leaf_size)
    return ((1 << depth) - 1) * NODE_BYTES + ((1 << depth) + 1) * LEAF_ENTRY_BYTES


@dataclass
class Forest:
    """The n kd-trees of one partitioned photon map, on the device.

    Photons are in tree order: map 0's photons first, each map's photons ordered so that
    every leaf is a contiguous run. ``tree_order`` maps a tree-order index back to the
    caller's photon index.

    Attributes
    ----------
    records : mi.Float, 4 N entries
        Per photon in tree order: x, y, z and a 32-bit payload (float bits).
    nodes : mi.Float, 2 I entries (at least 2)
        Per internal node, map after map: the split value and the split axis (0, 1, 2, as
        float bits).
    leaf_table : mi.UInt32
        For map m, entries ``leaf_base[m] .. leaf_base[m] + L_m`` are the first photon of each
        leaf and, last, the end of the map's photons (global tree-order indices).
    tree_order : mi.UInt32, N entries
        ``records`` entry t holds the caller's photon ``tree_order[t]``.
    node_base, leaf_base, internal_count, photon_count : (n,) int64 NumPy arrays
        Per-map offsets into ``nodes`` and ``leaf_table``, internal-node count ``I_m`` and the
        number of photons stored in the map.
    leaf_size : int
        The most photons a leaf holds.

    The NumPy properties :attr:`points`, :attr:`order`, :attr:`split_value`,
    :attr:`split_axis` and :attr:`leaf_start` copy the device arrays to the host, for
    inspection and tests.
    """

    records: object
    nodes: object
    leaf_table: object
    tree_order: object
    node_base: np.ndarray
    leaf_base: np.ndarray
    internal_count: np.ndarray
    photon_count: np.ndarray
    leaf_size: int
    _tables: dict = field(default_factory=dict, repr=False)

    @property
    def map_count(self) -> int:
        return int(self.photon_count.shape[0])

    @property
    def size(self) -> int:
        """Photons over all maps."""
        return int(self.photon_count.sum())

    @property
    def map_nbytes(self) -> np.ndarray:
        """Bytes of each map's tree (nodes and leaf table), photons not included."""
        return tree_bytes(self.photon_count, self.leaf_size)

    @property
    def nbytes(self) -> int:
        """Bytes of all trees (nodes and leaf tables), photons not included."""
        return int(self.map_nbytes.sum())

    def depth(self, m: int) -> int:
        """Depth D of map m's tree (0 for a map that is a single leaf)."""
        return int(np.log2(int(self.internal_count[m]) + 1))

    def tables(self) -> dict:
        """The per-map offsets as Dr.Jit arrays (made once)."""
        if not self._tables:
            self._tables = {name: mi.UInt32(getattr(self, name).astype(np.uint32))
                            for name in ("node_base", "leaf_base", "internal_count")}
        return self._tables

    # ---------------------------------------------------------------- host views

    @property
    def points(self) -> np.ndarray:
        """(N, 3) float32 positions in tree order."""
        return self.records.numpy().reshape(-1, RECORD_FLOATS)[:, :3]

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


def _as_points(points) -> mi.Point3f:
    if isinstance(points, mi.Point3f):
        return points
    pts = np.asarray(points, dtype=np.float32).reshape(-1, 3)
    return mi.Point3f(*[np.ascontiguousarray(pts[:, a]) for a in range(3)])


def _spread_bits(x):
    """The low 10 bits of ``x`` spread to every third bit (bit i to bit 3 i)."""
    x = (x | (x << 16)) & 0x030000FF
    x = (x | (x << 8)) & 0x0300F00F
    x = (x | (x << 4)) & 0x030C30C3
    return (x | (x << 2)) & 0x09249249


def morton_codes(p: mi.Point3f) -> mi.UInt32:
    """30-bit Morton (Z-order) codes of ``p`` over its bounding box, on the device."""
    code = dr.zeros(mi.UInt32, dr.width(p))
    for a, c in enumerate((p.x, p.y, p.z)):
        lo, hi = dr.min(c), dr.max(c)            # 1-wide arrays: no round trip to the host
        q = mi.UInt32(dr.clip((c - lo) * (1023.0 / dr.maximum(hi - lo, 1e-30)), 0.0, 1023.0))
        code |= _spread_bits(q) << a
    return code


def morton_order(points) -> np.ndarray:
    """The permutation that sorts ``points`` (K, 3) along a Z-order (Morton) curve.

    Queries that are close in space and close in this order walk the same nodes, side by side
    in a SIMD packet and one after another in the caches. The queries of :mod:`.radius` and
    :mod:`.knn` put their query points in this order themselves.
    """
    p = _as_points(points)
    if dr.width(p) == 0:
        return np.zeros(0, dtype=np.int64)
    return dr.argsort(morton_codes(p)).numpy().astype(np.int64)


def _presort(coord, map_ids, map_count):
    """Per axis, the permutation that sorts the points by map, then by that coordinate
    (two stable radix sorts on the device)."""
    orders = []
    for axis in range(3):
        order = dr.argsort(coord[axis])
        if map_count > 1:
            order = dr.gather(mi.UInt32, order,
                              dr.argsort(dr.gather(mi.UInt32, map_ids, order)))
        dr.eval(order)
        orders.append(order)
    return orders


def _split_level(coord, orders, first, stop, median):
    """Split axis and value of each node of a level, from its runs ``[first, stop)`` in the
    three sorted orders: the longest extent, and the coordinate of the ``median`` entry."""
    extent = [dr.gather(mi.Float, coord[a], dr.gather(mi.UInt32, orders[a], stop - 1))
              - dr.gather(mi.Float, coord[a], dr.gather(mi.UInt32, orders[a], first))
              for a in range(3)]
    axis = mi.UInt32(dr.select((extent[0] >= extent[1]) & (extent[0] >= extent[2]), 0,
                               dr.select(extent[1] >= extent[2], 1, 2)))
    value = [dr.gather(mi.Float, coord[a], dr.gather(mi.UInt32, orders[a], median))
             for a in range(3)]
    split = dr.select(axis == 0, value[0], dr.select(axis == 1, value[1], value[2]))
    dr.eval(axis, split)
    return axis, split


def _partition_level(orders, node_first, node_median, node_axis, level_node, in_level,
                     position):
    """Stable partition of the three sorted orders into every node's two halves.

    ``level_node`` is each position's node in the level's node arrays; a position right of
    its node's median goes right. Each order is partitioned with one prefix sum and one
    scatter. Returns the new orders and, per position, 1 where it went right."""
    n = dr.width(position)
    first = dr.gather(mi.UInt32, node_first, level_node, in_level)
    median = dr.gather(mi.UInt32, node_median, level_node, in_level)
    axis = dr.gather(mi.UInt32, node_axis, level_node, in_level)
    right_of_median = mi.UInt32(position >= median)
    goes_right = dr.zeros(mi.UInt32, n)          # per point: its side along its node's axis
    for a in range(3):
        dr.scatter(goes_right, right_of_median, orders[a], in_level & (axis == a))
    dr.eval(goes_right, first, median, in_level)
    new = []
    for a in range(3):
        right = dr.gather(mi.UInt32, goes_right, orders[a])
        rights_before = dr.prefix_sum(right)     # exclusive: right-goers before each position
        dr.eval(rights_before)
        rank_right = rights_before - dr.gather(mi.UInt32, rights_before, first)
        rank_left = (position - first) - rank_right
        target = dr.select(in_level, dr.select(right == 1, median + rank_right,
                                               first + rank_left), position)
        out = dr.empty(mi.UInt32, n)
        dr.scatter(out, orders[a], target)
        orders[a] = None                          # free the old order before the next one
        new.append(out)
    dr.eval(new)
    return new, right_of_median


def _partition_levels(coord, map_ids, counts, starts, depth, node_base, nodes):
    """Split every node of every level; fill ``nodes``; return the tree order (device).

    Presorted build: for each axis, a permutation of the points sorted along that axis within
    every map (:func:`_presort`). A node's bounds are then the first and last entries of its
    runs and its median the middle entry of the run of its longest axis, found by one small
    kernel over the level's nodes (:func:`_split_level`). Then every position looks up its
    node (it tracks its node's index within its map's level, which becomes 2k or 2k+1 at the
    next level) and the three permutations are partitioned stably into the left and right
    halves (:func:`_partition_level`): a handful of whole-array kernels per level, over all
    maps at once, with no division and no sort after the first.
    """
    n = dr.width(coord[0])
    n_maps = counts.shape[0]
    orders = _presort(coord, map_ids, n_maps)
    position = dr.arange(mi.UInt32, n)
    point_map = dr.gather(mi.UInt32, map_ids, orders[0])   # map of each position
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
        axis, split = _split_level(coord, orders, first, stop, median)
        node = mi.UInt32((node_base[node_map] + (per_map - 1) + node_index).astype(np.uint32))
        dr.scatter(nodes, split, 2 * node)
        dr.scatter(nodes, dr.reinterpret_array(mi.Float, axis), 2 * node + 1)

        # Where each map's nodes start in the level's arrays (none: the map is finished).
        level_offset = np.full(n_maps, 0xFFFFFFFF, dtype=np.uint32)
        level_offset[maps] = (np.arange(maps.shape[0]) * per_map).astype(np.uint32)
        offset = dr.gather(mi.UInt32, mi.UInt32(level_offset), point_map)
        in_level = offset != 0xFFFFFFFF
        level_node = dr.select(in_level, offset + node_in_map, 0)
        orders, went_right = _partition_level(orders, first, median, axis, level_node,
                                              in_level, position)
        node_in_map = dr.select(in_level, 2 * node_in_map + went_right, node_in_map)
        dr.eval(node_in_map, nodes)
    return orders[0]


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


def _check_input(p, ids, map_count, leaf_size):
    n_points = dr.width(p)
    if dr.width(ids) != n_points:
        raise ValueError(f"map_ids has {dr.width(ids)} entries for {n_points} points")
    if not isinstance(leaf_size, (int, np.integer)) or leaf_size < 1:
        raise ValueError(f"leaf_size must be an integer >= 1, got {leaf_size!r}")
    if n_points == 0:
        return
    if map_count < 1:
        raise ValueError(f"map_count must be >= 1, got {map_count}")
    if not bool(dr.all(dr.isfinite(p.x) & dr.isfinite(p.y) & dr.isfinite(p.z))):
        raise ValueError("photon positions must be finite")


def build_forest(points, map_ids=None, map_count: int | None = None,
                 leaf_size: int = LEAF_SIZE, payload=None) -> Forest:
    """Build one balanced kd-tree per photon map, on the device.

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

    Returns
    -------
    Forest

    Raises
    ------
    ValueError
        Mismatched sizes, map ids out of range, a leaf size below 1, or a position that is
        not finite.

    Notes
    -----
    The points are sorted once per axis (Dr.Jit radix sorts); each level is then a few
    whole-array passes over every photon still in an unfinished tree
    (:func:`_partition_levels`): the bounding box of each node from its sorted runs, the
    longest axis, the median along it as the split, and a stable partition into the two
    halves. Node ``k`` of level ``d`` in a map of ``c`` photons covers the run
    ``[floor(k c / 2**d), floor((k+1) c / 2**d))``, so its two halves differ by at most one.
    """
    p = _as_points(points)
    n_points = dr.width(p)
    if map_ids is None:
        ids = dr.zeros(mi.UInt32, n_points)
    elif isinstance(map_ids, mi.UInt32):
        ids = map_ids
    else:
        host = np.asarray(map_ids, dtype=np.int64).reshape(-1)
        if host.size and host.min() < 0:
            raise ValueError(f"map_ids must lie in [0, {map_count}), got a minimum of "
                             f"{host.min()}")
        ids = mi.UInt32(host.astype(np.uint32))
    if map_count is None:
        map_count = int(dr.max(ids)[0]) + 1 if n_points else 1
    _check_input(p, ids, map_count, leaf_size)
    counts = np.zeros(map_count, dtype=np.int64)
    if n_points:
        largest = int(dr.max(ids)[0])
        if largest >= map_count:
            raise ValueError(f"map_ids must lie in [0, {map_count}), got a maximum of {largest}")
        tally = dr.zeros(mi.UInt32, map_count)
        dr.scatter_reduce(dr.ReduceOp.Add, tally, 1, ids)
        counts = tally.numpy().astype(np.int64)
    starts = np.concatenate(([0], np.cumsum(counts)))[:-1]
    depth = tree_depth(counts, leaf_size)
    internal, leaves = (1 << depth) - 1, 1 << depth
    node_base = np.concatenate(([0], np.cumsum(internal)))[:-1]
    leaf_base = np.concatenate(([0], np.cumsum(leaves + 1)))[:-1]
    # One unused node when every map is a single leaf: no empty arrays.
    nodes = dr.zeros(mi.Float, 2 * max(1, int(internal.sum())))

    if n_points:
        order = _build_groups(p, ids, counts, starts, depth, node_base, nodes)
    else:
        order = dr.zeros(mi.UInt32, 0)
    records = _records(p, order, payload)

    # Leaf table: leaf j of map m starts at floor(j c / L); one closing entry per map.
    m = np.repeat(np.arange(map_count), leaves + 1)
    j = np.arange(int((leaves + 1).sum())) - np.repeat(leaf_base, leaves + 1)
    leaf_start = (starts[m] + (j * counts[m]) // leaves[m]).astype(np.uint32)
    return Forest(records=records, nodes=nodes, leaf_table=mi.UInt32(leaf_start),
                  tree_order=order, node_base=node_base, leaf_base=leaf_base,
                  internal_count=internal, photon_count=counts, leaf_size=int(leaf_size))


def _records(p, order, payload):
    """The 4-float records of the photons in tree ``order`` (at least one record)."""
    n = dr.width(order)
    records = dr.zeros(mi.Float, RECORD_FLOATS * max(n, 1))
    if n == 0:
        return records
    slot = dr.arange(mi.UInt32, n) * RECORD_FLOATS
    for a, c in enumerate((p.x, p.y, p.z)):
        dr.scatter(records, dr.gather(mi.Float, c, order), slot + a)
    if payload is not None:
        dr.scatter(records, dr.reinterpret_array(mi.Float, dr.gather(mi.UInt32, payload,
                                                                     order)), slot + 3)
    dr.eval(records)
    return records
