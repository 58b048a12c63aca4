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
the n = 1 estimate (eq. 2), which the run checks.

:func:`run_speedup` is three phases: :func:`_setup` (scene, photons, hit points),
:func:`_measure` per n (times, counts, the gather's error) and the report (CSV, JSON, plot,
workloads).
"""
from __future__ import annotations

import csv
import json
import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Sequence

import drjit as dr
import mitsuba as mi
import numpy as np

from hwsim.workload import MapWorkloads, save_workloads
from ..estimate import radiance_estimate
from ..eyepath import first_hits
from ..kdtree import LEAF_SIZE, NODE_BYTES
from ..photonmap import build_photon_maps, fixed_radius, record_bytes
from ..scenes import load_scene
from ..timing import timed
from ..trace import trace_photons

__all__ = ["run_speedup", "format_speedup", "plot_speedup"]

log = logging.getLogger("mi_partpm")


@dataclass
class _Setup:
    scene_name: str
    photons: int
    traced: object       # Photons, traced once into lcm streams
    si: object           # the hit points (first non-delta hits, Morton order)
    bsdf: object
    radius: float
    active: object

    @property
    def queries(self) -> int:
        return dr.width(self.si.p)


def _check(maps_list, photons, repeats):
    maps_list = sorted(set(int(n) for n in maps_list))
    if not maps_list or maps_list[0] < 1:
        raise ValueError(f"--maps must list integers >= 1, got {maps_list}")
    lcm = math.lcm(*maps_list)
    if lcm > photons:
        raise ValueError(f"the maps {maps_list} need lcm = {lcm} photon streams but only "
                         f"{photons} photons are emitted: raise --photons or choose n values "
                         f"with a smaller common multiple (e.g. powers of two)")
    if repeats < 1:
        raise ValueError(f"repeats must be >= 1, got {repeats}")
    return maps_list, lcm


def _setup(scene_name, photons, streams, resolution, spp, radius_fraction, seed, data_dir,
           say) -> _Setup:
    scene = load_scene(scene_name, resolution=resolution, spp=spp, data_dir=data_dir)
    radius = fixed_radius(scene, None, radius_fraction)
    say(f"tracing {photons} photons into {streams} streams ...")
    traced = trace_photons(scene, photons, streams, seed)
    si, bsdf, _ = first_hits(scene, spp, seed)
    setup = _Setup(scene_name, photons, traced, si, bsdf, radius,
                   dr.full(mi.Bool, True, dr.width(si.p)))
    say(f"{len(traced)} photons stored; {setup.queries} hit points; r = {radius:.4g}")
    return setup


def _measure(s: _Setup, n: int, repeats: int):
    """Time every map of n alone ``repeats`` times; record its traversal counts and its
    partial estimates. Returns (maps, times (n, repeats), counts (3, n, Q), gathered (Q, 3))."""
    maps = build_photon_maps(s.traced.with_maps(s.traced.maps % n, n))

    def one_map(m):
        # The hit points are already in Morton order (first_hits).
        return radiance_estimate(maps, s.si, s.bsdf, s.radius, s.active, map_range=(m, m + 1),
                                 order="given")
    timed(lambda: one_map(0))     # warm-up: compile (one kernel for every map, opaque range)
    times = np.zeros((n, repeats))
    for rep in range(repeats):
        for m in range(n):
            times[m, rep] = timed(lambda: one_map(m))[1]
    # Traversal counts and the partial estimates (untimed: a kernel with more outputs).
    counts = np.zeros((3, n, s.queries), dtype=np.uint32)
    gathered = np.zeros((s.queries, 3))
    for m in range(n):
        L, stats = radiance_estimate(maps, s.si, s.bsdf, s.radius, s.active,
                                     map_range=(m, m + 1), with_stats=True, order="given")
        dr.eval(L, stats.nodes_visited, stats.photons_tested, stats.photons_found)
        counts[:, m] = [stats.nodes_visited.numpy(), stats.photons_tested.numpy(),
                        stats.photons_found.numpy()]
        gathered += np.array(L, dtype=np.float64).reshape(3, -1).T
    return maps, times, counts, gathered


def _row(n, maps, times, counts, gather_error) -> dict:
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
        "gather_max_rel_error": gather_error,
    }


def run_speedup(scene_name: str, maps_list: Sequence[int], out_dir, photons: int = 100_000,
                resolution=(480, 480), spp: int = 1, repeats: int = 3,
                radius_fraction: float = 0.05, seed: int = 0, data_dir: Optional[str] = None,
                save_workload_files: bool = True, progress=print) -> dict:
    """Run the experiment; write ``speedup.csv``, ``speedup.json``, ``speedup.png`` and the
    workloads (``workloads/n{n}.npz`` + ``workloads/meta.json``) into ``out_dir``."""
    maps_list, lcm = _check(maps_list, photons, repeats)
    say = progress or (lambda *a: None)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    s = _setup(scene_name, photons, lcm, resolution, spp, radius_fraction, seed, data_dir, say)

    rows, loads, reference = [], {}, None
    for n in maps_list:
        maps, times, counts, gathered = _measure(s, n, repeats)
        reference = gathered if reference is None else reference
        scale = np.maximum(np.abs(reference).max(), 1e-12)
        row = _row(n, maps, times, counts, float(np.abs(gathered - reference).max() / scale))
        rows.append(row)
        say(f"n = {n:4d}: one map {row['per_map_seconds'] * 1e3:8.1f} ms, all {n} maps "
            f"{row['total_seconds']:6.2f} s; per query: {row['mean_nodes_visited']:.1f} nodes, "
            f"{row['mean_photons_tested']:.1f} tested, {row['mean_photons_found']:.1f} found")
        loads[n] = MapWorkloads(n=n, nodes_visited=counts[0], photons_tested=counts[1],
                                photons_found=counts[2],
                                map_photons=maps.forest.photon_count.astype(np.int64),
                                map_bytes=maps.map_bytes.astype(np.int64), map_seconds=times,
                                bytes_per_node=NODE_BYTES, bytes_per_photon=record_bytes())
        del maps
    _add_ratios(rows)
    result = {"scene": scene_name, "photons_emitted": photons,
              "photons_stored": len(s.traced), "resolution": list(resolution), "spp": spp,
              "queries": int(s.queries), "radius": s.radius, "repeats": repeats,
              "streams": lcm, "rows": rows}
    _write(out, result, rows)
    if save_workload_files:
        save_workloads(out / "workloads", loads, scene=scene_name, radius=s.radius,
                       photons_emitted=photons, photons_stored=len(s.traced),
                       leaf_size=LEAF_SIZE)
    return result


def _add_ratios(rows):
    base = rows[0]
    for row in rows:
        row["speedup"] = base["per_map_seconds"] / row["per_map_seconds"]
        row["ideal"] = row["n"] / base["n"]
        row["node_ratio"] = base["mean_nodes_visited"] / row["mean_nodes_visited"]
        row["tested_ratio"] = base["mean_photons_tested"] / row["mean_photons_tested"]


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
    return "\n".join(lines)
