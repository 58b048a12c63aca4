"""The paper's speedup experiment (figures 5 and 6): per-map density-estimation time vs n.

For each n, the photons are split into n maps and ONE map answers the fixed-radius queries of
every hit point of the image; its time (median over the maps and the repeats) against n = 1 is
the speedup of density estimation that n processors with one map each would see. The
traversal counts per query (nodes visited, photons tested, photons found) explain it, and are
saved per map as the workload that ``hwsim`` replays (format: ``hwsim/WORKLOAD.md``).

The same photons serve every n: they are traced once into L = lcm(n values) streams, and map j
of n holds the streams i with i mod n = j, so every map still holds its own N/n emissions
(DESIGN.md) while the total work is identical across n; the per-map estimates of each n must
add up to the n = 1 estimate (eq. 2), which the run checks.
"""
from __future__ import annotations

import csv
import json
import logging
import math
import time
from pathlib import Path
from typing import Optional, Sequence

import drjit as dr
import mitsuba as mi
import numpy as np

from .estimate import radiance_estimate
from .eyepath import first_estimate_hits
from .kdtree import LEAF_SIZE
from .photonmap import PhotonMaps, build_photon_maps, fixed_radius
from .photons import trace_photons
from .scenes import load_scene

__all__ = ["run_speedup", "map_bytes", "format_speedup", "plot_speedup", "WORKLOAD_VERSION"]

log = logging.getLogger("mi_partpm")

#: Version of the workload file format (hwsim/WORKLOAD.md).
WORKLOAD_VERSION = 1


def map_bytes(maps: PhotonMaps) -> np.ndarray:
    """Bytes of each map: its photon records plus its tree (split nodes, leaf table)."""
    forest = maps.forest
    per_photon = maps.nbytes_per_photon
    internal = forest.internal_count.astype(np.int64)
    leaves = internal + 1
    return (forest.photon_count.astype(np.int64) * per_photon + internal * 8
            + (leaves + 1) * 4)


def _timed(fn):
    t0 = time.perf_counter()
    out = fn()
    dr.eval(out)
    dr.sync_thread()
    return out, time.perf_counter() - t0


def run_speedup(scene_name: str, maps_list: Sequence[int], out_dir, photons: int = 100_000,
                resolution=(480, 480), spp: int = 1, repeats: int = 3,
                radius_fraction: float = 0.05, seed: int = 0, data_dir: Optional[str] = None,
                save_workloads: bool = True, progress=print) -> dict:
    """Run the experiment; write ``speedup.csv``, ``speedup.json``, ``speedup.png`` and the
    workloads (``workloads/n{n}.npz`` + ``workloads/meta.json``) into ``out_dir``."""
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
    say = progress or (lambda *a: None)
    out = Path(out_dir)
    (out / "workloads").mkdir(parents=True, exist_ok=True)

    scene = load_scene(scene_name, resolution=resolution, spp=spp, data_dir=data_dir)
    radius = fixed_radius(scene, None, radius_fraction)
    say(f"tracing {photons} photons into {lcm} streams ...")
    traced = trace_photons(scene, photons, lcm, seed)
    si, bsdf, _ = first_estimate_hits(scene, spp, seed)
    queries = dr.width(si.p)
    say(f"{len(traced)} photons stored; {queries} hit points; r = {radius:.4g}")
    active = dr.full(mi.Bool, True, queries)

    rows, reference = [], None
    for n in maps_list:
        maps = build_photon_maps(traced.with_maps(traced.map_id % n, n))
        dr.eval(maps.direction32, maps.power)
        # Warm up: compile the kernels (one for every map, the range is opaque).
        _timed(lambda: radiance_estimate(maps, si, bsdf, radius, active, map_range=(0, 1)))
        times = np.zeros((n, repeats))
        for rep in range(repeats):
            for m in range(n):
                _, times[m, rep] = _timed(lambda: radiance_estimate(
                    maps, si, bsdf, radius, active, map_range=(m, m + 1)))
        # Traversal counts and the partial estimates (untimed: a kernel with more outputs).
        counts = np.zeros((3, n, queries), dtype=np.uint32)
        gathered = np.zeros((queries, 3))
        for m in range(n):
            L, stats = radiance_estimate(maps, si, bsdf, radius, active, map_range=(m, m + 1),
                                         with_stats=True)
            dr.eval(L, stats.nodes_visited, stats.photons_tested, stats.photons_found)
            counts[0, m] = stats.nodes_visited.numpy()
            counts[1, m] = stats.photons_tested.numpy()
            counts[2, m] = stats.photons_found.numpy()
            gathered += np.array(L, dtype=np.float64).reshape(3, -1).T
        if reference is None:
            reference = gathered
        scale = np.maximum(np.abs(reference).max(), 1e-12)
        gather_error = float(np.abs(gathered - reference).max() / scale)
        sizes = map_bytes(maps)
        per_map = float(np.median(times))
        row = {
            "n": n, "per_map_seconds": per_map,
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
        rows.append(row)
        say(f"n = {n:4d}: one map {per_map * 1e3:8.1f} ms, all {n} maps "
            f"{row['total_seconds']:6.2f} s; per query: {row['mean_nodes_visited']:.1f} nodes, "
            f"{row['mean_photons_tested']:.1f} tested, {row['mean_photons_found']:.1f} found")
        if save_workloads:
            np.savez_compressed(
                out / "workloads" / f"n{n}.npz", nodes_visited=counts[0],
                photons_tested=counts[1], photons_found=counts[2],
                map_photons=maps.forest.photon_count.astype(np.int64), map_bytes=sizes,
                map_seconds=times, version=np.int64(WORKLOAD_VERSION))
        del maps
    base = rows[0]
    for row in rows:
        row["speedup"] = base["per_map_seconds"] / row["per_map_seconds"]
        row["ideal"] = row["n"] / base["n"]
        row["node_ratio"] = base["mean_nodes_visited"] / row["mean_nodes_visited"]
        row["tested_ratio"] = base["mean_photons_tested"] / row["mean_photons_tested"]

    result = {"scene": scene_name, "photons_emitted": photons, "photons_stored": len(traced),
              "resolution": list(resolution), "spp": spp, "queries": int(queries),
              "radius": radius, "repeats": repeats, "streams": lcm, "rows": rows}
    meta = {"version": WORKLOAD_VERSION, "scene": scene_name, "queries": int(queries),
            "radius": radius, "photons_emitted": photons, "photons_stored": len(traced),
            "leaf_size": LEAF_SIZE,
            "bytes_per_photon": int(PhotonMaps.bytes_per_photon()),
            "bytes_per_node": 8, "maps": maps_list,
            "files": {str(n): f"n{n}.npz" for n in maps_list}}
    if save_workloads:
        (out / "workloads" / "meta.json").write_text(json.dumps(meta, indent=2) + "\n")
    with open(out / "speedup.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    (out / "speedup.json").write_text(json.dumps(result, indent=2) + "\n")
    _plot(rows, out / "speedup.png", scene_name)
    return result


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
