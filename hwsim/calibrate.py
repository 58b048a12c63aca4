"""Calibration: per-node, per-test, per-found and per-map costs fitted to measured CPU times.

The measured CPU time of map m answering all Q queries (``map_seconds`` in a workload, the
median over its repeats) is modelled as

    t_m = a * sum_q nodes + b * sum_q tested + c * sum_q found + d
          (+ the two cache terms below, where the workloads record the L1 cache)

with a, b, c, d >= 0: seconds per node visited, per photon tested, per photon found, and
per map run (the fixed cost of one map answering its queries: on the CPU, recording and
launching its kernel). One row per map of every n of every set.

**Packets.** On the CPU the queries do not walk alone: Dr.Jit's LLVM backend runs them side
by side in packets of ``lanes`` SIMD lanes (16 with AVX-512), and a packet loops until its
slowest lane is done, so a lane that finished early costs as much as the slowest one. Where a
workload records its ``lanes`` (WORKLOAD.md), each sum over queries is therefore taken per
packet of consecutive queries, in the order they ran, as ``lanes`` times the packet's largest
count (:func:`packet_sum`). This approximates what the CPU's loops paid for from below: the
walk's loops are nested (a descent and a leaf scan per leaf), and a packet pays the slowest
lane of every inner loop, not only of the whole walk. This matters across scenes:
where neighbouring hit points find very different numbers of photons (the Cornell box's
caustic beside its walls), the plain sums undercount the work more than on a scene of even
density, and costs fitted on one scene on plain sums are biased on the other. A scalar
processing element pays for its own counts only: hwsim's PE model runs the costs on the
plain per-query counts.

**Caches.** A map larger than the CPU's caches costs more per action: its nodes and records
come from further away. Where a workload records the CPU's L1 data cache (``l1_bytes``), two
more columns count nodes and tests times the doublings of the map's bytes beyond it,
log2(map bytes / L1) where positive, with costs ``per_node_cache`` and ``per_test_cache``
(seconds per action per doubling). Where no workload records ``l1_bytes``, the two costs are
not part of the model (:func:`cache_modelled`); sets that record it only in part are refused. They are the CPU's memory hierarchy: hwsim's PE model has
its own (SRAM, DRAM) and runs on the four costs above.

**The design.** Within one speedup run (one leaf size, one radius) nodes, tests and found
photons fall together as n grows, so the columns are nearly collinear and the fit cannot
tell the costs apart (it may put one of them at 0 and another absorbs it). ``partpm
calibrate`` therefore records *sets*: the same photons and hit points at several leaf sizes
(small leaves: many nodes per test; large leaves: many tests per node) and several radii
(found photons grow as r^2, tests per found photon shrink). :func:`design` reports how far
the columns are apart: their correlations, variance inflation factors and the condition
number of the scaled matrix the fit solves.

**The fit** (:func:`calibrate`, :func:`fit`) is non-negative least squares over all rows of
all sets, with columns scaled to unit norm (then unscaled). By default it weighs every row by
1 / t_m ("relative": it minimises relative errors, as the timing noise is relative and the
goal is a largest relative error); "absolute" weighs rows equally. Every cost comes with the
standard error of the least squares on the costs that stay positive (s^2 (A^T A)^-1 of the
weighted, scaled rows) and a bootstrap interval (rows resampled, 2.5 and 97.5 percentiles).
A cost fitted to 0 is flagged: the design did not identify it, or the time does not depend
on it.

:func:`check` predicts other per-map times with fitted costs: R^2, the largest and the median
relative error, overall and per set. :func:`cross_check` fits on one scene and predicts the
other, both ways, against :data:`GOAL`. :func:`write_costs` writes the fitted costs as the
file hwsim's ``[pe] costs = "fitted"`` reads (:mod:`hwsim.config`).

NumPy and SciPy only: hwsim never imports Mitsuba.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import nnls

from .workload import MapWorkloads, WorkloadSet

__all__ = ["Costs", "Fit", "COST_NAMES", "FEATURES", "WEIGHTINGS", "GOAL", "packet_sum",
           "features",
           "set_features", "fit", "calibrate", "check", "design", "cross_check", "goal",
           "write_costs", "read_costs", "format_fit", "format_check", "format_cross",
           "synthetic_workloads"]

#: The fitted costs, in the order of the feature columns.
COST_NAMES = ("per_node", "per_test", "per_found", "fixed", "per_node_cache",
              "per_test_cache")
#: What each column counts, per map.
FEATURES = ("nodes visited", "photons tested", "photons found", "map runs",
            "nodes x doublings beyond L1", "tests x doublings beyond L1")
#: The costs of the CPU's caches: in the model only where the workloads record ``l1_bytes``.
CACHE_COSTS = ("per_node_cache", "per_test_cache")
#: Row weightings of the fit: 1 / t (relative errors) or 1 (absolute errors).
WEIGHTINGS = ("relative", "absolute")
#: What a cross-scene prediction must reach: R^2, largest relative error, every cost > 0.
GOAL = {"r2": 0.95, "max_rel_error": 0.15}

#: Bytes of a tree node and a photon in the synthetic workloads (an RGB map's, unpadded:
#: position, direction code and RGB power; the golden reports are made with these).
SYNTHETIC_NODE_BYTES, SYNTHETIC_RECORD_BYTES = 8, 28


@dataclass
class Costs:
    """Seconds per node visited, photon tested, photon found, and per map run; and per node
    and per test for each doubling of the map beyond the L1 data cache."""

    per_node: float
    per_test: float
    per_found: float
    fixed: float
    per_node_cache: float = 0.0
    per_test_cache: float = 0.0

    def as_array(self) -> np.ndarray:
        return np.array([getattr(self, name) for name in COST_NAMES])

    def predict(self, x: np.ndarray) -> np.ndarray:
        return x @ self.as_array()


@dataclass
class Fit:
    """A calibration: the costs, how well they are determined, and the design behind them."""

    costs: Costs
    standard_errors: dict      # cost -> seconds (None for a cost fitted to 0)
    intervals: dict            # cost -> (low, high) bootstrap 95% interval, seconds
    zero_share: dict           # cost -> share of bootstrap fits that put it at 0
    zero: list                 # costs fitted to 0 (of those in the model)
    weighting: str
    rows: int
    sets: int
    design: dict
    self_check: dict
    unused: list = field(default_factory=list)   # cache costs not in the model (no L1)

    @property
    def all_positive(self) -> bool:
        return not self.zero

    def as_dict(self) -> dict:
        unused = set(self.unused)

        def modelled(d):
            return {k: v for k, v in d.items() if k not in unused}
        return {"costs": modelled(self.costs.__dict__),
                "standard_errors": modelled(self.standard_errors),
                "intervals": {k: list(v) for k, v in modelled(self.intervals).items()},
                "zero_share": modelled(self.zero_share), "zero": self.zero,
                **({"unused": sorted(unused)} if unused else {}),
                "all_positive": self.all_positive, "weighting": self.weighting,
                "rows": self.rows, "sets": self.sets, "design": self.design,
                "self": self.self_check}


def _as_sets(data) -> list:
    """A list of :class:`WorkloadSet` from one workload ``{n: MapWorkloads}``, one set, or a
    list of either."""
    if isinstance(data, WorkloadSet):
        return [data]
    if isinstance(data, dict):
        return [WorkloadSet("workloads", {}, data)]
    out = []
    for i, item in enumerate(data):
        out += [WorkloadSet(f"set{i}", {}, item)] if isinstance(item, dict) else _as_sets(item)
    if not out:
        raise ValueError("no workloads to calibrate on")
    return out


def packet_sum(counts, lanes: int | None = 1) -> float:
    """What ``counts`` (one per query, in the order the queries ran) cost in packets of
    ``lanes`` queries that each run until their slowest lane is done: per packet of
    consecutive queries, ``lanes`` times its largest count (a last, partial packet: its own
    size times its largest). ``lanes`` None or 1: the plain sum."""
    a = np.asarray(counts, dtype=np.float64).ravel()
    if lanes is None or lanes == 1 or a.size == 0:
        return float(a.sum())
    if not isinstance(lanes, (int, np.integer)) or lanes < 1:
        raise ValueError(f"lanes must be an integer >= 1, got {lanes!r}")
    full = a.size // lanes * lanes
    total = float(a[:full].reshape(-1, lanes).max(axis=1).sum()) * lanes
    if full < a.size:
        total += float(a[full:].max()) * (a.size - full)
    return total


def cache_doublings(map_bytes, l1_bytes) -> float:
    """log2(map_bytes / l1_bytes) where the map outgrows the L1 data cache, else 0 (and 0
    where ``l1_bytes`` is unknown)."""
    if not l1_bytes or map_bytes <= l1_bytes:
        return 0.0
    return float(np.log2(float(map_bytes) / float(l1_bytes)))


def cache_modelled(sets) -> bool:
    """Whether the cache costs are in the model of ``sets``: every set records the L1 cache
    (``l1_bytes``). ValueError where only some do: their cache costs cannot be fitted
    together."""
    recorded = [s.meta.get("l1_bytes") is not None for s in sets]
    if any(recorded) and not all(recorded):
        raise ValueError("some workloads record the L1 cache (l1_bytes) and some do not: "
                         "their cache costs cannot be fitted together (measure them again)")
    return bool(recorded) and all(recorded)


def _modelled_columns(sets) -> list:
    """The indices of :data:`COST_NAMES` in the model of ``sets``."""
    cache = cache_modelled(sets)
    return [j for j, name in enumerate(COST_NAMES) if cache or name not in CACHE_COSTS]


def features(loads, lanes: int | None = None,
             l1_bytes: int | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(X, t, n) of one workload ``{n: MapWorkloads}``: one row per map of every n, its
    counts summed over its queries (per packet of ``lanes``, :func:`packet_sum`), 1, and
    nodes and tests times the map's doublings beyond ``l1_bytes`` (:data:`FEATURES`); its
    median measured time; its n."""
    rows, times, ns = [], [], []
    for n, w in sorted(loads.items()):
        if w.map_seconds.size == 0:
            raise ValueError(f"workload n = {n} has no measured map_seconds to calibrate on")
        for m in range(n):
            nodes = packet_sum(w.nodes_visited[m], lanes)
            tests = packet_sum(w.photons_tested[m], lanes)
            level = cache_doublings(w.map_bytes[m], l1_bytes)
            rows.append([nodes, tests, packet_sum(w.photons_found[m], lanes), 1.0,
                         nodes * level, tests * level])
            times.append(float(np.median(w.map_seconds[m])))
            ns.append(n)
    return (np.array(rows).reshape(-1, len(COST_NAMES)), np.array(times), np.array(ns))


def set_features(data) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, list]:
    """(X, t, n, set index, sets) over every map of every n of every set of ``data``."""
    sets = _as_sets(data)
    xs, ts, ns, which = [], [], [], []
    for i, s in enumerate(sets):
        x, t, n = features(s.loads, s.meta.get("lanes"), s.meta.get("l1_bytes"))
        xs.append(x)
        ts.append(t)
        ns.append(n)
        which.append(np.full(t.size, i))
    t = np.concatenate(ts)
    if not np.all(t > 0):
        raise ValueError("every measured map time must be > 0 to calibrate on")
    return np.concatenate(xs), t, np.concatenate(ns), np.concatenate(which), sets


def _weighted(x, t, weighting):
    if weighting not in WEIGHTINGS:
        raise ValueError(f"weighting must be one of {', '.join(WEIGHTINGS)}, got "
                         f"{weighting!r}")
    w = 1.0 / t if weighting == "relative" else np.ones_like(t)
    return x * w[:, None], t * w


def _nnls(a, b) -> np.ndarray:
    """NNLS on columns scaled to unit norm (a column of zeros stays at 0)."""
    scale = np.linalg.norm(a, axis=0)
    scale = np.where(scale > 0, scale, 1.0)
    coef, _ = nnls(a / scale, b)
    return coef / scale


def fit(data, weighting: str = "relative") -> Costs:
    """The NNLS costs of ``data`` (a workload, a set or a list of them), in seconds."""
    x, t, *_ = set_features(data)
    a, b = _weighted(x, t, weighting)
    return Costs(*_nnls(a, b).tolist())


def _standard_errors(a, b, coef) -> dict:
    """Least-squares standard errors of the positive costs, s^2 (A_P^T A_P)^-1 on the
    weighted rows (P: the costs NNLS kept positive); None for a cost at 0."""
    positive = coef > 0
    out = {name: None for name in COST_NAMES}
    dof = b.size - int(positive.sum())
    if dof <= 0 or not positive.any():
        return out
    ap = a[:, positive]
    s2 = float(((a @ coef - b) ** 2).sum()) / dof
    scale = np.linalg.norm(ap, axis=0)
    cov = np.linalg.pinv((ap / scale).T @ (ap / scale)) * s2 / np.outer(scale, scale)
    for name, v in zip(np.array(COST_NAMES)[positive], np.sqrt(np.maximum(np.diag(cov), 0))):
        out[str(name)] = float(v)
    return out


def _bootstrap(a, b, resamples, seed):
    """NNLS of ``resamples`` bootstrap resamples of the rows: (resamples, columns) costs."""
    rng = np.random.default_rng(seed)
    m = b.size
    out = np.empty((resamples, a.shape[1]))
    for i in range(resamples):
        pick = rng.integers(0, m, m)
        out[i] = _nnls(a[pick], b[pick])
    return out


def calibrate(data, weighting: str = "relative", resamples: int = 400,
              seed: int = 0) -> Fit:
    """Fit the costs to every map of ``data`` (a workload, a set, or a list of them) and say
    how well they are determined: standard errors, bootstrap intervals (``resamples`` seeded
    resamples of the rows), the costs fitted to 0, the design's conditioning, and the fit's
    check on its own rows."""
    x, t, _, _, sets = set_features(data)
    kept = _modelled_columns(sets)
    unused = [name for j, name in enumerate(COST_NAMES) if j not in kept]
    if t.size < len(kept) + 1:
        raise ValueError(f"needs >= {len(kept) + 1} measured maps for its "
                         f"{len(kept)} costs, the workloads hold {t.size}")
    a, b = _weighted(x, t, weighting)
    coef = _nnls(a, b)
    boot = (_bootstrap(a, b, resamples, seed) if resamples
            else np.empty((0, len(COST_NAMES))))
    intervals, zero_share = {}, {}
    for j, name in enumerate(COST_NAMES):
        if name in unused:
            continue
        if boot.size:
            intervals[name] = (float(np.percentile(boot[:, j], 2.5)),
                               float(np.percentile(boot[:, j], 97.5)))
            zero_share[name] = float(np.mean(boot[:, j] <= 0))
        else:
            intervals[name], zero_share[name] = (math.nan, math.nan), math.nan
    costs = Costs(*coef.tolist())
    errors = {k: v for k, v in _standard_errors(a, b, coef).items() if k not in unused}
    return Fit(costs=costs, standard_errors=errors,
               intervals=intervals, zero_share=zero_share,
               zero=[n for n, c in zip(COST_NAMES, coef) if not c > 0 and n not in unused],
               unused=unused,
               weighting=weighting, rows=int(t.size), sets=len(sets),
               design=design(sets, weighting), self_check=check(costs, sets))


def design(data, weighting: str = "relative") -> dict:
    """How far apart the design puts the costs' columns, over every map of ``data``:
    the correlations of nodes, tests and found photons per map (``correlation``, 3 x 3), each
    column's variance inflation factor against the other columns in the model (the constant
    and, where modelled, the cache columns; 1 / (1 - R^2) of that regression; 1:
    independent, over 10: nearly collinear), and the condition number of the weighted matrix
    with unit-norm columns that NNLS solves."""
    x, t, _, _, sets = set_features(data)
    kept = _modelled_columns(sets)
    x = x[:, kept]
    counts = x[:, :3]
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = np.corrcoef(counts.T) if counts.shape[0] > 1 else np.full((3, 3), np.nan)
    vif = {}
    for j, name in enumerate(("nodes", "tests", "found")):
        others = np.delete(x, j, axis=1)
        coef, *_ = np.linalg.lstsq(others, counts[:, j], rcond=None)
        resid = counts[:, j] - others @ coef
        total = ((counts[:, j] - counts[:, j].mean()) ** 2).sum()
        r2 = 1.0 - float((resid ** 2).sum()) / total if total > 0 else 1.0
        vif[name] = 1.0 / (1.0 - r2) if r2 < 1 else math.inf
    a, _ = _weighted(x, t, weighting)
    norm = np.linalg.norm(a, axis=0)
    cond = float(np.linalg.cond(a / np.where(norm > 0, norm, 1.0)))
    return {"columns": [FEATURES[j] for j in kept], "correlation": np.round(corr, 6).tolist(),
            "vif": vif, "condition_number": cond, "weighting": weighting,
            "rows": int(t.size)}


def _scores(t, p) -> dict:
    rel = (p - t) / t
    ss_tot = float(((t - t.mean()) ** 2).sum())
    return {"r2": 1.0 - float(((t - p) ** 2).sum()) / ss_tot if ss_tot > 0 else math.nan,
            "max_rel_error": float(np.max(np.abs(rel))),
            "median_rel_error": float(np.median(np.abs(rel))),
            "bias": float(np.median(rel)), "maps": int(t.size)}


def check(costs: Costs, data) -> dict:
    """How well ``costs`` predict the per-map times of ``data``: R^2, the largest and median
    relative error and the median signed one (``bias``: predicted over measured, less 1),
    over every map and per set (``per_set``, with its leaf size and radius); the worst map;
    and per n the median time measured and predicted (``per_n``, pooled over sets)."""
    x, t, ns, which, sets = set_features(data)
    p = costs.predict(x)
    out = _scores(t, p)
    worst = int(np.argmax(np.abs(p - t) / t))
    s = sets[which[worst]]
    out["worst"] = {"set": s.name, "n": int(ns[worst]), "measured": float(t[worst]),
                    "predicted": float(p[worst])}
    out["per_set"] = {}
    for i, s in enumerate(sets):
        sel = which == i
        out["per_set"][s.name] = {"leaf_size": s.meta.get("leaf_size"),
                                  "radius": s.meta.get("radius"),
                                  "radius_fraction": s.meta.get("radius_fraction"),
                                  **_scores(t[sel], p[sel])}
    out["per_n"] = {int(n): {"measured": float(np.median(t[ns == n])),
                             "predicted": float(np.median(p[ns == n]))}
                    for n in np.unique(ns)}
    return out


def goal(fit_: Fit, prediction: dict) -> dict:
    """Whether a cross-scene prediction meets :data:`GOAL` (R^2, largest relative error) with
    every cost positive."""
    met = {"r2": prediction["r2"] >= GOAL["r2"],
           "max_rel_error": prediction["max_rel_error"] <= GOAL["max_rel_error"],
           "all_positive": fit_.all_positive}
    return {**met, "met": all(met.values())}


def cross_check(a, b, name_a: str = "a", name_b: str = "b", weighting: str = "relative",
                resamples: int = 400, seed: int = 0) -> dict:
    """Fit on ``a``, predict ``b``, and the other way round (each a workload, a set or a
    list of them): both fits (:meth:`Fit.as_dict`), both predictions (:func:`check`) and
    whether each meets :data:`GOAL`."""
    out = {"scenes": [name_a, name_b], "goal": dict(GOAL), "directions": []}
    for (fn, fd), (pn, pd) in (((name_a, a), (name_b, b)), ((name_b, b), (name_a, a))):
        f = calibrate(fd, weighting, resamples, seed)
        pred = check(f.costs, pd)
        out["directions"].append({"fit_on": fn, "predicts": pn, "fit": f.as_dict(),
                                  "prediction": pred, "goal": goal(f, pred)})
    return out


# ----------------------------------------------------------------------- the costs file

def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, int):
        return str(v)
    return repr(float(v))


def write_costs(path, fit_: Fit, *, scene: str, threads: int | None, source: str = ""):
    """Write ``fit_``'s costs as the file ``[pe] fitted_costs`` names (TOML): seconds per
    node, test, found and map run as measured with ``threads`` CPU threads (and, where
    modelled, the two cache costs, which the PE model does not read), their standard errors
    and intervals, and where they come from."""
    from pathlib import Path
    c = fit_.costs
    lines = ["# Costs fitted by hwsim.calibrate to measured per-map CPU times (partpm "
             "calibrate).",
             "# hwsim's [pe] costs = \"fitted\" reads them: cycles per node / test / found =",
             "# seconds x threads x clock_hz (a PE as fast as one measured CPU thread), cycles",
             "# per map = seconds_per_map x clock_hz (the host's serial cost of a map run).",
             f"scene = {_toml_value(scene)}",
             f"source = {_toml_value(source)}",
             f"threads = {int(threads) if threads else 1}",
             f"weighting = {_toml_value(fit_.weighting)}",
             f"rows = {fit_.rows}",
             f"sets = {fit_.sets}",
             f"all_positive = {_toml_value(fit_.all_positive)}",
             f"seconds_per_node = {_toml_value(c.per_node)}",
             f"seconds_per_test = {_toml_value(c.per_test)}",
             f"seconds_per_found = {_toml_value(c.per_found)}",
             f"seconds_per_map = {_toml_value(c.fixed)}",
             "# The CPU's caches (per action per doubling of the map beyond L1): not run by the",
             "# PE model, whose memory is its own SRAM and DRAM."]
    modelled = [n for n in CACHE_COSTS if n not in fit_.unused]
    lines += [f"{_CACHE_KEYS[n]} = {_toml_value(getattr(c, n))}" for n in modelled]
    lines += ["", "[standard_error]                # seconds; absent for a cost fitted to 0"]
    keys = {**_FILE_KEYS, **{n: _CACHE_KEYS[n] for n in modelled}}
    for name in keys:
        se = fit_.standard_errors.get(name)
        if se is not None:
            lines.append(f"{keys[name]} = {_toml_value(se)}")
    lines += ["", "[interval]                      # bootstrap 2.5 and 97.5 percentiles"]
    for name in keys:
        lo, hi = fit_.intervals[name]
        if lo == lo and hi == hi:
            lines.append(f"{keys[name]} = [{_toml_value(lo)}, {_toml_value(hi)}]")
    Path(path).write_text("\n".join(lines) + "\n")
    return Path(path)


#: Cost name -> its key in the costs file.
_FILE_KEYS = {"per_node": "seconds_per_node", "per_test": "seconds_per_test",
              "per_found": "seconds_per_found", "fixed": "seconds_per_map"}
#: The cache costs' keys (written where modelled; the PE model does not read them).
_CACHE_KEYS = {"per_node_cache": "seconds_per_node_per_doubling",
               "per_test_cache": "seconds_per_test_per_doubling"}


def read_costs(path) -> dict:
    """The costs file of :func:`write_costs`: ``{"seconds_per_node", "seconds_per_test",
    "seconds_per_found", "seconds_per_map": float >= 0, "threads": int >= 1, "scene": str}``.
    Raises ValueError naming the file and the key that is missing or wrong."""
    import tomllib
    try:
        with open(path, "rb") as f:
            data = tomllib.load(f)
    except OSError as e:
        raise ValueError(f"fitted costs file {path}: {e.strerror or e}") from None
    except tomllib.TOMLDecodeError as e:
        raise ValueError(f"fitted costs file {path} is not TOML: {e}") from None
    out = {"scene": str(data.get("scene", "")), "source": str(data.get("source", ""))}
    for key in _FILE_KEYS.values():
        v = data.get(key)
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) \
                or v < 0:
            raise ValueError(f"fitted costs file {path}: {key} must be a finite number >= 0 "
                             f"(seconds), got {v!r}")
        out[key] = float(v)
    threads = data.get("threads", 1)
    if isinstance(threads, bool) or not isinstance(threads, int) or threads < 1:
        raise ValueError(f"fitted costs file {path}: threads must be an integer >= 1, got "
                         f"{threads!r}")
    out["threads"] = threads
    return out


# ----------------------------------------------------------------------------- text

def _ns(v):
    return "n/a" if v is None or v != v else f"{v * 1e9:.3g}"


def format_fit(f: dict, scene: str = "") -> list:
    """Lines: the design's conditioning, each cost with its standard error and interval, the
    costs fitted to 0, and the fit's errors on its own rows (``f``: :meth:`Fit.as_dict`)."""
    d = f["design"]
    corr = d["correlation"]
    lines = [f"design{' of ' + scene if scene else ''}: {f['rows']} maps in {f['sets']} "
             f"set{'s' if f['sets'] != 1 else ''}; correlation nodes-tests "
             f"{corr[0][1]:.3f}, nodes-found {corr[0][2]:.3f}, tests-found {corr[1][2]:.3f}; "
             f"VIF " + ", ".join(f"{k} {v:.1f}" for k, v in d["vif"].items()) +
             f"; condition number {d['condition_number']:.3g}"]
    unit = {"per_node": "ns/node", "per_test": "ns/test", "per_found": "ns/found",
            "per_node_cache": "ns/node per doubling beyond L1",
            "per_test_cache": "ns/test per doubling beyond L1"}
    for name in COST_NAMES:
        if name not in f["costs"]:             # not in the model (as_dict leaves it out)
            continue
        c, se = f["costs"][name], f["standard_errors"].get(name)
        lo, hi = f["intervals"][name]
        if name == "fixed":
            text = (f"  per map run: {c * 1e3:.3g} ms (se {se * 1e3:.2g} ms, 95% "
                    f"{lo * 1e3:.3g}-{hi * 1e3:.3g} ms)" if se is not None else
                    f"  per map run: {c * 1e3:.3g} ms (95% {lo * 1e3:.3g}-{hi * 1e3:.3g} ms)")
        else:
            text = (f"  {unit[name]}: {_ns(c)} (se {_ns(se)}, 95% {_ns(lo)}-{_ns(hi)})")
        if name in f["zero"]:
            text += "  FITTED TO 0: not identified by these workloads"
        elif f["zero_share"].get(name, 0) > 0.025:
            text += f"  (0 in {f['zero_share'][name] * 100:.0f}% of the bootstrap fits)"
        lines.append(text)
    s = f["self"]
    lines.append(f"  on its own maps ({f['weighting']} weighting): R^2 {s['r2']:.4f}, largest "
                 f"error {s['max_rel_error'] * 100:.1f}%, median "
                 f"{s['median_rel_error'] * 100:.1f}%")
    return lines


def format_check(pred: dict, indent: str = "  ") -> list:
    """Lines: per set, R^2 and the largest, median and signed median relative error."""
    lines = [f"{indent}{'set':<18} {'leaf':>5} {'r':>8} {'maps':>5} {'R^2':>7} "
             f"{'largest':>8} {'median':>7} {'bias':>7}"]
    for name, s in pred["per_set"].items():
        r = s.get("radius")
        lines.append(f"{indent}{name:<18} {str(s.get('leaf_size') or '-'):>5} "
                     f"{(f'{r:.4g}' if r is not None else '-'):>8} {s['maps']:5d} "
                     f"{s['r2']:7.3f} {s['max_rel_error'] * 100:7.1f}% "
                     f"{s['median_rel_error'] * 100:6.1f}% {s['bias'] * 100:+6.1f}%")
    w = pred["worst"]
    lines.append(f"{indent}worst map: {w['set']}, n = {w['n']}: measured "
                 f"{w['measured'] * 1e3:.1f} ms, predicted {w['predicted'] * 1e3:.1f} ms")
    return lines


def format_cross(cross: dict) -> str:
    """The cross-scene check as text: per direction the fit, the prediction per set and
    whether it meets :data:`GOAL`."""
    g = cross["goal"]
    lines = [f"cross-scene check (goal: R^2 >= {g['r2']}, largest error <= "
             f"{g['max_rel_error'] * 100:.0f}%, every cost > 0)"]
    for d in cross["directions"]:
        p, ok = d["prediction"], d["goal"]
        lines.append(f"fitted on {d['fit_on']}, predicts {d['predicts']}: R^2 {p['r2']:.3f}, "
                     f"largest error {p['max_rel_error'] * 100:.1f}%, median "
                     f"{p['median_rel_error'] * 100:.1f}%: goal "
                     f"{'met' if ok['met'] else 'NOT met'} (R^2 {'ok' if ok['r2'] else 'no'}, "
                     f"largest error {'ok' if ok['max_rel_error'] else 'no'}, costs "
                     f"{'all > 0' if ok['all_positive'] else 'some 0'})")
        lines += format_fit(d["fit"], d["fit_on"])
        lines.append(f"  the fit of {d['fit_on']} on the maps of {d['predicts']}, per set:")
        lines += format_check(p)
    return "\n".join(lines)


def synthetic_workloads(maps=(1, 2, 4, 8), queries=500, photons=20_000, seed=0,
                        costs=(2e-8, 1e-8, 5e-9, 1e-4), noise=0.0):
    """A seeded synthetic family of workloads shaped like real ones (for tests and demos).

    Photons found split evenly over the maps; tested per found and nodes per query grow as
    maps get sparser, as measured. ``map_seconds`` follow ``costs`` (per node, test, found,
    fixed) with optional relative noise.
    """
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
