"""Balanced kd-trees over partitioned photon maps, and the queries over them.

- :mod:`.forest`: the forest (implicit balanced trees in flat device arrays, one per map or
  one per group of maps sharing split planes) and its build; :func:`tree_bytes` counts a
  separate tree's bytes;
- :mod:`.radius`: the fixed-radius query (eq. 2), a stackless while-while walk;
- :mod:`.knn`: the k-nearest-neighbour query (eq. 1), nearer child first with a per-lane heap,
  and the NumPy front ends of both queries, shaped as scipy's ``query`` and
  ``query_ball_point`` answer (:func:`knn_neighbours`, :func:`radius_neighbours`).

Both queries walk their query points in Morton order and answer in the caller's, and pass every
photon they accept to a callback with its squared distance, so a density kernel is one function
of the distance (:mod:`mi_partpm.estimate`).
"""
from .forest import (LAYOUTS, LEAF_BOX_BYTES, LEAF_ENTRY_BYTES, LEAF_SIZE, MAX_COORD, MAX_MAPS,
                     NODE_BYTES, RECORD_FLOATS, Forest, build_forest, morton_codes, morton_order,
                     rows_in_order, shared_leaf_size, tree_bytes, tree_depth)
from .knn import KnnResult, knn_neighbours, knn_query, radius_neighbours
from .radius import (ORDERS, WALKS, CallbackError, QueryStats, ResultTypeError,
                     photon_position, radius_query)

__all__ = ["Forest", "build_forest", "morton_codes", "morton_order", "tree_bytes",
           "tree_depth", "shared_leaf_size", "LAYOUTS", "LEAF_SIZE", "NODE_BYTES",
           "LEAF_ENTRY_BYTES", "LEAF_BOX_BYTES", "RECORD_FLOATS", "radius_query", "QueryStats",
           "photon_position", "ORDERS", "WALKS", "knn_query", "KnnResult", "knn_neighbours",
           "rows_in_order", "MAX_MAPS", "MAX_COORD", "radius_neighbours", "CallbackError",
           "ResultTypeError"]
