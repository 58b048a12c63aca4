"""``partpm bench``: our kd-tree and photon tracer against the baselines a user could pick.

Every comparison is timed in one run, on the same data, as medians over ``repeats``; each
prints a ratio against its named baseline and its target:

- fixed-radius power sums at every hit point, one map, vs ``scipy.spatial.cKDTree.
  query_ball_point(return_length=True, workers=-1)``, which only COUNTS (target: 3x faster);
- the kNN estimate's query (k = 50, power sums) vs ``pykdtree`` ``query(k=50)`` on all cores
  (target: no slower);
- the kd-tree build of the stored photons and of 10^6 photons vs ``cKDTree(balanced_tree=
  True)`` (target: no slower);
- all 32 maps answered one after another vs one map with all photons (target: at most 2x,
  i.e. per-map speedup >= 16), and the same ratio for one cKDTree per map (count only);
- photon tracing, ray segments per second, vs Mitsuba's ``path`` (target: >= 0.8x);
- bytes per stored photon including its tree, for 10^6 and 10^7 photons (target: <= 32);
- photons traced per second for every kind of emitter Mitsuba ships, against an area light
  (target: none more than 5x slower).
"""
from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np

from ..eyepath import first_hits
from ..kdtree import build_forest, knn_query, radius_query
from ..photonmap import build_photon_maps, fixed_radius, map_bytes
from ..scenes import load_scene
from ..timing import median_time, sync
from ..trace import trace_photons

__all__ = ["run_bench", "format_bench"]


@dataclass
class _Bench:
    """The shared workload of one run, and the rows measured on it."""

    scene: object
    radius: float
    traced: object
    points: np.ndarray       # stored photon positions (N, 3)
    maps: object             # one map of all stored photons
    p: object                # hit points (Dr.Jit)
    queries: np.ndarray      # hit points (Q, 3)
    repeats: int
    say: object
    rows: list = field(default_factory=list)

    def power_sums(self, maps, map_range=None):
        return radius_query(maps.forest, self.p, self.radius,
                            lambda i, d2, a, s: maps.photon_power(i, a), mi.Spectrum,
                            maps=map_range)

    def row(self, name, ours, base, base_name, target, ratio, meaning, at_least=True,
            unit="s"):
        ok = ratio >= target if at_least else ratio <= target
        self.rows.append({"benchmark": name, "ours": ours, "baseline": base,
                          "baseline_name": base_name, "ratio": ratio, "target": target,
                          "target_is": "at least" if at_least else "at most",
                          "ratio_meaning": meaning, "met": bool(ok), "unit": unit})
        self.say(f"  {name}: ours {ours:.4g} {unit}, {base_name} {base:.4g} {unit}, {meaning} "
                 f"{ratio:.2f} (target {'>=' if at_least else '<='} {target}) "
                 f"{'met' if ok else 'NOT met'}")

    def faster(self, name, ours, base, base_name, target):
        self.row(name, ours, base, base_name, target, base / ours, "baseline time / ours")


def _setup(scene_name, photons, resolution, repeats, say) -> _Bench:
    scene = load_scene(scene_name, resolution=resolution, spp=1)
    traced = trace_photons(scene, photons, 1, 0)
    si = first_hits(scene, 1, 0)[0]
    b = _Bench(scene=scene, radius=fixed_radius(scene, None, 0.05), traced=traced,
               points=np.ascontiguousarray(traced.position, dtype=np.float32),
               maps=build_photon_maps(traced), p=si.p,
               queries=np.ascontiguousarray(np.array(si.p, dtype=np.float32).T),
               repeats=repeats, say=say)
    say(f"{scene_name}: {photons} photons emitted, {len(b.points)} stored, "
        f"{b.queries.shape[0]} hit points, r = {b.radius:.4g}")
    return b


def _bench_queries(b: _Bench):
    """1. Fixed-radius power sums, one map; 2. kNN, k = 50."""
    from scipy.spatial import cKDTree
    ours = median_time(lambda: b.power_sums(b.maps), b.repeats)
    ck = cKDTree(b.points, balanced_tree=True)
    base = median_time(lambda: ck.query_ball_point(b.queries, b.radius, return_length=True,
                                                   workers=-1), b.repeats, jit=False)
    b.faster("radius sums, n=1", ours, base, "cKDTree count only", 3.0)
    ours = median_time(lambda: knn_query(b.maps.forest, b.p, 50,
                                         lambda i, d2, a, s: b.maps.photon_power(i, a),
                                         mi.Spectrum).total, b.repeats)
    try:
        from pykdtree.kdtree import KDTree
        kd = KDTree(b.points)
        base = median_time(lambda: kd.query(b.queries, k=50), b.repeats, jit=False)
        b.faster("kNN k=50, n=1", ours, base, "pykdtree query(k=50)", 1.0)
    except ImportError:
        base = median_time(lambda: ck.query(b.queries, k=50, workers=-1), b.repeats, jit=False)
        b.faster("kNN k=50, n=1", ours, base, "cKDTree query(k=50) (pykdtree not installed)",
                 1.0)


def _bench_builds(b: _Bench, big: int):
    """3. Builds of the stored photons and of ``big`` photons."""
    from scipy.spatial import cKDTree
    ours = median_time(lambda: build_forest(b.points), b.repeats, jit=False)
    base = median_time(lambda: cKDTree(b.points, balanced_tree=True), b.repeats, jit=False)
    b.faster(f"build, {len(b.points)} photons", ours, base, "cKDTree(balanced_tree=True)", 1.0)
    more = trace_photons(b.scene, max(1, big // 2), 1, 1)
    points = np.ascontiguousarray(np.concatenate([more.position, b.points])[:big],
                                  dtype=np.float32)
    few = max(1, b.repeats // 2)
    ours = median_time(lambda: build_forest(points), few, jit=False)
    base = median_time(lambda: cKDTree(points, balanced_tree=True), few, jit=False)
    b.faster(f"build, {len(points)} photons", ours, base, "cKDTree(balanced_tree=True)", 1.0)


def _bench_maps_in_turn(b: _Bench, n: int = 32):
    """4. All n maps one after another vs one map with all photons (and the same for one
    cKDTree per map, count only)."""
    from scipy.spatial import cKDTree
    index = np.arange(len(b.points))
    split = build_photon_maps(b.traced.with_maps(index % n, n))
    one = median_time(lambda: b.power_sums(b.maps), b.repeats)

    def all_maps():
        total = 0.0
        for m in range(n):
            t0 = time.perf_counter()
            sync(b.power_sums(split, (m, m + 1)))
            total += time.perf_counter() - t0
        return total
    all_maps()
    few = max(1, b.repeats // 2)
    ours = float(np.median([all_maps() for _ in range(few)]))
    b.row(f"{n} maps in turn / 1 map", ours, one, "one map, all photons", 2.0, ours / one,
          f"time of {n} maps / 1 map", at_least=False)
    trees = [cKDTree(b.points[index % n == m], balanced_tree=True) for m in range(n)]
    ck_n = median_time(lambda: [t.query_ball_point(b.queries, b.radius, return_length=True,
                                                   workers=-1) for t in trees], few, jit=False)
    whole = cKDTree(b.points, balanced_tree=True)
    ck_1 = median_time(lambda: whole.query_ball_point(b.queries, b.radius, return_length=True,
                                                      workers=-1), b.repeats, jit=False)
    b.rows[-1]["ckdtree_ratio"] = ck_n / ck_1
    b.say(f"    (one cKDTree per map, count only: {n} maps / 1 map = {ck_n / ck_1:.2f})")


def _path_segments_per_sample(scene, spp, seed=0):
    """Ray segments Mitsuba's ``path`` traces per sample at max_depth = 2: the camera ray,
    then, where it hits, the bounce ray and (on surfaces with a smooth lobe) a shadow ray."""
    si, _, _ = first_hits(scene, spp, seed, max_depth=1)
    cam = scene.sensors()[0]
    size = cam.film().crop_size()
    samples = int(size[0]) * int(size[1]) * spp
    # Camera rays that hit anything at all (smooth or delta): count them separately.
    sampler = cam.sampler().clone()
    sampler.seed(seed, samples)
    uv = mi.Point2f(sampler.next_1d(), sampler.next_1d())
    ray, _ = cam.sample_ray(0.0, 0.5, uv, mi.Point2f(0.5, 0.5))
    valid = np.count_nonzero(scene.ray_intersect(ray).is_valid().numpy()) / samples
    smooth = dr.width(si.p) / samples
    return 1.0 + valid + smooth


def _bench_tracing(b: _Bench, scene_name, resolution, count, path_spp):
    """5. Photon tracing vs Mitsuba's path tracer, ray segments per second."""
    t_trace = float("inf")
    for seed in (2, 3):
        t0 = time.perf_counter()
        traced = trace_photons(b.scene, count, 1, seed)
        t_trace = min(t_trace, time.perf_counter() - t0)
    ours_rate = traced.segments / t_trace
    path = mi.load_dict({"type": "path", "max_depth": 2})
    path_scene = load_scene(scene_name, resolution=resolution, spp=path_spp)
    t_path = median_time(lambda: mi.render(path_scene, integrator=path, spp=path_spp),
                         max(1, b.repeats // 2))
    samples = resolution[0] * resolution[1] * path_spp
    path_rate = samples * _path_segments_per_sample(path_scene, path_spp) / t_path
    b.row(f"tracing, {count} photons", ours_rate / 1e6, path_rate / 1e6,
          "Mitsuba path (max_depth 2)", 0.8, ours_rate / path_rate, "our rate / baseline rate",
          unit="M segments/s")


def _bench_emitters(b: _Bench, count: int):
    """7. Photons emitted and traced per second, per kind of emitter (the floor of
    :mod:`mi_partpm.scenes.emitters`), against the rectangular area light."""
    import tempfile
    from ..scenes.emitters import EMITTER_KINDS, emitter_scene, write_textures
    rates = {}
    with tempfile.TemporaryDirectory() as folder:
        textures = write_textures(folder)
        for kind in EMITTER_KINDS:
            scene = emitter_scene(kind, textures)
            seconds = median_time(lambda: trace_photons(scene, count, 1, 0), b.repeats,
                                  jit=False)
            rates[kind] = count / seconds
    area = rates["area_rectangle"]
    for kind, rate in rates.items():
        if kind != "area_rectangle":
            b.row(f"emitting, {kind}", rate / 1e6, area / 1e6, "area light (rectangle)", 0.2,
                  rate / area, "photons/s over the area light's", unit="M photons/s")


def run_bench(out_json=None, scene_name: str = "cornell_box", photons: int = 100_000,
              resolution=(480, 480), repeats: int = 5, big: int = 1_000_000,
              huge: int = 10_000_000, trace_photons_count: int = 1_000_000,
              path_spp: int = 16, progress=print) -> dict:
    """Run every benchmark; return (and with ``out_json`` write) the table."""
    b = _setup(scene_name, photons, resolution, repeats, progress or (lambda *a: None))
    _bench_queries(b)
    _bench_builds(b, big)
    _bench_maps_in_turn(b)
    _bench_tracing(b, scene_name, resolution, trace_photons_count, path_spp)
    _bench_emitters(b, trace_photons_count)
    # 6. Memory per stored photon, record and tree.
    for count in (big, huge):
        per_photon = float(map_bytes([count])[0]) / count
        b.row(f"memory, {count} photons", per_photon, 20.0, "Jensen's photon record (no tree)",
              32.0, per_photon, "bytes per photon", at_least=False, unit="bytes/photon")
    result = {"scene": scene_name, "photons_emitted": photons,
              "photons_stored": int(len(b.points)), "queries": int(b.queries.shape[0]),
              "radius": b.radius, "repeats": repeats, "threads": int(dr.thread_count()),
              "rows": b.rows}
    if out_json:
        Path(out_json).parent.mkdir(parents=True, exist_ok=True)
        Path(out_json).write_text(json.dumps(result, indent=2) + "\n")
    return result


def format_bench(result) -> str:
    lines = [f"{result['scene']}: {result['photons_stored']} photons stored, "
             f"{result['queries']} queries, r = {result['radius']:.4g}, "
             f"{result['threads']} threads, medians of {result['repeats']}",
             f"{'benchmark':30} {'ours':>9} {'baseline':>9} {'ratio':>6} {'target':>8}  "
             f"met  (ratio = ...; baseline)"]
    for r in result["rows"]:
        target = f"{'>=' if r['target_is'] == 'at least' else '<='} {r['target']:g}"
        lines.append(f"{r['benchmark']:30} {r['ours']:9.4g} {r['baseline']:9.4g} "
                     f"{r['ratio']:6.2f} {target:>8}  {'yes' if r['met'] else 'NO ':3}"
                     f"  ({r['ratio_meaning']}; {r['baseline_name']}, {r['unit']})")
    return "\n".join(lines)
