"""``partpm bench``: what users run, against the baselines they could pick, in one run.

Every comparison is timed in one run, on the same data, in ``repeats`` rounds that run ours and
the baseline one after the other (:func:`~mi_partpm.timing.paired_times`), so that both see
the same load on the machine. Each row prints the medians' ratio against its named baseline,
the target it is held to, and the range of the per-round ratios (how far the machine's load
moved the comparison within the run):

- fixed-radius power sums (the bare :func:`~mi_partpm.kdtree.radius_query`) vs
  ``scipy.spatial.cKDTree.query_ball_point(return_length=True, workers=-1)``, which only
  COUNTS (target 3x faster), on queries in random order and in Morton order, on two
  workloads: the Cornell box's photons and eye-ray hits, and a room nobody tuned on
  (:func:`room_workload`: photons on the walls, a sphere and a slab, falling off from the
  ceiling; queries in random order on the same surfaces);
- the kNN query, k = 50, power sums vs ``pykdtree`` ``query(k=50)`` (target: no slower), on
  the same four inputs;
- the integrator's own estimate (BSDF, side test, photon count) at one pass's visible points,
  with the photons in 1 map and in 32 maps: as the integrator builds them, sharing split
  planes (target: 32 maps at most 2x), and, for reference, one separate tree per map walked
  in turn (the paper's processing elements, whose workloads hwsim replays; no target);
- the kd-tree build vs ``cKDTree(balanced_tree=True)`` at 3 x 10^5, 10^6 and 3 x 10^7
  photons (targets 1x, 1x, 1.5x);
- photon tracing vs Mitsuba's ``path`` (max_depth 2), ray segments per second, both counted:
  ours by the tracer, path's by replaying its decisions (:func:`path_segments`) (target 0.8x),
  and beside them the rate of Mitsuba's closest-hit intersection alone on as many incoherent
  rays, the bound of a tracer that intersects every segment, and what sorting the rays would
  buy (the same rays sorted and traced as coherent, and the cost of sorting them and moving
  a lane's state);
- photons traced per second for every kind of emitter, against an area light (none more than
  5x slower);
- memory per stored photon, MEASURED in a fresh process rendering 10^6 and 10^7 photons: the
  process's peak resident memory and Dr.Jit's own peak (:mod:`.memprobe`) (target 80 bytes).
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np

from .provenance import code_version, git_commit, machine
from ..estimate import gather_flux
from ..eyepath import eye_paths, first_hits
from ..kdtree import LAYOUTS, build_forest, knn_query, morton_codes, morton_order, radius_query
from ..photonmap import build_photon_maps, fixed_radius
from ..scenes import load_scene
from ..timing import median_time, paired_times, sync
from ..trace import trace_photons

__all__ = ["run_bench", "format_bench", "room_workload", "path_segments", "SIZES"]

#: Sizes of a full run and of ``--smoke`` (tiny: checks that everything runs).
SIZES = {
    "full": dict(photons=100_000, resolution=(480, 480), repeats=5, room=200_000,
                 builds=(300_000, 1_000_000, 30_000_000), trace=1_000_000, path_spp=16,
                 emitter_photons=1_000_000, memory=(1_000_000, 10_000_000)),
    "smoke": dict(photons=5_000, resolution=(32, 32), repeats=1, room=5_000,
                  builds=(5_000, 20_000), trace=20_000, path_spp=2, emitter_photons=20_000,
                  memory=(20_000,)),
}


def room_workload(points: int, queries: int, seed: int = 0):
    """A workload nobody tuned on: photon-like points on the surfaces of a room 0.6 wide with
    a sphere and a slab, their density falling off from the ceiling, and query points on the
    same surfaces in random order. With 2 x 10^5 of each, r = 0.05 finds about 580-900
    photons per query. Returns (points (N, 3), queries (Q, 3)) float32."""
    rng = np.random.default_rng(seed)

    def surface(m):
        kind = rng.integers(0, 8, m)
        u, v = rng.random(m) * 2 - 1, rng.random(m) * 2 - 1
        p = np.zeros((m, 3))
        for axis in range(3):
            for side, k in ((-1, 2 * axis), (1, 2 * axis + 1)):
                sel = kind == k
                p[sel, axis] = side
                p[sel, (axis + 1) % 3], p[sel, (axis + 2) % 3] = u[sel], v[sel]
        sel = kind == 6
        d = rng.normal(size=(sel.sum(), 3))
        p[sel] = np.array([0.3, -0.6, 0.0]) + 0.4 * d / np.linalg.norm(d, axis=1)[:, None]
        sel = kind == 7
        p[sel] = np.c_[rng.random(sel.sum()) * 0.8 - 0.8, np.full(sel.sum(), -0.5),
                       rng.random(sel.sum()) * 0.8 - 0.4]
        return (0.3 * p).astype(np.float32)
    pts = surface(points * 3)
    pts = pts[rng.random(len(pts)) < np.exp(-(0.3 - pts[:, 1]) / 0.3)][:points]
    qs = surface(queries)
    rng.shuffle(qs)
    return np.ascontiguousarray(pts), np.ascontiguousarray(qs)


@dataclass
class _Workload:
    """Photons and queries for the bare-API rows."""

    name: str
    points: np.ndarray
    queries: np.ndarray        # random order
    radius: float


@dataclass
class _Bench:
    repeats: int
    say: object
    rows: list = field(default_factory=list)
    judged: bool = True         # False at the smoke size: its figures mean nothing

    def row(self, name, ours, base, base_name, target, ratio, meaning, at_least=True,
            unit="s", rounds=None, **extra):
        """One row; ``rounds``: the ratio of every timed round (its range is reported);
        ``target`` None: a reference row, held to nothing."""
        if target is None or not self.judged:
            ok = None
        else:
            ok = bool(ratio >= target if at_least else ratio <= target)
        if rounds is not None:
            extra.update(ratio_range=[float(np.min(rounds)), float(np.max(rounds))],
                         rounds=int(len(rounds)))
        self.rows.append({"benchmark": name, "ours": ours, "baseline": base,
                          "baseline_name": base_name, "ratio": ratio, "target": target,
                          "target_is": "none" if target is None else
                          "at least" if at_least else "at most",
                          "ratio_meaning": meaning, "met": ok, "unit": unit, **extra})
        spread = (f", rounds {extra['ratio_range'][0]:.2f}-{extra['ratio_range'][1]:.2f}"
                  if rounds is not None else "")
        held = "(for reference, no target)" if target is None else \
            "(smoke size: target not judged)" if not self.judged else \
            f"(target {'>=' if at_least else '<='} {target}) {'met' if ok else 'NOT met'}"
        self.say(f"  {name}: ours {ours:.4g} {unit}, {base_name} {base:.4g} {unit}, {meaning} "
                 f"{ratio:.2f}{spread} {held}")

    def pair(self, ours, base, repeats=None, base_jit=False):
        """(ours, baseline) seconds per round, timed in alternating rounds."""
        t = paired_times([(ours, True), (base, base_jit)], repeats or self.repeats)
        return t[0], t[1]

    def faster(self, name, ours, base, base_name, target, **extra):
        """A row from per-round seconds: medians, their ratio, the rounds' ratios."""
        ours, base = np.asarray(ours), np.asarray(base)
        o, b = float(np.median(ours)), float(np.median(base))
        self.row(name, o, b, base_name, target, b / o, "baseline time / ours",
                 rounds=base / ours, **extra)


def _points(a: np.ndarray) -> mi.Point3f:
    return mi.Point3f(*[np.ascontiguousarray(a[:, k]) for k in range(3)])


def _bench_queries(b: _Bench, w: _Workload):
    """Rows 1-2: radius power sums and kNN, unsorted and Morton-sorted queries."""
    from scipy.spatial import cKDTree
    forest = build_forest(w.points)
    power = mi.Float(np.ones(len(w.points), np.float32))
    ck = cKDTree(w.points, balanced_tree=True)
    try:
        from pykdtree.kdtree import KDTree
        knn_base, knn_name = KDTree(w.points), "pykdtree query(k=50)"
    except ImportError:
        knn_base, knn_name = None, "cKDTree query(k=50) (pykdtree not installed)"
    found = float(np.mean(ck.query_ball_point(w.queries[:2000], w.radius, return_length=True)))
    for order in ("unsorted", "sorted"):
        q = w.queries if order == "unsorted" else w.queries[morton_order(w.queries)]
        p = _points(q)
        ours, base = b.pair(
            lambda: radius_query(forest, p, w.radius, lambda i, d2, a, s: dr.gather(
                mi.Float, power, i, a)),
            lambda: ck.query_ball_point(q, w.radius, return_length=True, workers=-1))
        b.faster(f"radius sums, {w.name}, {order}", ours, base, "cKDTree count only", 3.0,
                 photons_per_query=found)
        ours, base = b.pair(
            lambda: knn_query(forest, p, 50, lambda i, d2, a, s: dr.gather(
                mi.Float, power, i, a)).total,
            (lambda: knn_base.query(q, k=50)) if knn_base is not None
            else (lambda: ck.query(q, k=50, workers=-1)))
        b.faster(f"kNN k=50, {w.name}, {order}", ours, base, knn_name, 1.0)


def _bench_estimate(b: _Bench, scene, photons: int, n: int = 32):
    """Row 3: the integrator's estimate at one pass's visible points, 1 map vs n maps: as
    the integrator builds them (sharing split planes; the target) and one separate tree per
    map walked in turn (for reference)."""
    traced = trace_photons(scene, photons, n, 1)
    one = build_photon_maps(traced.with_maps(dr.zeros(mi.UInt32, len(traced)), 1))
    split = {layout: build_photon_maps(traced, layout=layout) for layout in LAYOUTS}
    sensor = scene.sensors()[0]
    sampler = sensor.sampler()
    size = sensor.film().crop_size()
    sampler.seed(0, int(size[0] * size[1]))
    idx = dr.arange(mi.UInt32, int(size[0] * size[1]))
    uv = (mi.Vector2f(mi.Float(idx % int(size[0])), mi.Float(idx // int(size[0])))
          + sampler.next_2d()) / mi.ScalarVector2f(size)
    ray, _ = sensor.sample_ray(0.0, 0.5, uv, mi.Point2f(0.5))
    points = eye_paths(scene, sampler, ray, -1, 5, False, False).points
    radius = fixed_radius(scene, None, 0.05)

    def estimate(maps):
        est = gather_flux(maps, points.si, points.bsdf, radius)
        return est.flux, est.found
    for layout, name, target in (("shared", f"integrator estimate, {n} maps / 1 map", 2.0),
                                 ("separate", f"estimate, {n} separate trees in turn / 1 map",
                                  None)):
        tn, t1 = b.pair(lambda: estimate(split[layout]), lambda: estimate(one), base_jit=True)
        b.row(name, float(np.median(tn)), float(np.median(t1)), "one map, all photons", target,
              float(np.median(tn) / np.median(t1)), f"time of {n} maps / 1 map",
              at_least=False, rounds=tn / t1, visible_points=len(points), layout=layout)


def _bench_builds(b: _Bench, scene, sizes):
    """Row 4: builds at the given photon counts (photons traced in ``scene``)."""
    from scipy.spatial import cKDTree
    targets = {0: 1.0, 1: 1.0}
    emitted = max(1, max(sizes) // 3 + 1)
    positions = trace_photons(scene, emitted, 1, 2).position
    while len(positions) < max(sizes):
        positions = np.concatenate([positions, positions + 1e-4])
    for j, size in enumerate(sizes):
        pts = np.ascontiguousarray(positions[:size])
        device = _points(pts)
        sync(device)
        reps = b.repeats if size <= 1_000_000 else 1
        ours, base = b.pair(lambda: build_forest(device).records,
                            lambda: cKDTree(pts, balanced_tree=True), reps)
        b.faster(f"build, {size:,} photons", ours, base, "cKDTree(balanced_tree=True)",
                 targets.get(j, 1.5))
        del device


def path_segments(scene, spp: int, max_depth: int = 2, seed: int = 0) -> int:
    """Ray segments Mitsuba's ``path`` traces at ``max_depth`` without Russian roulette,
    counted by replaying its decisions: every camera ray; a shadow ray where emitter sampling
    finds a direction (a surface with a smooth lobe, depth + 1 < max_depth); a continuation
    ray where BSDF sampling gives a nonzero weight and depth + 1 < max_depth. The replay
    draws its own random numbers, so where a path escapes after a bounce can differ from
    path's own samples: the count is exact at max_depth 2 but for the rays whose BSDF sample
    has zero weight, and within about 1e-4 at max_depth 8 (a sum over 10^6 paths)."""
    sensor = scene.sensors()[0]
    size = sensor.film().crop_size()
    width = int(size[0] * size[1] * spp)
    sampler = sensor.sampler().clone()
    sampler.seed(seed, width)
    idx = dr.arange(mi.UInt32, width) // spp
    uv = (mi.Vector2f(mi.Float(idx % int(size[0])), mi.Float(idx // int(size[0])))
          + sampler.next_2d()) / mi.ScalarVector2f(size)
    ray, _ = sensor.sample_ray(0.0, 0.5, uv, mi.Point2f(0.5))
    active = dr.full(mi.Bool, True, width)
    segments = 0
    ctx = mi.BSDFContext()
    for depth in range(max_depth):
        segments += int(dr.count(active)[0])
        si = scene.ray_intersect(ray, active)
        active &= si.is_valid()
        if depth + 1 >= max_depth:
            break
        bsdf = si.bsdf(ray)
        smooth = active & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)
        ds, _ = scene.sample_emitter_direction(si, sampler.next_2d(smooth), False, smooth)
        segments += int(dr.count(smooth & (ds.pdf != 0))[0])
        bs, weight = bsdf.sample(ctx, si, sampler.next_1d(active), sampler.next_2d(active),
                                 active)
        active &= dr.any(weight != 0)
        ray = si.spawn_ray(si.to_world(bs.wo))
    return segments


def _bench_tracing(b: _Bench, scene_name, resolution, count, path_spp):
    """Row 5: photon tracing vs Mitsuba's path tracer, segments per second, both counted."""
    scene = load_scene(scene_name, resolution=resolution, spp=1)
    segments = trace_photons(scene, count, 1, 2).segments        # the same photons each round
    bound = _intersection_rate(scene, segments, b.repeats)
    ordered = _sorted_intersection(scene, segments, b.repeats)
    # Two baselines: path at max_depth 2 (camera, shadow and one bounce ray per sample: the
    # coherent camera rays flatter it) and at max_depth 8 without Russian roulette (mostly
    # incoherent bounces, like a photon's), its samples cut to keep the same work. Each is
    # timed in rounds with the tracer (its photons evaluated before the clock stops).
    for depth, spp in ((2, path_spp), (8, max(1, path_spp // 4))):
        path = mi.load_dict({"type": "path", "max_depth": depth, "rr_depth": 100})
        path_scene = load_scene(scene_name, resolution=resolution, spp=spp)
        ours_t, path_t = b.pair(lambda: trace_photons(scene, count, 1, 2),
                                lambda: mi.render(path_scene, integrator=path, spp=spp),
                                base_jit=True)
        path_count = path_segments(path_scene, spp, depth)
        ours_rate, path_rate = segments / np.median(ours_t), path_count / np.median(path_t)
        b.row(f"tracing, {count:,} photons, vs path max_depth {depth}", ours_rate / 1e6,
              path_rate / 1e6, f"Mitsuba path (max_depth {depth}, no Russian roulette)", 0.8,
              float(ours_rate / path_rate), "our rate / baseline rate", unit="M segments/s",
              rounds=(segments / ours_t) / (path_count / path_t),
              intersections_per_s=bound, of_intersections=float(ours_rate / bound),
              **ordered)
        b.say(f"    Mitsuba's ray_intersect alone, {segments:,} incoherent rays: "
              f"{bound / 1e6:.4g} M rays/s; the tracer runs at {ours_rate / bound:.2f} of it")
    b.say(f"    the same rays sorted (direction octant, origin's Morton code) and traced as "
          f"coherent: {ordered['sorted_intersections_per_s'] / 1e6:.4g} M rays/s; sorting them "
          f"and moving {LANE_STATE_BYTES} bytes of state per ray: "
          f"{ordered['reorder_ns_per_ray']:.1f} ns per ray; both: "
          f"{ordered['sorted_with_reorder_per_s'] / 1e6:.4g} M rays/s")


def _incoherent_rays(scene, count: int):
    """``count`` incoherent rays: origins uniform in the scene's bounding box shrunk by a
    tenth, directions uniform on the sphere (evaluated)."""
    rng = mi.PCG32(count)
    box = scene.bbox()
    lo, extent = box.min + 0.05 * box.extents(), 0.9 * box.extents()
    o = mi.Point3f(*[lo[a] + extent[a] * rng.next_float32() for a in range(3)])
    d = mi.warp.square_to_uniform_sphere(mi.Point2f(rng.next_float32(), rng.next_float32()))
    ray = mi.Ray3f(o, d)
    sync(ray)
    return ray


def _closest_hits(scene, ray, coherent: bool):
    """What the tracer reads of a closest hit (every surface field)."""
    return scene.ray_intersect(ray, ray_flags=mi.RayFlags.All, coherent=coherent).p


def _intersection_rate(scene, count: int, repeats: int) -> float:
    """Closest hits per second of ``scene.ray_intersect`` alone (every surface field, as the
    tracer asks for) on ``count`` incoherent rays (:func:`_incoherent_rays`). A bound on any
    tracer's segments per second that intersects each segment in the order its paths give
    them, as ours does; a shadow ray (``ray_test``, which path counts as a segment too) costs
    a fraction of it."""
    ray = _incoherent_rays(scene, count)
    return count / median_time(lambda: _closest_hits(scene, ray, False), repeats)


#: Bytes of a tracer lane's state (ray, power, random stream, photon, bounce, rank, runs of
#: photons and slots): what a tracer that sorted its rays would move with each ray.
LANE_STATE_BYTES = 64


def _sort_key(ray, box):
    """A 16-bit key that makes neighbouring rays alike: the direction's octant (3 bits),
    then the top 13 bits of the origin's Morton code over ``box`` (the scene's bounding
    box)."""
    octant = mi.UInt32(ray.d.x > 0) | (mi.UInt32(ray.d.y > 0) << 1) | \
        (mi.UInt32(ray.d.z > 0) << 2)
    return (octant << 13) | (morton_codes(ray.o, box) >> 17)


def _ray_order(key):
    """The permutation that sorts 16-bit ``key``: one radix pass where Dr.Jit has it."""
    mkperm = getattr(dr.detail, "block_mkperm", None)
    if mkperm is None or dr.backend_v(key) != dr.JitBackend.LLVM:
        return dr.argsort(key)
    dr.eval(key)
    return mkperm(key, dr.width(key), 1 << 16)


def _sorted_intersection(scene, count: int, repeats: int) -> dict:
    """What sorting every bounce's rays would buy: the closest hits per second of the same
    incoherent rays put in the order of :func:`_sort_key` and traced as coherent (sort not
    timed), and the time per ray to sort them and move :data:`LANE_STATE_BYTES` of state per
    ray into the new order (16-byte packet gathers, sequential stores), as a tracer that
    sorted its rays each bounce would pay."""
    ray, box = _incoherent_rays(scene, count), scene.bbox()
    ordered = dr.gather(mi.Ray3f, ray, _ray_order(_sort_key(ray, box)))
    sync(ordered)
    sorted_rate = count / median_time(lambda: _closest_hits(scene, ordered, True), repeats)
    words = LANE_STATE_BYTES // 16
    # Memory of its own: a gather from a literal (dr.zeros) folds into the literal, and
    # the reorder timed only the sort and stores of zeros (half its cost).
    state = dr.arange(mi.Float, 4 * words * count)
    dr.make_opaque(state)
    own = dr.arange(mi.UInt32, count)

    def reorder():
        perm = _ray_order(_sort_key(ray, box))
        moved = dr.empty(mi.Float, 4 * words * count)
        for w in range(words):
            dr.scatter(moved, dr.gather(mi.Vector4f, state, words * perm + w), words * own + w)
        return moved
    seconds = median_time(reorder, repeats)
    return {"sorted_intersections_per_s": sorted_rate, "reorder_ns_per_ray": seconds / count * 1e9,
            "sorted_with_reorder_per_s": 1.0 / (1.0 / sorted_rate + seconds / count)}


def _bench_emitters(b: _Bench, count: int):
    """Row 6: photons emitted and traced per second, per kind of emitter, against the area
    light (the floor of :mod:`mi_partpm.scenes.emitters`)."""
    import tempfile
    from ..scenes.emitters import EMITTER_KINDS, emitter_scene, write_textures
    rates = {}
    with tempfile.TemporaryDirectory() as folder:
        textures = write_textures(folder)
        for kind in EMITTER_KINDS:
            if kind == "sunsky" and mi.is_monochromatic:
                # (Mitsuba's sunsky refuses to load there: the run ended in its traceback.)
                b.say(f"emitting, {kind}: skipped (Mitsuba's sunsky renders in RGB and "
                      f"spectral variants only)")
                continue
            scene = emitter_scene(kind, textures)
            seconds = median_time(lambda: trace_photons(scene, count, 1, 0).points, b.repeats)
            rates[kind] = count / seconds
    area = rates["area_rectangle"]
    for kind, rate in rates.items():
        if kind != "area_rectangle":
            b.row(f"emitting, {kind}", rate / 1e6, area / 1e6, "area light (rectangle)", 0.2,
                  rate / area, "photons/s over the area light's", unit="M photons/s")


def _bench_memory(b: _Bench, scene_name, counts):
    """Row 7: bytes per stored photon, measured in a fresh process (:mod:`.memprobe`)."""
    from .memprobe import probe
    for count in counts:
        m = probe(scene_name, count, variant=mi.variant())   # the variant the bench runs
        b.row(f"memory, {count:,} photons emitted", m["peak_rss_bytes"] / m["stored"],
              m["drjit_peak_bytes"] / m["stored"], "Dr.Jit's own peak (B/photon)", 80.0,
              m["peak_rss_bytes"] / m["stored"], "process peak, bytes per stored photon",
              at_least=False, unit="B/photon", stored=m["stored"],
              peak_rss_bytes=m["peak_rss_bytes"], drjit_peak_bytes=m["drjit_peak_bytes"],
              baseline_rss_bytes=m["baseline_rss_bytes"], seconds=m["seconds"],
              variant=m["variant"])


def run_bench(out_json=None, scene_name: str = "cornell_box", size: str = "full",
              repeats: int | None = None, progress=print) -> dict:
    """Run every benchmark at ``size`` ("full" or "smoke"); return (and with ``out_json``
    write) the table."""
    cfg = dict(SIZES[size])
    if repeats is not None:
        cfg["repeats"] = repeats
    b = _Bench(cfg["repeats"], progress or (lambda *a: None), judged=size != "smoke")
    scene = load_scene(scene_name, resolution=cfg["resolution"], spp=1)
    traced = trace_photons(scene, cfg["photons"], 1, 0)
    hits = np.array(first_hits(scene, 1, 0)[0].p, dtype=np.float32).T
    rng = np.random.default_rng(5)
    cornell = _Workload(scene_name, traced.position, np.ascontiguousarray(
        hits[rng.permutation(len(hits))]), fixed_radius(scene, None, 0.05))
    b.say(f"{scene_name}: {cfg['photons']:,} photons emitted, {len(traced):,} stored, "
          f"{len(hits):,} hit points, r = {cornell.radius:.4g}")
    pts, qs = room_workload(cfg["room"], cfg["room"])
    for workload in (cornell, _Workload("room", pts, qs, 0.05)):
        _bench_queries(b, workload)
    _bench_estimate(b, scene, cfg["photons"])
    _bench_builds(b, scene, cfg["builds"])
    _bench_tracing(b, scene_name, cfg["resolution"], cfg["trace"], cfg["path_spp"])
    _bench_emitters(b, cfg["emitter_photons"])
    _bench_memory(b, scene_name, cfg["memory"])
    result = {"scene": scene_name, "size": size, "photons_emitted": cfg["photons"],
              "photons_stored": len(traced), "queries": len(hits), "radius": cornell.radius,
              "repeats": cfg["repeats"], "threads": int(dr.thread_count()),
              "code": code_version(), "commit": git_commit(), "machine": machine(),
              "rows": b.rows}
    if out_json:
        Path(out_json).parent.mkdir(parents=True, exist_ok=True)
        Path(out_json).write_text(json.dumps(result, indent=2) + "\n")
    return result


def format_bench(result) -> str:
    lines = [f"{result['scene']}: {result['photons_stored']} photons stored, "
             f"{result['queries']} queries, r = {result['radius']:.4g}, "
             f"{result['threads']} threads, medians of {result['repeats']} rounds "
             f"(code {result['code']}, commit {result['commit'] or 'unknown'})",
             f"{'benchmark':44} {'ours':>9} {'baseline':>9} {'ratio':>6} {'rounds':>11} "
             f"{'target':>8}  met  (ratio = ...; baseline)"]
    smoke = result.get("size") == "smoke"
    if smoke:
        lines.insert(1, "smoke size: this checks that every benchmark runs; its figures mean "
                        "nothing, and no target is judged (partpm bench, without --smoke, "
                        "measures)")
    for r in result["rows"]:
        target = "-" if r["target"] is None else \
            f"{'>=' if r['target_is'] == 'at least' else '<='} {r['target']:g}"
        met = "-" if r["met"] is None else "yes" if r["met"] else "NO "
        lo, hi = r.get("ratio_range", (None, None))
        spread = f"{lo:.2f}-{hi:.2f}" if lo is not None else "-"
        lines.append(f"{r['benchmark']:44} {r['ours']:9.4g} {r['baseline']:9.4g} "
                     f"{r['ratio']:6.2f} {spread:>11} {target:>8}  {met:3}"
                     f"  ({r['ratio_meaning']}; {r['baseline_name']}, {r['unit']})")
    return "\n".join(lines)
