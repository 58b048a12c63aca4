"""The paper's speedup experiment (figures 5 and 6): per-map density-estimation time vs n.

For each n, the photons are split into n maps and ONE map answers the fixed-radius queries of
every hit point of the image; its time (median over the maps and the repeats) against n = 1 is
the speedup of density estimation that n processors with one map each would see. The
traversal counts per query (nodes visited, photons tested, photons found) explain it, and are
saved per map as the workload that ``hwsim`` replays (written by :mod:`hwsim.workload`, format
in ``hwsim/WORKLOAD.md``).

The same photons serve every n: they are traced once into L = lcm(n values) streams, and map j
of n holds the streams i with i mod n = j, so every map still holds its own N/n emissions
while the total work is identical across n; the per-map estimates of each n must add up to
the n = 1 estimate (eq. 2), which the run checks: a run whose sum at some hit point is off by
more than float32 rounding can explain (:func:`gather_bound`) stops with a
:class:`GatherError` rather than record a workload that is not the one-map workload split n
ways.

:func:`run_speedup` is three phases: :func:`_setup` (scene, photons, hit points),
:func:`_measure` per n (times, counts, the gather's error) and the report (CSV, JSON, plot,
workloads).
"""
from __future__ import annotations

import csv
import json
import logging
import math
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Optional, Sequence

import drjit as dr
import mitsuba as mi
import numpy as np

from hwsim.workload import MapWorkloads, save_workloads
from .provenance import code_version, l1_data_bytes, scene_digest, simd_lanes
from .. import memory
from ..estimate import radiance_estimate
from ..eyepath import first_hits
from ..kdtree import LEAF_SIZE, NODE_BYTES
from ..photonmap import build_photon_maps, fixed_radius, record_bytes
from ..scenes import load_scene
from ..timing import timed
from ..trace import trace_photons

__all__ = ["run_speedup", "check_speedup", "check_maps", "format_speedup", "plot_speedup",
           "gather_bound", "gather_excess", "GatherError", "build_maps", "time_map", "map_counts",
           "map_workloads"]

log = logging.getLogger("mi_partpm")

#: float32's unit roundoff: a sum or product of float32 values is off by at most this share.
FLOAT32_ROUNDOFF = 2.0 ** -24


class GatherError(RuntimeError):
    """The measured estimates are not the workload the experiment stands for: the per-map
    estimates of some n do not add up to the one-map estimate (eq. 2), or the one-map
    estimate is 0 at every hit point although its queries found photons."""


def gather_bound(reference, found):
    """How far the sum of a hit point's n per-map estimates may lie from its one-map
    estimate ``reference`` (Q, 3) by float32 rounding alone, with ``found`` (Q,) photons
    within r of it: (2 m + 4) 2^-24 |reference| for m photons.

    Both sides sum the same positive contributions f_r * dPhi_p in float32, in another order
    (one tree, or n trees then float64 over the maps), and multiply by the same f_r and
    1 / (pi r^2): a float32 sum of m positive terms is off by at most (m - 1) 2^-24 of itself,
    each product by 2^-24, so the two differ by at most (2 m + 2) 2^-24 of the estimate, to
    first order; 4 leaves room for the second. A photon lost or counted twice changes a
    hit point by about 1 / m of it, more than the bound while m < 2900 (a few hundred photons
    are found at the paper's size, a few thousand in a caustic, where the bound loosens).
    Measured at the paper's 10^5 photons, n = 2 - 32: 0.09 - 0.11 of the bound at the worst
    hit point, on the Cornell box and on the Happy Buddha."""
    found = np.asarray(found, np.float64).reshape(-1, 1)
    return (2.0 * found + 4.0) * FLOAT32_ROUNDOFF * np.abs(np.asarray(reference, np.float64))


def gather_excess(gathered, reference, found):
    """The largest |gathered - reference| / :func:`gather_bound` over the hit points and
    colour channels (at most 1 when float32 rounding explains the difference; infinite where
    an estimate is not 0 but the reference is), and the hit point where it is (-1 when the
    two agree exactly)."""
    gathered, reference = np.asarray(gathered, np.float64), np.asarray(reference, np.float64)
    diff = np.abs(gathered - reference)
    if not diff.size or not diff.any():
        return 0.0, -1
    bound = gather_bound(reference, found)
    with np.errstate(divide="ignore", invalid="ignore"):
        share = np.where(diff > 0, diff / bound, 0.0)
    worst = int(np.argmax(share.max(axis=1)))
    return float(share[worst].max()), worst


def _check_gather(n: int, reference_n: int, gathered, reference, found):
    """Raise a :class:`GatherError` unless the n per-map estimates of every hit point add
    up to its n = ``reference_n`` estimate within :func:`gather_bound`; return the largest
    share of the bound."""
    share, i = gather_excess(gathered, reference, found)
    if share <= 1.0:
        return share
    m, ref, got = int(found[i]), reference[i], gathered[i]
    rel = np.abs(got - ref).max() / max(np.abs(ref).max(), 1e-300)
    tolerance = (2 * m + 4) * FLOAT32_ROUNDOFF
    raise GatherError(
        f"eq. (2) fails at n = {n}: at hit point {i}, with {m} photons within r, the {n} "
        f"per-map estimates add up to {np.array2string(got, precision=6)} against the "
        f"n = {reference_n} estimate {np.array2string(ref, precision=6)}: {rel:.3g} "
        f"relative, {share:.3g} times the tolerance (2 m + 4) 2^-24 = {tolerance:.3g} that "
        f"float32 rounding can explain. The maps of n = {n} do not hold the same photons, or "
        f"an estimate counts photons it should not. Stopped before writing results or "
        f"workloads.")


@dataclass
class _Setup:
    scene_name: str
    scene: object        # kept alive: the hit points' BSDF pointers point into it
    photons: int
    traced: object       # Photons, traced once into lcm streams
    si: object           # the hit points (first non-delta hits, Morton order)
    bsdf: object
    radius: float
    active: object

    @property
    def queries(self) -> int:
        return dr.width(self.si.p)


def check_maps(maps_list, photons, repeats=1):
    """The sorted map counts and their lcm (the photon streams they need); a ValueError
    naming --maps (or the repeats) when they cannot be measured."""
    given = [int(n) for n in maps_list]
    maps_list = sorted(set(given))
    if not maps_list or maps_list[0] < 1:
        raise ValueError(f"--maps must list integers >= 1, got {maps_list}")
    twice = sorted({n for n in given if given.count(n) > 1})
    if twice:
        raise ValueError(f"--maps lists {', '.join(map(str, twice))} more than once: give each "
                         f"map count once")
    if int(photons) < 1:
        raise ValueError(f"photons must be an integer >= 1, got {photons}")
    lcm = math.lcm(*maps_list)
    if lcm > photons:
        raise ValueError(f"the maps {maps_list} need lcm = {lcm} photon streams but only "
                         f"{photons} photons are emitted: raise --photons or choose n values "
                         f"with a smaller common multiple (e.g. powers of two)")
    if repeats < 1:
        raise ValueError(f"repeats must be >= 1, got {repeats}")
    return maps_list, lcm


def check_speedup(maps_list, photons, repeats=1):
    """The sorted map counts of a speedup run and their lcm (the photon streams); a
    ValueError naming the option when they cannot be measured."""
    maps_list, lcm = check_maps(maps_list, photons, repeats)
    if maps_list[0] != 1:
        raise ValueError(f"--maps must include 1: the speedup is one map's time over n maps' "
                         f"time, got {maps_list}")
    return maps_list, lcm


def _setup(scene_name, photons, streams, resolution, spp, radius_fraction, seed, data_dir,
           say, forests: int = 1, more: str = "") -> _Setup:
    """The scene, its traced photons and hit points; the memory guard counts ``forests``
    forests of the photons kept at once (one built at a time), and adds ``more`` to its
    advice."""
    scene = load_scene(scene_name, resolution=resolution, spp=spp, data_dir=data_dir)
    radius = fixed_radius(scene, None, radius_fraction)
    width, height = resolution

    def fits(stored_per_emitted=None, done=None):
        """The memory guard: before tracing, and again with the stored photons measured."""
        estimate = memory.estimate_render(photons, -1, width, height, spp, stored_per_emitted)
        kept = (forests - 1) * estimate.stored * memory.FOREST_BYTES_PER_STORED
        estimate = replace(estimate, photon_maps=int(estimate.photon_maps + kept))
        memory.check_fits(estimate, f"--photons {photons}" + (
            f" (projected from the first {done:,} photons traced)" if done else "") + (
            f" with {forests} forests kept" if forests > 1 else ""),
            option="--photons", more=more)
    fits()
    say(f"tracing {photons} photons into {streams} streams ...")
    traced = trace_photons(scene, photons, streams, seed, memory_check=fits)
    si, bsdf, _ = first_hits(scene, spp, seed)
    setup = _Setup(scene_name, scene, photons, traced, si, bsdf, radius,
                   dr.full(mi.Bool, True, dr.width(si.p)))
    say(f"{len(traced)} photons stored; {setup.queries} hit points; r = {radius:.4g}")
    return setup


def build_maps(s: _Setup, n: int, leaf_size: int = LEAF_SIZE):
    """The n maps of the experiment's photons (map j holds the streams i = j mod n)."""
    return build_photon_maps(s.traced.with_maps(s.traced.maps % n, n), leaf_size=leaf_size,
                             layout="separate")


def time_map(s: _Setup, maps, m: int, radius: float) -> float:
    """Seconds of map ``m`` alone answering every hit point's query (what hwsim models: one
    map, all queries), evaluated and synchronised. The hit points are already in Morton
    order (first_hits). Each query walks its own ball (``walk="own"``), the walk whose counts
    :func:`map_counts` records, so that the calibration fits times to the counts of the
    walk that ran."""
    return timed(lambda: radiance_estimate(maps, s.si, s.bsdf, radius, s.active,
                                           map_range=(m, m + 1), order="given",
                                           walk="own"))[1]


def map_counts(s: _Setup, maps, radius: float):
    """Traversal counts (3, n, Q) of every map and the sum of their partial estimates
    (Q, 3), untimed (a kernel with more outputs). The counts are those of each query's own
    walk (``walk="own"``): the work of one processing element per query, what hwsim
    replays, and the walk :func:`time_map` times."""
    n = maps.map_count
    counts = np.zeros((3, n, s.queries), dtype=np.uint32)
    gathered = np.zeros((s.queries, 3))
    for m in range(n):
        L, stats = radiance_estimate(maps, s.si, s.bsdf, radius, s.active,
                                     map_range=(m, m + 1), with_stats=True, order="given",
                                     walk="own")
        dr.eval(L, stats.nodes_visited, stats.photons_tested, stats.photons_found)
        counts[:, m] = [stats.nodes_visited.numpy(), stats.photons_tested.numpy(),
                        stats.photons_found.numpy()]
        gathered += np.array(L, dtype=np.float64).reshape(3, -1).T
    return counts, gathered


def map_workloads(n: int, maps, times, counts) -> MapWorkloads:
    """The workload of n maps: their counts, photons, bytes and measured times."""
    return MapWorkloads(n=n, nodes_visited=counts[0], photons_tested=counts[1],
                        photons_found=counts[2],
                        map_photons=maps.forest.photon_count.astype(np.int64),
                        map_bytes=maps.map_bytes.astype(np.int64), map_seconds=times,
                        bytes_per_node=NODE_BYTES, bytes_per_photon=record_bytes())


def _measure(s: _Setup, n: int, repeats: int):
    """Time every map of n alone ``repeats`` times; record its traversal counts and its
    partial estimates. Returns (maps, times (n, repeats), counts (3, n, Q), gathered (Q, 3))."""
    maps = build_maps(s, n)
    time_map(s, maps, 0, s.radius)   # warm-up: compile (one kernel for every map, opaque range)
    times = np.zeros((n, repeats))
    for rep in range(repeats):
        for m in range(n):
            times[m, rep] = time_map(s, maps, m, s.radius)
    counts, gathered = map_counts(s, maps, s.radius)
    return maps, times, counts, gathered


def _row(n, maps, times, counts, max_rel_error, rounding_share) -> dict:
    sizes = maps.map_bytes
    return {
        "n": n, "per_map_seconds": float(np.median(times)),
        "per_map_seconds_min": float(times.min()), "per_map_seconds_max": float(times.max()),
        "total_seconds": float(np.median(times, axis=1).sum()),
        "mean_nodes_visited": float(counts[0].mean()),
        "mean_photons_tested": float(counts[1].mean()),
        "mean_photons_found": float(counts[2].mean()),
        "photons_per_map": float(maps.forest.photon_count.mean()),
        "tree_depth": int(max(maps.forest.depth(m) for m in range(n))),
        "map_bytes_mean": float(sizes.mean()),
        "gather_max_rel_error": max_rel_error,
        "gather_rounding_share": rounding_share,
    }


def run_speedup(scene_name: str, maps_list: Sequence[int], out_dir, photons: int = 100_000,
                resolution=(480, 480), spp: int = 1, repeats: int = 3,
                radius_fraction: float = 0.05, seed: int = 0, data_dir: Optional[str] = None,
                save_workload_files: bool = True, progress=print) -> dict:
    """Run the experiment; write ``speedup.csv``, ``speedup.json``, ``speedup.png`` and the
    workloads (``workloads/n{n}.npz`` + ``workloads/meta.json``) into ``out_dir``."""
    maps_list, lcm = check_speedup(maps_list, photons, repeats)
    say = progress or (lambda *a: None)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    s = _setup(scene_name, photons, lcm, resolution, spp, radius_fraction, seed, data_dir, say)

    code = code_version()
    rows, loads, reference = [], {}, None
    for n in maps_list:
        maps, times, counts, gathered = _measure(s, n, repeats)
        if reference is None:
            reference = gathered
            if counts[2].any() and not np.any(reference):
                raise GatherError(
                    f"the n = {n} estimate is 0 at every hit point although its queries "
                    f"found {int(counts[2].sum())} photons: the hit points' BSDFs or the "
                    f"photons' powers are not what they should be. Stopped before writing "
                    f"results or workloads.")
        scale = np.maximum(np.abs(reference).max(), 1e-12)
        share = _check_gather(n, maps_list[0], gathered, reference, counts[2].sum(axis=0))
        row = _row(n, maps, times, counts, float(np.abs(gathered - reference).max() / scale),
                   share)
        rows.append(row)
        say(f"n = {n:4d}: one map {row['per_map_seconds'] * 1e3:8.1f} ms, all {n} maps "
            f"{row['total_seconds']:6.2f} s; per query: {row['mean_nodes_visited']:.1f} nodes, "
            f"{row['mean_photons_tested']:.1f} tested, {row['mean_photons_found']:.1f} found")
        loads[n] = map_workloads(n, maps, times, counts)
        del maps
    _add_ratios(rows)
    doubts = timing_doubts(rows)
    if doubts:
        log.warning("speedup of %s: %s", scene_name, "; ".join(doubts))
    result = {"scene": scene_name, "photons_emitted": photons,
              "photons_stored": len(s.traced), "resolution": list(resolution), "spp": spp,
              "queries": int(s.queries), "radius": s.radius, "repeats": repeats,
              "radius_fraction": radius_fraction, "seed": seed, "streams": lcm, "code": code, "rows": rows, "timing_doubts": doubts,
              "scene_sha256": scene_digest(scene_name, data_dir)}
    _write(out, result, rows)
    if save_workload_files:
        save_workloads(out / "workloads", loads, scene=scene_name, radius=s.radius,
                       photons_emitted=photons, photons_stored=len(s.traced),
                       leaf_size=LEAF_SIZE, radius_fraction=radius_fraction,
                       threads=dr.thread_count(), lanes=simd_lanes(),
                       l1_bytes=l1_data_bytes())
    return result


def _add_ratios(rows):
    base = rows[0]
    for row in rows:
        row["speedup"] = base["per_map_seconds"] / row["per_map_seconds"]
        row["ideal"] = row["n"] / base["n"]
        row["node_ratio"] = base["mean_nodes_visited"] / row["mean_nodes_visited"]
        row["tested_ratio"] = base["mean_photons_tested"] / row["mean_photons_tested"]


#: How far a speedup may pass n (the smaller maps' better use of the caches), or fall from
#: the n before, before the timings are doubted: the paper-size and 1024-map runs of this
#: machine stayed below n and fell by at most 2% (1024 maps of the Buddha).
DOUBT_MARGIN = 0.10


def timing_doubts(rows) -> list:
    """Sentences on speedups that the maps alone do not explain: above n by more than
    :data:`DOUBT_MARGIN`, or falling by more than it as n grows. Both come from timings
    disturbed by other work on the machine (a notebook run beside a build measured 10.0x
    at n = 8, then 5.4x at n = 16); the traversal counts do not depend on timing."""
    doubts = []
    for before, row in zip([None] + rows[:-1], rows):
        if row["speedup"] > row["ideal"] * (1 + DOUBT_MARGIN):
            doubts.append(f"the speedup at n = {row['n']} is {row['speedup']:.2f}, above "
                          f"n / {rows[0]['n']} = {row['ideal']:g}")
        if before is not None and row["speedup"] < before["speedup"] * (1 - DOUBT_MARGIN):
            doubts.append(f"the speedup falls from {before['speedup']:.2f} at n = "
                          f"{before['n']} to {row['speedup']:.2f} at n = {row['n']}")
    if doubts:
        doubts.append("the timings look disturbed (other work on the machine while they "
                      "ran?): the traversal counts hold, the times do not; rerun on an idle "
                      "machine, or with more --repeats")
    return doubts


def _write(out: Path, result: dict, rows: list):
    with open(out / "speedup.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    (out / "speedup.json").write_text(json.dumps(result, indent=2) + "\n")
    _plot(rows, out / "speedup.png", result["scene"])


def plot_speedup(speedup_json, path=None):
    """Redraw ``speedup.png`` from a saved ``speedup.json``."""
    result = json.loads(Path(speedup_json).read_text())
    path = Path(speedup_json).with_suffix(".png") if path is None else path
    _plot(result["rows"], path, result["scene"])
    return path


def _plot(rows, path, title):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    n = [r["n"] for r in rows]
    fig, ax = plt.subplots(figsize=(5, 4))
    ax.plot(n, [r["ideal"] for r in rows], "k--", label="ideal (n)")
    ax.plot(n, [r["speedup"] for r in rows], "o-", label="measured: time of one map")
    ax.plot(n, [r["tested_ratio"] for r in rows], "^:",
            label="photons tested per query: n = 1 over n")
    ax.plot(n, [r["node_ratio"] for r in rows], "s:",
            label="nodes visited per query: n = 1 over n")
    ax.set_xscale("log", base=2)
    ax.set_yscale("log", base=2)
    ax.set_xticks(n)
    ax.set_xticklabels([str(v) for v in n])
    ax.set_xlabel("number of photon maps n")
    ax.set_ylabel("speedup of density estimation")
    ax.set_title(f"{title}: per-map speedup (figures 5-6)", fontsize=10)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def format_speedup(result) -> str:
    lines = [f"{result['scene']}: {result['photons_emitted']} photons emitted, "
             f"{result['photons_stored']} stored, {result['queries']} hit points, "
             f"r = {result['radius']:.4g}",
             f"{'n':>4} {'one map ms':>10} {'speedup':>8} {'all maps s':>10} {'nodes':>7} "
             f"{'tested':>7} {'found':>7} {'depth':>5} {'gather err':>10}"]
    for r in result["rows"]:
        lines.append(f"{r['n']:4d} {r['per_map_seconds'] * 1e3:10.1f} {r['speedup']:8.2f} "
                     f"{r['total_seconds']:10.2f} {r['mean_nodes_visited']:7.1f} "
                     f"{r['mean_photons_tested']:7.1f} {r['mean_photons_found']:7.1f} "
                     f"{r['tree_depth']:5d} {r['gather_max_rel_error']:10.1e}")
    if result.get("timing_doubts"):
        lines.append("note: " + "; ".join(result["timing_doubts"]))
    return "\n".join(lines)
