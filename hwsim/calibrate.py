"""Calibration: fit per-node, per-test, per-found and fixed costs to measured per-map times.

The measured CPU time of map m answering all queries (``map_seconds`` in the workload) is
modelled as

    t_m = a * sum_q nodes + b * sum_q tested + c * sum_q found + d

with a, b, c, d >= 0 (non-negative least squares over every map of every n of one scene).
:func:`check` then predicts another scene's per-map times with the fitted costs and reports
R^2 and the largest relative error: whether the traversal counts explain the time.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import nnls

__all__ = ["Costs", "features", "fit", "check", "synthetic_workloads"]

#: Bytes of a tree node and a photon record in the synthetic workloads (those of an RGB map).
SYNTHETIC_NODE_BYTES, SYNTHETIC_RECORD_BYTES = 8, 28


@dataclass
class Costs:
    per_node: float
    per_test: float
    per_found: float
    fixed: float

    def predict(self, x: np.ndarray) -> np.ndarray:
        return x @ np.array([self.per_node, self.per_test, self.per_found, self.fixed])


def features(loads) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(X, t, n): one row per map of every n: summed counts and 1; its median time; its n."""
    rows, times, ns = [], [], []
    for n, w in sorted(loads.items()):
        if w.map_seconds.size == 0:
            raise ValueError(f"workload n = {n} has no measured map_seconds to calibrate on")
        for m in range(n):
            rows.append([float(w.nodes_visited[m].sum()), float(w.photons_tested[m].sum()),
                         float(w.photons_found[m].sum()), 1.0])
            times.append(float(np.median(w.map_seconds[m])))
            ns.append(n)
    return np.array(rows), np.array(times), np.array(ns)


def fit(loads) -> Costs:
    """Non-negative least-squares costs (seconds per node, test, found, and per map run)."""
    x, t, _ = features(loads)
    # Scale columns to comparable magnitudes before NNLS; undo afterwards.
    scale = np.maximum(np.abs(x).max(axis=0), 1e-30)
    coef, _ = nnls(x / scale, t)
    coef = coef / scale
    return Costs(*coef.tolist())


def check(costs: Costs, loads) -> dict:
    """How well ``costs`` predict the per-map times of ``loads``: R^2, largest relative error,
    and the per-n medians measured and predicted."""
    x, t, ns = features(loads)
    p = costs.predict(x)
    ss_res = float(((t - p) ** 2).sum())
    ss_tot = float(((t - t.mean()) ** 2).sum())
    per_n = {int(n): {"measured": float(np.median(t[ns == n])),
                      "predicted": float(np.median(p[ns == n]))} for n in np.unique(ns)}
    return {"r2": 1.0 - ss_res / ss_tot if ss_tot > 0 else float("nan"),
            "max_rel_error": float(np.max(np.abs(p - t) / t)),
            "per_n": per_n}


def synthetic_workloads(maps=(1, 2, 4, 8), queries=500, photons=20_000, seed=0,
                        costs=(2e-8, 1e-8, 5e-9, 1e-4), noise=0.0):
    """A seeded synthetic family of workloads shaped like real ones (for tests and demos).

    Photons found split evenly over the maps; tested per found and nodes per query grow as
    maps get sparser, as measured. ``map_seconds`` follow ``costs`` (per node, test, found,
    fixed) with optional relative noise.
    """
    from .workload import MapWorkloads
    rng = np.random.default_rng(seed)
    found1 = rng.gamma(4.0, 40.0, queries)
    loads = {}
    for n in maps:
        depth = max(1, int(np.log2(photons / n / 16)))
        found = rng.poisson(np.tile(found1 / n, (n, 1))).astype(np.uint32)
        tested = (found * (1.7 + 0.1 * np.log2(n)) + rng.poisson(8, (n, queries))).astype(
            np.uint32)
        nodes = (depth + 1 + tested // 16 * 2 + rng.poisson(3, (n, queries))).astype(np.uint32)
        x = np.stack([nodes.sum(1), tested.sum(1), found.sum(1), np.ones(n)], axis=1)
        t = x @ np.array(costs)
        t = t * (1 + noise * rng.standard_normal(n))
        loads[n] = MapWorkloads(n=n, nodes_visited=nodes, photons_tested=tested,
                                photons_found=found, map_photons=np.full(n, photons // n),
                                map_bytes=np.full(n, photons // n * SYNTHETIC_RECORD_BYTES),
                                map_seconds=np.tile(t[:, None], (1, 3)),
                                bytes_per_node=SYNTHETIC_NODE_BYTES,
                                bytes_per_photon=SYNTHETIC_RECORD_BYTES)
    return loads
