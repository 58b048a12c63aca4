"""The kd-tree forest: structure, fixed-radius and kNN queries against scipy, eq. (2)."""
import numpy as np
import pytest
from scipy.spatial import cKDTree

import drjit as dr
import mitsuba as mi

from mi_partpm.kdtree import build_forest, knn_neighbours, knn_query, morton_order, radius_query
from mi_partpm.kdtree.radius import group_lanes, packet_lanes
from mi_partpm.photonmap import build_photon_maps
from mi_partpm.trace import trace_photons
from mi_partpm.estimate import radiance_estimate


def _query_sums(forest, weights, queries, r, maps=None):
    w = mi.Float(np.asarray(weights, np.float32)[forest.order])
    q = mi.Point3f(*[np.asarray(queries[:, k], np.float32) for k in range(3)])
    total, stats = radius_query(forest, q, r, lambda i, d2, a, s: dr.gather(mi.Float, w, i, a),
                                maps=maps, with_stats=True)
    return total.numpy(), stats.photons_found.numpy(), stats


def _reference(points, weights, queries, r):
    """scipy's neighbours, with the photons within float rounding of the sphere set apart."""
    tree = cKDTree(points.astype(np.float64))
    inner = tree.query_ball_point(queries, r * (1 - 1e-5))
    outer = tree.query_ball_point(queries, r * (1 + 1e-5))
    lo = np.array([weights[i].sum() for i in inner])
    hi = np.array([weights[i].sum() for i in outer])
    return lo, hi, np.array([len(i) for i in inner]), np.array([len(i) for i in outer])


def _check_against_scipy(points, queries, r, map_ids=None, n_maps=None, layout="separate",
                         leaf_size=32):
    rng = np.random.default_rng(3)
    weights = rng.random(points.shape[0]).astype(np.float32)
    forest = build_forest(points, map_ids, n_maps, leaf_size=leaf_size, layout=layout)
    sums, found, _ = _query_sums(forest, weights, queries, r)
    lo, hi, n_lo, n_hi = _reference(points, weights, queries, r)
    assert np.all(found >= n_lo) and np.all(found <= n_hi), "photon sets differ from scipy's"
    tol = 1e-5 * np.maximum(hi, 1) + 1e-6
    assert np.all(sums >= lo - tol) and np.all(sums <= hi + tol), "power sums differ"
    assert found.sum() > 0, "the test found no photon at all"


def test_tree_structure_is_balanced_median_split():
    rng = np.random.default_rng(0)
    pts = rng.random((1000, 3)) * np.array([4.0, 1.0, 0.5])
    f = build_forest(pts, leaf_size=8)
    # 1000 photons, leaves of <= 8: 2^7 = 128 leaves of 7 or 8 photons.
    assert f.depth(0) == 7
    sizes = np.diff(f.leaf_start.astype(np.int64))
    assert sizes.min() >= 7 and sizes.max() <= 8 and sizes.sum() == 1000
    # The root splits the longest axis (x) at the median.
    assert f.split_axis[0] == 0
    assert abs(f.split_value[0] - np.median(pts[:, 0])) < 0.05
    # Every photon of the left subtree is <= the split, every one of the right >= it.
    assert f.points[:500, 0].max() <= f.split_value[0] <= f.points[500:, 0].min()
    assert np.array_equal(np.sort(f.order), np.arange(1000))


@pytest.mark.parametrize("layout", ["separate", "shared"])
def test_uneven_map_sizes_and_empty_maps(layout):
    pts = np.random.default_rng(1).random((37, 3))
    ids = np.r_[np.zeros(30, int), np.full(7, 2)]
    f = build_forest(pts, ids, map_count=4, layout=layout)
    assert list(f.photon_count) == [30, 0, 7, 0]
    _check_against_scipy(pts, pts[:10], 0.3, ids, 4, layout)


@pytest.mark.parametrize("layout", ["separate", "shared"])
def test_radius_query_matches_scipy_on_random_photons(layout):
    rng = np.random.default_rng(2)
    pts = rng.random((20000, 3))
    queries = rng.random((3000, 3))
    _check_against_scipy(pts, queries, 0.05, layout=layout)
    _check_against_scipy(pts, queries, 0.05, rng.integers(0, 5, 20000), 5, layout)


def test_shared_layout_keeps_every_map_its_own_photons(monkeypatch):
    """Maps that share split planes: each leaf holds every map's photons as one run per map;
    a query over one map finds exactly that map's photons within r (brute force), a query
    over a range of maps the sum of theirs, and groups of maps (several trees) too."""
    from mi_partpm.kdtree import forest as forest_module
    from mi_partpm.kdtree import shared_leaf_size
    monkeypatch.setattr(forest_module, "GROUP_PHOTONS", 9_000)   # maps of about 3,000
    rng = np.random.default_rng(12)
    n = 7
    pts = rng.random((21_000, 3)).astype(np.float32)
    ids = rng.integers(0, n, 21_000)
    forest = build_forest(pts, ids, n, leaf_size=8, layout="shared")
    assert forest.tree_count == 3 and list(forest.tree_map_count) == [2, 3, 2]
    # Leaf runs: entry e of tree t is (leaf j, map m); runs are contiguous and hold only m.
    table = forest.leaf_start.astype(np.int64)
    tree_ids = ids[forest.order]
    for t in range(forest.tree_count):
        s, f0 = int(forest.tree_map_count[t]), int(forest.tree_first_map[t])
        leaves = int(forest.internal_count[t]) + 1
        base = int(forest.leaf_base[t])
        runs = table[base: base + leaves * s + 1]
        assert np.all(np.diff(runs) >= 0)
        for e in range(leaves * s):
            assert np.all(tree_ids[runs[e]:runs[e + 1]] == f0 + e % s)
        leaf_sizes = runs[s::s] - runs[:-1:s]
        assert leaf_sizes.max() <= shared_leaf_size(8, s)
    queries = rng.random((400, 3)).astype(np.float32)
    q = mi.Point3f(*[queries[:, k] for k in range(3)])
    weights = rng.random(len(pts)).astype(np.float32)
    w = mi.Float(weights[forest.order])                 # in tree order, as the walk reads
    r = 0.08
    d2 = ((queries[:, None, :] - pts[None, :, :]) ** 2).sum(-1)
    # Every map alone, all maps, ranges that start or end inside a group or cross groups.
    for maps in [(m, m + 1) for m in range(n)] + [(0, n), (1, 4), (2, 6), (3, 7), (5, 7)]:
        total, stats = radius_query(forest, q, r, lambda i, dd, a, st: dr.gather(
            mi.Float, w, i, a), maps=maps, with_stats=True)
        in_range = ((ids >= maps[0]) & (ids < maps[1]))[None]
        inside = (d2 < r * r * (1 - 1e-5)) & in_range
        edge = (d2 <= r * r * (1 + 1e-5)) & in_range
        found, sums = stats.photons_found.numpy(), total.numpy()
        assert np.all(found >= inside.sum(1)) and np.all(found <= edge.sum(1)), maps
        lo, hi = inside @ weights, edge @ weights
        assert np.all(sums >= lo - 1e-4 * hi - 1e-6) and np.all(sums <= hi + 1e-4 * hi + 1e-6)
        assert found.sum() > 0
    # An empty range finds nothing; a range outside the maps is an error, before any walk.
    _, stats = radius_query(forest, q, r, lambda i, dd, a, st: mi.Float(1.0), maps=(3, 3),
                            with_stats=True)
    assert stats.photons_found.numpy().sum() == 0
    with pytest.raises(ValueError, match=r"0 <= first <= stop <= map_count = 7, got \(0, 8\)"):
        radius_query(forest, q, r, lambda i, dd, a, st: mi.Float(1.0), maps=(0, 8))


@pytest.mark.parametrize("layout", ["separate", "shared"])
def test_maps_of_different_depths_and_empty_maps_in_one_tree(layout):
    """One build of maps whose trees end at different levels (1,000 and 50 photons in leaves
    of 8), an empty map and a map that is a single leaf, against scipy, map by map and all
    together; with no photon at all, the forest is empty and every query finds nothing."""
    rng = np.random.default_rng(14)
    sizes = [1000, 0, 50, 5]
    ids = np.repeat(np.arange(4), sizes)
    pts = rng.random((ids.size, 3))
    queries = rng.random((300, 3))
    forest = build_forest(pts, ids, 4, leaf_size=8, layout=layout)
    assert [forest.depth(m) for m in range(4)] == ([7, 0, 3, 0] if layout == "separate"
                                                   else [7] * 4)
    _check_against_scipy(pts, queries, 0.15, ids, 4, layout)
    for m in range(4):
        sel = ids == m
        _, found, _ = _query_sums(forest, np.ones(ids.size), queries, 0.15, maps=(m, m + 1))
        ref = cKDTree(pts[sel]).query_ball_point(queries, 0.15 * (1 - 1e-5),
                                                 return_length=True) if sel.any() else 0
        assert np.all(found >= ref) and (sel.any() or found.sum() == 0), m
    empty = build_forest(np.zeros((0, 3)), np.zeros(0, int), 3, layout=layout)
    assert empty.size == 0 and empty.nbytes > 0
    _, found, _ = _query_sums(empty, np.ones(0), queries[:5], 0.5)
    assert found.sum() == 0


def test_build_forest_rejects_an_unknown_layout():
    with pytest.raises(ValueError, match="layout must be one of 'separate', 'shared', got 'x'"):
        build_forest(np.zeros((4, 3)), layout="x")


def test_radius_query_matches_scipy_on_traced_photons():
    scene = mi_partpm_scene("cornell_box_diffuse")
    photons = trace_photons(scene, 20000, 1, seed=1)
    queries = photons.position[::7]
    _check_against_scipy(photons.position, queries, 0.1)


def test_degenerate_sets_duplicates_and_plane():
    pts = np.zeros((100, 3))
    _check_against_scipy(pts, np.zeros((2, 3)), 0.1)
    # A map that is a single leaf (no internal node).
    _check_against_scipy(np.random.default_rng(5).random((5, 3)), np.zeros((3, 3)), 0.9)
    rng = np.random.default_rng(4)
    plane = np.c_[rng.random((5000, 2)), np.zeros(5000)]
    _check_against_scipy(plane, plane[:500], 0.02)


def mi_partpm_scene(name, res=(32, 32), spp=1):
    import mi_partpm
    return mi_partpm.load_scene(name, resolution=res, spp=spp)


@pytest.mark.parametrize("n", [1, 2, 7, 32])
def test_partition_invariance_eq2(n):
    """One photon set split into n maps and gathered = one map, at the same hit points."""
    scene = mi_partpm_scene("cornell_box", res=(48, 48))
    photons = trace_photons(scene, 30000, 1, seed=5)
    rng = np.random.default_rng(n)
    one = build_photon_maps(photons)
    split = build_photon_maps(photons.with_maps(rng.integers(0, n, len(photons)), n))
    sensor = scene.sensors()[0]
    k = 48 * 48
    uv = mi.Point2f(*[mi.Float(np.asarray(a, np.float32)) for a in rng.random((2, k))])
    ray, _ = sensor.sample_ray(0.0, 0.5, uv, mi.Point2f(0.5, 0.5))
    si = scene.ray_intersect(ray)
    bsdf = si.bsdf(ray)
    active = si.is_valid() & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)
    a = radiance_estimate(one, si, bsdf, 0.1, active).numpy()
    b = radiance_estimate(split, si, bsdf, 0.1, active).numpy()
    assert a.max() > 0
    np.testing.assert_allclose(b, a, rtol=1e-5, atol=1e-6 * a.max())
    # Each map alone is a partial term; the partial terms add up to the whole.
    parts = sum(radiance_estimate(split, si, bsdf, 0.1, active, map_range=(m, m + 1)).numpy()
                for m in range(n))
    np.testing.assert_allclose(parts, a, rtol=1e-4, atol=1e-6 * a.max())


def _check_knn_against_scipy(points, queries, k, max_radius=None, map_ids=None, n_maps=None,
                             layout="separate"):
    """Same neighbours, same distances as cKDTree.query (distances to float32 rounding)."""
    forest = build_forest(points, map_ids, n_maps, layout=layout)
    dist, idx = knn_neighbours(forest, queries, k, max_radius)
    bound = np.inf if max_radius is None else max_radius
    ref_d, ref_i = cKDTree(points.astype(np.float32).astype(np.float64)).query(
        queries.astype(np.float32), k, distance_upper_bound=bound)
    ref_d, ref_i = ref_d.reshape(dist.shape), ref_i.reshape(idx.shape)
    np.testing.assert_array_equal(np.isfinite(dist), np.isfinite(ref_d))
    finite = np.isfinite(ref_d)
    np.testing.assert_allclose(dist[finite], ref_d[finite], rtol=1e-5, atol=1e-7)
    # Same neighbours wherever the k-th distance is not tied with the next (random data: all).
    assert (idx == ref_i).mean() > 0.999, f"{(idx != ref_i).sum()} neighbours differ"
    return forest, dist


def test_knn_matches_scipy_query():
    rng = np.random.default_rng(7)
    pts = rng.random((20000, 3))
    queries = rng.random((2000, 3))
    _check_knn_against_scipy(pts, queries, 1)
    _check_knn_against_scipy(pts, queries, 50)
    # Over several maps, the k nearest of all of them (the same photons as one map), with
    # a tree per map and with maps sharing one.
    ids = rng.integers(0, 5, 20000)
    _check_knn_against_scipy(pts, queries, 16, map_ids=ids, n_maps=5)
    _check_knn_against_scipy(pts, queries, 16, map_ids=ids, n_maps=5, layout="shared")


def test_knn_max_radius_caps_the_search_like_jensen():
    rng = np.random.default_rng(8)
    pts = rng.random((3000, 3))
    queries = np.r_[rng.random((500, 3)), [[5.0, 5.0, 5.0]]]   # the last one finds nothing
    forest, dist = _check_knn_against_scipy(pts, queries, 12, max_radius=0.1)
    q = mi.Point3f(*[np.asarray(queries[:, j], np.float32) for j in range(3)])
    res = knn_query(forest, q, 12, lambda i, d2, a, s: mi.Float(1.0), max_radius=0.1)
    count, r2, total = res.count.numpy(), res.radius2.numpy(), res.total.numpy()
    assert 0 < (count < 12).sum() < len(count), "want capped and uncapped queries both"
    np.testing.assert_array_equal(count, np.isfinite(dist).sum(axis=1))
    np.testing.assert_array_equal(total, count)
    # Capped: r = max_radius; full: r = distance to the k-th photon.
    np.testing.assert_allclose(np.sqrt(r2), np.where(count < 12, 0.1, dist[:, -1]), rtol=1e-5)


def test_knn_on_traced_photons_and_degenerate_sets():
    scene = mi_partpm_scene("cornell_box_diffuse")
    photons = trace_photons(scene, 20000, 1, seed=1)
    _check_knn_against_scipy(photons.position, photons.position[::9], 20)
    rng = np.random.default_rng(9)
    plane = np.c_[rng.random((4000, 2)), np.zeros(4000)]
    _check_knn_against_scipy(plane, plane[:300] + [0, 0, 0.01], 8)
    # k larger than the photon count: every photon, then "missing" entries.
    dist, idx = knn_neighbours(build_forest(plane[:5]), plane[:2], 8)
    assert np.isfinite(dist).sum(axis=1).tolist() == [5, 5] and (idx[:, 5:] == 5).all()
    # All photons at one point: distances all equal, k of them taken.
    dist, _ = knn_neighbours(build_forest(np.zeros((100, 3))), np.ones((3, 3)), 10)
    np.testing.assert_allclose(dist, np.sqrt(3), rtol=1e-6)


def test_knn_rejects_bad_k():
    forest = build_forest(np.zeros((4, 3)))
    with pytest.raises(ValueError, match=r"k must be an integer in \[1, 16383\], got 0"):
        knn_query(forest, mi.Point3f(0, 0, 0), 0)
    with pytest.raises(ValueError, match=r"k must be an integer in \[1, 16383\], got 16384"):
        knn_neighbours(forest, np.zeros((1, 3)), 16384)


def test_knn_neighbours_above_the_photon_count_asks_for_the_photons_only(monkeypatch):
    """A k above the forest's N photons (a scipy user's "all of them") answers as scipy does,
    inf and N past the N found, but walks for N only: the walk's cost follows the k it
    keeps, and all 100 photons asked for with k = 3400 took 12.6 s where k = 100 takes 0.01 s
    (and k = 16383 of 1000 photons 258 s). Asserted on the k the walk is given."""
    import mi_partpm.kdtree.knn as knn
    rng = np.random.default_rng(5)
    points, queries = rng.random((100, 3)), rng.random((7, 3))
    asked = []
    walk = knn.knn_query
    monkeypatch.setattr(knn, "knn_query",
                        lambda f, p, k, **kw: asked.append(k) or walk(f, p, k, **kw))
    dist, idx = knn_neighbours(build_forest(points), queries, 3400)
    ref_d, ref_i = cKDTree(points).query(queries, 3400)
    assert asked == [100] and dist.shape == idx.shape == (7, 3400)
    np.testing.assert_allclose(dist, ref_d, rtol=1e-5, atol=1e-6)
    assert (idx[:, 100:] == 100).all() and np.isinf(dist[:, 100:]).all()
    assert all(set(a) == set(b) for a, b in zip(idx[:, :100], ref_i[:, :100]))


@pytest.mark.parametrize("order, queries", [("given", 10), ("morton", 4100)])
def test_knn_at_the_largest_k_answers_as_scipy(order, queries):
    """The largest k the query takes runs on both walks: it was one too many for Dr.Jit's
    local arrays (65536 entries) and failed in the grouped walk (the given order, or 4096
    queries or more in Morton order) instead of answering."""
    from mi_partpm.kdtree.knn import MAX_K
    rng = np.random.default_rng(3)
    points, q = rng.random((MAX_K + 500, 3)), rng.random((queries, 3))
    result = knn_query(build_forest(points), q, MAX_K, order=order)
    assert (result.count.numpy() == MAX_K).all()
    kth, _ = cKDTree(points).query(q, [MAX_K])
    np.testing.assert_allclose(np.sqrt(result.radius2.numpy()), kth[:, 0], rtol=1e-5)


def test_the_grouped_walk_keeps_its_local_arrays_within_bounds():
    """The grouped walk's candidates and k nearest (8 bytes each per lane) stay within
    LOCAL_BYTES per lane: 40 bytes per k and lane took 10.5 MB of a thread's 8 MB stack at
    k = 16,383 and 16 lanes (AVX-512) and ended pm's process (a segfault; its test runs pm
    in a process of its own). Up to k = 6,553 it keeps 4 k as before; above, fewer, and the
    answers stay scipy's (the test above, at the largest k)."""
    from mi_partpm.kdtree.knn import KNN_KEEP, LOCAL_BYTES, MAX_K, kept_candidates
    for k in (1, 2, 50, 6553, 6554, 10_000, MAX_K):
        keep = kept_candidates(k)
        assert k <= keep <= KNN_KEEP * k and 8 * (keep + k) <= LOCAL_BYTES, k
    assert kept_candidates(6553) == KNN_KEEP * 6553 and kept_candidates(6554) < KNN_KEEP * 6554


def _call(kind, forest, q, **kw):
    if kind == "radius":
        return radius_query(forest, q, kw.pop("r", 0.1), lambda i, d2, a, s: mi.Float(1.0),
                            **kw)
    return knn_query(forest, q, 2, **kw)


@pytest.mark.parametrize("make, message", [
    (lambda pts: build_forest(pts.T), r"points must have shape \(N, 3\), got \(3, 99\)"),
    (lambda pts: build_forest(pts[:, :2]), r"points must have shape \(N, 3\), got \(99, 2\)"),
    (lambda pts: build_forest(pts, np.full(99, 2**32), 2), r"map_ids must be integers >= 0, "
                                                           r"< map_count = 2; got values"),
    (lambda pts: build_forest(pts, np.full(99, 0.5), 2), r"map_ids must be integers"),
    # Beyond 32 bits without map_count: the bound is the forest's (it said "integers >= 0,
    # got values from 1099511627776").
    (lambda pts: build_forest(pts, np.full(99, 2**40)), r"map_ids must be integers in "
                                                        r"\[0, 1048576\) \(a forest holds at "
                                                        r"most 1048576 maps\); got values from "
                                                        r"1099511627776"),
    (lambda pts: build_forest(pts, payload=mi.UInt32([1, 2, 3])),
     r"payload has 3 entries for 99 points"),
    (lambda pts: knn_neighbours(build_forest(pts), pts[:5].T, 2),
     r"points must have shape \(N, 3\), got \(3, 5\)"),
    (lambda pts: build_forest([[0, 0, 0], [1, 2]]), r"points must be numbers of shape \(N, 3\)"),
    (lambda pts: knn_neighbours(build_forest(pts), [[0, 0, 0], [1, 2]], 2),
     r"points must be numbers of shape \(N, 3\)"),
    (lambda pts: _call("radius", build_forest(pts), pts[:5], r=-0.3),
     r"r must be 0 or in \[1e-15, inf\] \(inf for no bound\), got -0.3"),
    (lambda pts: _call("radius", build_forest(pts), pts[:5], r=5e-16),
     r"r must be 0 or in \[1e-15, inf\] \(inf for no bound\), got 5e-16"),
    (lambda pts: _call("radius", build_forest(pts), pts[:5], r=10**400),
     r"r must be 0 or in \[1e-15, inf\] \(inf for no bound\), got an integer too large"),
    (lambda pts: _call("radius", build_forest(pts), pts[:10], r=np.ones((2, 5))),
     r"r must be a number or one per query point \(shape \(Q,\)\), got shape \(2, 5\)"),
    (lambda pts: _call("radius", build_forest(pts), pts[:10], active=np.ones(10) / 2),
     r"active must be true or false, or one bool per query point"),
    (lambda pts: _call("radius", build_forest(pts), pts[:10], active=0.5),
     r"active must be true or false, or one bool per query point, got 0.5"),
    (lambda pts: _call("radius", build_forest(pts), pts[:10], r=True),
     r"r must be 0 or in \[1e-15, inf\] \(inf for no bound\), got True \(a bool is no "
     r"radius\)"),
    (lambda pts: _call("radius", build_forest(pts), pts[:5], maps=(0.5, 1.7)),
     r"maps must be \(first, stop\) with 0 <= first <= stop <= map_count = 1, got \(0.5"),
    (lambda pts: _call("knn", build_forest(pts), pts[:5], maps=(True, 1)),
     r"maps must be \(first, stop\)"),
    (lambda pts: build_forest(pts, leaf_size=True), r"leaf_size must be an integer in \[1, "
                                                    r"4294967296\] .*, got True"),
    # Beyond 64 bits it was an OverflowError from NumPy.
    (lambda pts: build_forest(pts, leaf_size=2**70), r"leaf_size must be an integer in \[1, "),
    # A Dr.Jit Bool was taken as radius 1 or 0; a 3-vector failed inside Dr.Jit.
    (lambda pts: _call("radius", build_forest(pts), pts[:3], r=mi.Bool([True, False, True])),
     r"r must be a number or one per query point \(a mi.Float\), got Bool"),
    (lambda pts: _call("knn", build_forest(pts), pts[:3], max_radius=mi.Bool(True)),
     r"max_radius must be a number or one per query point \(a mi.Float\), got Bool"),
    (lambda pts: _call("radius", build_forest(pts), pts[:3], r=mi.Point3f(0.1, 0.2, 0.3)),
     r"r must be a number or one per query point \(a mi.Float\), got Point3f"),
    (lambda pts: build_forest(pts + 1j), r"points must be real numbers of shape \(N, 3\)"),
    (lambda pts: build_forest(pts * 1e-18),
     r"photon positions span 9.\d+e-19 \(the longest side of their bounding box\), less "
     r"than 1e-12"),
    (lambda pts: _call("radius", build_forest(pts), pts[:5], r="0.1"),
     r"r must be a number or one per query point \(shape \(Q,\)\), got '0.1'"),
    (lambda pts: _call("radius", build_forest(pts), pts[:5], maps=2),
     r"maps must be \(first, stop\) with 0 <= first <= stop <= map_count = 1, got 2"),
    (lambda pts: build_forest(pts * 3e19),
     r"photon positions must be finite with coordinates within \+-1e\+18"),
    (lambda pts: knn_neighbours(build_forest(pts), np.array([[3e19, 0, 0]]), 2),
     r"points must be finite with coordinates within \+-1e\+18"),
    (lambda pts: morton_order(np.array([[np.inf, 0, 0], [1, 1, 1]])),
     r"points must be finite with coordinates within"),
    (lambda pts: build_forest(pts, np.r_[np.zeros(98, int), 10**7]),
     r"map_ids must lie in \[0, 1048576\) \(a forest holds at most 1048576 maps\), got a "
     r"maximum of 10000000"),
    (lambda pts: build_forest(pts, mi.UInt32(np.r_[np.zeros(98), 2**32 - 1].astype(np.uint32))),
     r"map_ids must lie in \[0, 1048576\)"),
    (lambda pts: build_forest(pts, np.zeros(99, int), 4.0),
     r"map_count must be an integer in \[1, 1048576\], got 4.0"),
    (lambda pts: build_forest(pts, np.zeros(99, int), "4"),
     r"map_count must be an integer in \[1, 1048576\], got '4'"),
    (lambda pts: build_forest(pts, payload=mi.Float(np.ones(99))),
     r"payload must be mi.UInt32 or integers of shape \(N,\), got Float"),
    (lambda pts: build_forest(pts, payload=np.ones(99) / 2),
     r"payload must be integers in \[0, 2\^32\), one per point"),
    (lambda pts: _call("radius", build_forest(pts), pts[:5], r=mi.Float([0.1, 0.2])),
     r"r has 2 entries for 5 query points"),
    (lambda pts: _call("knn", build_forest(pts), pts[:5], max_radius=mi.Float([0.1, -1, 0, 0,
                                                                                0])),
     r"max_radius must be 0 or in \[1e-15, inf\]"),
    (lambda pts: _call("knn", build_forest(pts), pts[:5], active=mi.Bool([True, False])),
     r"active has 2 entries for 5 query points"),
    (lambda pts: _call("radius", build_forest(pts), np.array([[0, 0, np.nan]])),
     r"p must be finite with coordinates within \+-1e\+18"),
    (lambda pts: knn_neighbours(build_forest(pts), np.array([[np.inf, 0, 0]]), 2),
     r"points must be finite with coordinates within \+-1e\+18"),
])
def test_bad_input_names_the_argument(make, message):
    """What scipy refuses (or what would pair the wrong numbers into points, walk the wrong
    sides of the tree with a negative radius, wrap map ids past 2^32, allocate a table per
    map id up to a stray large one, or compare squared distances that overflow or leave
    float32's normal range) is a ValueError that names the argument and what it may be."""
    pts = np.random.default_rng(0).random((99, 3))
    with pytest.raises(ValueError, match=message):
        make(pts)


def test_the_least_radius_finds_what_scipy_finds():
    """At the least radius the photons found are scipy's, to float32 rounding: a cluster
    ten radii wide near the origin (where float32 resolves it) inside a cloud of size 1,
    queries in the cluster, about 80 photons found per query. At 1e-18, the least radius
    before, squared coordinate differences flushed to zero: photons up to 1.0001 r were
    found, and 1124 of 3000 queries differed from scipy (a cluster 1e-17 wide)."""
    from mi_partpm.kdtree.radius import MIN_RADIUS
    rng = np.random.default_rng(0)
    width = 10 * MIN_RADIUS
    cluster = (rng.random((20000, 3)) * width).astype(np.float32)
    points = np.concatenate([cluster, rng.random((100, 3)).astype(np.float32)])
    q = (rng.random((500, 3)) * width).astype(np.float32)
    found = radius_query(build_forest(points), q, MIN_RADIUS,
                         lambda i, d2, a, s: mi.Float(1.0)).numpy()
    ref = np.asarray(cKDTree(points.astype(np.float64)).query_ball_point(
        q.astype(np.float64), MIN_RADIUS, return_length=True))
    assert ref.mean() > 20, ref.mean()
    assert np.abs(found - ref).sum() <= 3, (found.sum(), ref.sum())   # boundary rounding


def test_an_empty_forest_refuses_what_a_full_one_refuses():
    """The checks of order and maps come before an empty forest's answer of zeros."""
    empty = build_forest(np.zeros((0, 3)), map_count=5)
    q = np.random.default_rng(0).random((2, 3))
    with pytest.raises(ValueError, match=r"maps must be \(first, stop\) with 0 <= first <= "
                                         r"stop <= map_count = 5, got \(1, 9\)"):
        radius_query(empty, q, 0.3, lambda i, d2, a, s: mi.Float(1.0), maps=(1, 9))
    with pytest.raises(ValueError, match=r"order must be one of"):
        radius_query(empty, q, 0.3, lambda i, d2, a, s: mi.Float(1.0), order="bogus")
    with pytest.raises(ValueError, match=r"maps must be \(first, stop\)"):
        knn_query(empty, q, 3, maps=(0, 9))


def test_tree_bytes_refuses_what_is_no_count():
    from mi_partpm.kdtree import tree_bytes
    with pytest.raises(ValueError, match=r"counts must be integers >= 0, got \[-5\]"):
        tree_bytes([-5])
    with pytest.raises(ValueError, match=r"leaf_size must be integers >= 1, got 0"):
        tree_bytes([100], 0)
    for leaf_size in (True, 1.5):
        with pytest.raises(ValueError, match=r"leaf_size must be integers >= 1"):
            tree_bytes([100], leaf_size)
    with pytest.raises(ValueError, match=r"counts must be integers >= 0, got \[2.5\]"):
        tree_bytes([2.5])


def test_a_forest_is_asked_for_by_name():
    with pytest.raises(TypeError, match=r"forest must be a Forest \(made by build_forest\), "
                                        r"got ndarray"):
        radius_query(np.zeros((4, 3)), np.zeros((1, 3)), 0.1, lambda i, d2, a, s: mi.Float(1.0))
    with pytest.raises(TypeError, match=r"forest must be a Forest"):
        knn_query(np.zeros((4, 3)), np.zeros((1, 3)), 2)


def test_payloads_as_integers_and_the_extremes_of_scale():
    """A payload of NumPy integers is kept as a mi.UInt32 one is; the coordinates and radii
    at the ends of the accepted range give scipy's answers (points up to 1e18 apart in
    magnitude, points that span the least extent, 1e-12); an empty forest has no points
    and reports a radius of 0 (not inf) where it finds nothing without a cap."""
    rng = np.random.default_rng(3)
    pts = rng.random((300, 3))
    codes = rng.integers(0, 1 << 31, 300).astype(np.uint32)
    a, b = build_forest(pts, payload=codes), build_forest(pts, payload=mi.UInt32(codes))
    np.testing.assert_array_equal(a.records.numpy(), b.records.numpy())
    for scale, r in ((1e18 / 2, 1e17), (1.02e-12, 1e-13)):
        p, q = pts * scale, rng.random((50, 3)) * scale
        found = radius_query(build_forest(p), q, r, lambda i, d2, a, s: mi.Float(1.0)).numpy()
        assert found.tolist() == cKDTree(p).query_ball_point(q, r, return_length=True).tolist()
        d, i = knn_neighbours(build_forest(p), q, 3)
        np.testing.assert_array_equal(i, cKDTree(p).query(q, 3)[1])
    empty = build_forest(np.zeros((0, 3)))
    assert empty.points.shape == (0, 3) and empty.order.shape == (0,)
    assert knn_query(empty, np.zeros((2, 3)), 3).radius2.numpy().tolist() == [0, 0]
    assert knn_query(empty, np.zeros((2, 3)), 3, max_radius=2).radius2.numpy().tolist() == [4, 4]


def test_numpy_and_other_drjit_vectors_are_points_too():
    """Queries as NumPy arrays, and points as other Dr.Jit 3-vectors, give scipy's answers;
    zero queries give empty results, as scipy's."""
    rng = np.random.default_rng(1)
    pts, q = rng.random((500, 3)), rng.random((7, 3))
    ref_d, ref_i = cKDTree(pts).query(q, 4)
    for points in (pts, mi.Vector3f(*pts.T.astype(np.float32)), mi.Point3d(*pts.T)):
        d, i = knn_neighbours(build_forest(points), q, 4)
        np.testing.assert_array_equal(i, ref_i)
        np.testing.assert_allclose(d, ref_d, rtol=1e-5)
    forest = build_forest(pts)
    counts = radius_query(forest, q, 0.2, lambda i, d2, a, s: mi.Float(1.0)).numpy()
    assert counts.tolist() == [len(x) for x in cKDTree(pts).query_ball_point(q, 0.2)]
    d, i = knn_neighbours(forest, np.zeros((0, 3)), 3)
    assert d.shape == i.shape == (0, 3)
    assert build_forest(mi.ScalarPoint3f(1, 2, 3)).size == 1          # one point
    # An inactive lane may hold any radius, as it may hold any point.
    r = mi.Float([0.2, float("nan"), -1.0])
    got = radius_query(forest, q[:3], r, lambda i, d2, a, s: mi.Float(1.0),
                       active=mi.Bool([True, False, False])).numpy()
    assert got.tolist() == [len(cKDTree(pts).query_ball_point(q[0], 0.2)), 0, 0]


class _KnnState:
    """Per-query data for kNN callbacks, permuted with the queries."""
    DRJIT_STRUCT = {"odd": mi.Bool, "radius2": mi.Float}


def _knn_both_walks(forest, q, k, contribution=None, **kw):
    """knn_query's grouped and own walks on the same queries."""
    return [knn_query(forest, q, k, contribution, walk=walk, neighbours=True, **kw)
            for walk in ("group", "own")]


def _sorted_neighbours(d2, idx):
    d2 = np.stack([a.numpy() for a in d2], axis=1)
    idx = np.stack([a.numpy() for a in idx], axis=1)
    order = np.lexsort((idx, d2), axis=1)           # equal distances: by index
    return np.take_along_axis(d2, order, axis=1), np.take_along_axis(idx, order, axis=1)


def _assert_same_answers(group, own):
    """The same total (to float rounding of the order summed), radius, count and
    neighbours."""
    (g, *g_lists), (o, *o_lists) = group, own
    np.testing.assert_allclose(g.total.numpy(), o.total.numpy(), rtol=1e-5, atol=1e-9)
    np.testing.assert_array_equal(g.radius2.numpy(), o.radius2.numpy())
    np.testing.assert_array_equal(g.count.numpy(), o.count.numpy())
    for a, b in zip(_sorted_neighbours(*g_lists), _sorted_neighbours(*o_lists)):
        np.testing.assert_array_equal(a, b)


def test_grouped_knn_finds_the_neighbours_of_the_own_walk(monkeypatch):
    """The grouped kNN (a bound from each group's leader, a walk of that ball in groups, a
    selection by distance bins, the own walk for the lanes it does not settle) returns what
    the own walk does, exactly: the same totals, radii, counts and neighbours, and scipy's
    distances. Queries on the photons' surfaces, more than SORT_FROM so they are sorted and
    grouped, denser than the photons (as a render's visible points are), a count that leaves
    the last group short; a scalar and a per-lane cap, an accept test that differs per lane,
    inactive lanes (one holding NaN), a range of maps; then queries too sparse to walk together."""
    from mi_partpm.kdtree import knn as knn_module
    rng = np.random.default_rng(21)
    n, m, k = 30000, 12003, 24
    pts = np.c_[rng.random((n, 2)), 0.02 * rng.random(n)].astype(np.float32)
    queries = np.c_[0.4 * rng.random((m, 2)), 0.02 * rng.random(m)].astype(np.float32)
    queries[3] = np.nan                  # an inactive lane: NaN is refused in active ones
    forest = build_forest(pts, rng.integers(0, 3, n), 3)
    q = mi.Point3f(*[mi.Float(queries[:, j]) for j in range(3)])
    active = mi.Bool(np.arange(m) % 97 != 3)
    lanes = []
    real_walk = knn_module._knn_walk

    def spy(f, p, *a):                          # the widths the own walk runs at
        lanes.append(dr.width(p))
        return real_walk(f, p, *a)
    monkeypatch.setattr(knn_module, "_knn_walk", spy)

    def parity(i, a, s):                        # odd lanes accept odd photons only
        return ~s.odd | ((i & 1) == 1)

    state = _KnnState()
    state.odd, state.radius2 = mi.Bool(np.arange(m) % 2 == 1), dr.zeros(mi.Float, m)
    cap = mi.Float(np.where(np.arange(m) % 3 == 0, 0.011, np.inf).astype(np.float32))
    for kw in ({}, {"max_radius": 0.011}, {"max_radius": cap}, {"maps": (1, 3)},
               {"accept": parity, "state": state}):
        lanes.clear()
        group, own = _knn_both_walks(forest, q, k, lambda i, d2, a, s: mi.Float(d2),
                                     active=active, with_stats=True, **kw)
        _assert_same_answers(group, own)
        stats = group[0].stats
        np.testing.assert_array_equal(stats.photons_found.numpy(), group[0].count.numpy())
        np.testing.assert_array_equal(stats.nodes_visited.numpy() > 0, active.numpy())
        assert (stats.photons_tested.numpy() >= stats.photons_found.numpy()).all()
        # The grouped walk settled most lanes itself: the own walk ran for the leaders (one
        # per group) and for fewer than a third of the others (a ball short of k, as where
        # lanes accept other photons than their leader, or one with more photons than it
        # keeps: 5-22% here in groups of 8, 10-29% in groups of 16); then the own walk of
        # the comparison.
        size = group_lanes(q)
        assert lanes[0] == -(-m // size) and lanes[-1] == m, lanes
        assert len(lanes) == 2 or (len(lanes) == 3 and lanes[1] < m / 3), lanes
    _check_knn_against_scipy(pts, queries[np.isfinite(queries).all(1)], k)
    # Queries farther apart than their neighbours (on the whole slab): most walk on their own.
    sparse = mi.Point3f(*[mi.Float(a) for a in (rng.random(m), rng.random(m),
                                                 0.02 * rng.random(m))])
    _assert_same_answers(*_knn_both_walks(forest, sparse, k, lambda i, d2, a, s: d2))
    # Fewer photons than k (in the maps asked for), and fewer queries than SORT_FROM: the own
    # walk alone (they are not sorted, so a group's lanes would lie apart).
    _assert_same_answers(*_knn_both_walks(build_forest(pts[:20]), q, k, active=active))
    lanes.clear()
    few = mi.Point3f(*[mi.Float(queries[:1000, j]) for j in range(3)])
    _assert_same_answers(*_knn_both_walks(forest, few, k,
                                          active=mi.Bool(np.arange(1000) % 97 != 3)))
    assert lanes == [1000, 1000]
    # Whatever the bound or the room, the lanes the grouped walk cannot settle are walked on
    # their own: no room beyond k, a first ball of only the leader's radius, one bin.
    for name, value in (("KNN_KEEP", 1), ("KNN_REACH", 0.0), ("KNN_BINS", 1)):
        with monkeypatch.context() as patch:
            patch.setattr(knn_module, name, value)
            _assert_same_answers(*_knn_both_walks(forest, q, k, lambda i, d2, a, s: d2,
                                                  active=active))


def test_grouped_knn_weighs_by_each_lanes_own_radius():
    """A contribution that reads ``state.radius2`` (a density kernel) sees each query's own
    k-th distance in the grouped walk too, and the state keeps it afterwards; ties (every
    photon at one point, fewer than the walk keeps) take k."""
    rng = np.random.default_rng(22)
    pts = rng.random((20000, 3)).astype(np.float32)
    queries = rng.random((9001, 3)).astype(np.float32)
    forest = build_forest(pts)
    q = mi.Point3f(*[mi.Float(queries[:, j]) for j in range(3)])
    state = _KnnState()
    state.odd, state.radius2 = dr.zeros(mi.Bool, 9001), dr.zeros(mi.Float, 9001)
    group, own = _knn_both_walks(forest, q, 10, lambda i, d2, a, s: 1 - d2 / s.radius2,
                                 state=state, order="given")
    _assert_same_answers(group, own)
    assert (group[0].total.numpy() > 0).all()
    np.testing.assert_array_equal(state.radius2.numpy(), own[0].radius2.numpy())
    same = build_forest(np.zeros((30, 3), np.float32))
    group, own = _knn_both_walks(same, q, 10, lambda i, d2, a, s: mi.Float(1.0))
    _assert_same_answers(group, own)
    np.testing.assert_array_equal(group[0].count.numpy(), 10)
    np.testing.assert_array_equal(group[0].total.numpy(), 10)
    np.testing.assert_allclose(group[0].radius2.numpy(), (queries ** 2).sum(1), rtol=1e-6)
    with pytest.raises(ValueError, match="walk must be one of 'group', 'own', got 'x'"):
        knn_query(forest, q, 3, walk="x")


def test_morton_order_is_a_permutation_that_keeps_neighbours_together():
    from mi_partpm.kdtree import morton_order
    pts = np.random.default_rng(11).random((5000, 3))
    order = morton_order(pts)
    assert np.array_equal(np.sort(order), np.arange(5000))
    step = np.linalg.norm(np.diff(pts[order], axis=0), axis=1).mean()
    random_step = np.linalg.norm(np.diff(pts, axis=0), axis=1).mean()
    assert step < random_step / 4, (step, random_step)
    assert morton_order(np.zeros((0, 3))).shape == (0,)


@pytest.mark.parametrize("grouped_ids", [True, False])
def test_maps_built_in_groups_give_the_same_forest(monkeypatch, grouped_ids):
    """Large photon sets are built a group of maps at a time (cache-sized); the forest is
    the one an all-at-once build gives, bit for bit, whether or not the caller's photons
    come grouped by map."""
    from mi_partpm.kdtree import forest as forest_module
    rng = np.random.default_rng(1)
    pts = rng.random((50_000, 3)).astype(np.float32)
    ids = rng.integers(0, 7, 50_000)
    if grouped_ids:
        ids = np.sort(ids)
    monkeypatch.setattr(forest_module, "GROUP_PHOTONS", 1 << 30)
    whole = build_forest(pts, ids, 7)
    monkeypatch.setattr(forest_module, "GROUP_PHOTONS", 10_000)
    assert len(forest_module._groups(whole.photon_count)) == 7
    grouped = build_forest(pts, ids, 7)
    for name in ("order", "leaf_start"):
        np.testing.assert_array_equal(getattr(grouped, name), getattr(whole, name))
    np.testing.assert_array_equal(grouped.nodes.numpy(), whole.nodes.numpy())
    np.testing.assert_array_equal(grouped.records.numpy(), whole.records.numpy())


_SHARED_BESIDE_ONE = """
import sys
import numpy as np, drjit as dr, mitsuba as mi
mi.set_variant(sys.argv[1])
from mi_partpm.kdtree import forest
forest.GROUP_PHOTONS = 1000
count = int(sys.argv[2])
rng = np.random.default_rng(count)
ids = np.sort(rng.integers(0, 2, count))
first, maps = forest._trees(np.bincount(ids, minlength=8), "shared")
assert first.shape[0] >= 2 and maps.max() > 1, (first, maps)
f = forest.build_forest(rng.random((count, 3)).astype(np.float32), ids, 8, layout="shared")
dr.eval(f.records, f.leaf_table)
print("built", f.leaf_table.numpy()[-1])
"""


@pytest.mark.parametrize("count", [1601, 2003])
def test_shared_trees_beside_a_tree_of_one_map(monkeypatch, count):
    """A tree of one map beside a shared one whose other maps are empty (a wave that traces
    maps 0 and 1 of 8): its leaf table once came from an integer division by a tree's count,
    which in the lanes a SIMD packet runs past the end divided by zero and stopped the
    process with SIGFPE; so the build runs in a process of its own first, and then must
    find scipy's photons."""
    import subprocess
    import sys
    run = subprocess.run([sys.executable, "-c", _SHARED_BESIDE_ONE, mi.variant(), str(count)],
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, f"the build stopped the process ({run.returncode}): " \
                                f"{run.stderr[-2000:]}"
    assert run.stdout.strip() == f"built {count}"
    from mi_partpm.kdtree import forest as forest_module
    monkeypatch.setattr(forest_module, "GROUP_PHOTONS", 1000)
    rng = np.random.default_rng(count)
    ids = np.sort(rng.integers(0, 2, count))
    pts = rng.random((count, 3)).astype(np.float32)
    _check_against_scipy(pts, rng.random((300, 3)), 0.1, ids, 8, "shared")


def _check_split_planes(forest, count):
    """Every internal node of a one-map forest: the photons of its left half lie at or below
    its split value along its axis, those of its right half at or above it."""
    points, value, axis = forest.points, forest.split_value, forest.split_axis
    for level in range(forest.depth(0)):
        for k in range(1 << level):
            node = (1 << level) - 1 + k
            first = (k * count) >> level
            stop = ((k + 1) * count) >> level
            median = ((2 * k + 1) * count) >> (level + 1)
            a = int(axis[node])
            assert np.all(points[first:median, a] <= value[node]), (level, k)
            assert np.all(points[median:stop, a] >= value[node]), (level, k)


@pytest.mark.parametrize("count", [5, 37, 1000])
def test_leaves_of_one_photon(count):
    """With leaves of one photon, a node of one photon is split (5 photons: node 2 of level
    2 holds photon 2 alone, its median is its end): its split value must be its own
    photon's coordinate, not the next node's, or the plane would hide the photon."""
    rng = np.random.default_rng(count)
    pts = rng.random((count, 3)).astype(np.float32)
    _check_split_planes(build_forest(pts, leaf_size=1), count)
    _check_against_scipy(pts, np.concatenate([pts, rng.random((200, 3))]), 0.2,
                         leaf_size=1)


@pytest.mark.parametrize("count, leaf", [(1001, 7), (64, 8), (5, 3)])
def test_a_ball_over_everything_tests_every_photon_once(count, leaf):
    """A radius that covers the whole set reaches every leaf: each photon is tested and found
    exactly once, whatever the leaves' sizes (odd ones too: the leaf scan tests photons in
    pairs and must neither skip the last one nor read past a leaf's end)."""
    pts = np.random.default_rng(count).random((count, 3)).astype(np.float32)
    forest = build_forest(pts, leaf_size=leaf)
    _, found, stats = _query_sums(forest, np.ones(count), np.full((3, 3), 0.5), 10.0)
    assert np.all(stats.photons_tested.numpy() == count)
    assert np.all(found == count)


def _check_medians(forest, m, points, ids):
    """Every node of map m's separate tree splits its photons (the caller's ``points`` of
    map m) at their median along their longest axis (ties: x, then y), as NumPy finds them:
    the median is the coordinate of the node's middle photon in the order along that axis."""
    mine = points[ids == m]
    count = mine.shape[0]
    base = int(forest.node_base[m])
    start = int(forest.leaf_start[int(forest.leaf_base[m])])
    tree_points = forest.points[start:start + count]
    assert np.array_equal(np.sort(forest.order[start:start + count]),
                          np.flatnonzero(ids == m))
    for level in range(forest.depth(m)):
        for k in range(1 << level):
            first = (k * count) >> level
            stop = ((k + 1) * count) >> level
            median = ((2 * k + 1) * count) >> (level + 1)
            node = tree_points[first:stop]
            extent = node.max(axis=0) - node.min(axis=0)
            axis = 0 if extent[0] >= max(extent[1], extent[2]) else \
                (1 if extent[1] >= extent[2] else 2)
            got_axis = int(forest.split_axis[base + (1 << level) - 1 + k])
            got_value = forest.split_value[base + (1 << level) - 1 + k]
            assert got_axis == axis, (m, level, k, extent)
            assert got_value == np.sort(node[:, axis])[min(median, stop - 1) - first], \
                (m, level, k)


def test_large_nodes_split_at_their_exact_medians():
    """Nodes of more than 2^16 photons sort their three orders with one prefix sum each, the
    smaller ones two orders with one shared sum (each count in 16 bits of one word): every
    node of trees that go through both, alone in a group and two maps in a group, has the
    axis and median NumPy finds. Photons on a few planes give ties along every axis."""
    rng = np.random.default_rng(7)
    count = 150_000
    pts = rng.random((count, 3)).astype(np.float32)
    pts[: count // 3, 1] = np.round(pts[: count // 3, 1] * 8) / 8
    ids = np.sort(rng.integers(0, 2, count))
    ids[: 140_000] = 0
    forest = build_forest(pts, ids, 2, leaf_size=32)
    assert int(np.bincount(ids)[0]) > 2 << 16
    for m in (0, 1):
        _check_medians(forest, m, pts, ids)
    alone = build_forest(pts, leaf_size=32)
    _check_medians(alone, 0, pts, np.zeros(count, np.int64))


@pytest.mark.parametrize("map_count", [1, 3, 70_000])
def test_presort_orders_by_map_then_coordinate_stably(map_count):
    """The build's radix sort (two 16-bit passes over a float's order-preserving bits, one
    over the map ids) gives NumPy's stable order by (map, value): negative values, equal
    values, -0 before +0, and map counts beyond one pass's 2^16 buckets (Dr.Jit's argsort)."""
    from mi_partpm.kdtree.forest import _sorted_by_map_then
    rng = np.random.default_rng(map_count)
    n = 50_000
    key = (rng.standard_normal(n) * 10).astype(np.float32)
    key[: n // 4] = np.round(key[: n // 4])                  # many ties
    key[n // 4: n // 4 + 50] = -0.0
    key[n // 4 + 50: n // 4 + 100] = 0.0
    key[n // 2: n // 2 + 10] = [-3e38, 3e38, -1e-38, 1e-38, -1e-45, 1e-45, 7, -7, 0, -0.0]
    maps = rng.integers(0, map_count, n).astype(np.uint32)
    got = _sorted_by_map_then(mi.Float(key), mi.UInt32(maps), map_count).numpy()
    # -0 sorts before +0 by its bits, as Dr.Jit's argsort orders them.
    bits = key.view(np.uint32)
    ordinal = np.where(bits >> 31 == 1, ~bits, bits | 0x80000000).astype(np.uint32)
    np.testing.assert_array_equal(got, np.lexsort((ordinal, maps)) if map_count > 1
                                  else np.argsort(ordinal, kind="stable"))


def test_negative_coordinates_split_at_their_exact_medians():
    """Photons on both sides of 0 (a scene centred on the origin): every node's axis and
    median are NumPy's."""
    rng = np.random.default_rng(3)
    pts = (rng.random((20_000, 3)) * 2 - 1).astype(np.float32)
    pts[:2000, 2] = -0.0
    forest = build_forest(pts, leaf_size=8)
    _check_medians(forest, 0, pts, np.zeros(20_000, np.int64))


@pytest.mark.parametrize("layout", ["separate", "shared"])
def test_leaf_boxes_are_the_bounds_of_their_leaves(layout):
    """Every leaf's box (all its maps' runs) is the exact bounding box of its photons; an
    empty leaf's box is empty (+inf, -inf), so no ball reaches it."""
    rng = np.random.default_rng(11)
    pts = rng.random((3000, 3)).astype(np.float32) * np.array([3, 1, 2], np.float32)
    ids = rng.integers(0, 5, 3000)
    ids[ids == 3] = 2                                   # map 3 empty
    f = build_forest(pts, ids, 5, leaf_size=6, layout=layout)
    boxes = f.leaf_boxes.numpy().reshape(-1, 8)
    table = f.leaf_start
    assert boxes.shape[0] == int((f.internal_count + 1).sum())
    for t in range(f.tree_count):
        s, leaves = int(f.tree_map_count[t]), int(f.internal_count[t]) + 1
        for j in range(leaves):
            first = table[f.leaf_base[t] + j * s]
            stop = table[f.leaf_base[t] + (j + 1) * s]
            box = boxes[f.node_base[t] + t + j]
            if stop == first:
                assert np.all(box[:3] == np.inf) and np.all(box[4:7] == -np.inf)
            else:
                run = f.points[first:stop]
                assert np.array_equal(box[:3], run.min(axis=0)), (t, j)
                assert np.array_equal(box[4:7], run.max(axis=0)), (t, j)


def test_queries_that_walk_as_a_group_keep_their_own_balls():
    """Morton-sorted neighbours walk the trees as groups (one ball around the group's balls)
    and still find exactly the photons of their own ball: per-query radii from 0 to large,
    inactive lanes (one of them at NaN) and an infinite radius in the middle of groups,
    checked against scipy and against each lane's own walk. The groups must really walk
    together (their node counts differ from the own walk's on most lanes), and each walk
    tests exactly the photons of the leaves whose bounding box the lane's own ball reaches."""
    rng = np.random.default_rng(12)
    pts = rng.random((20_000, 3)).astype(np.float32)
    pts[:, 2] *= 0.05                                  # photons near a plane, as on a surface
    q = np.c_[rng.random((9000, 2)) * 0.3, np.full(9000, 0.025)].astype(np.float32)
    r = (0.01 + 0.03 * rng.random(9000)).astype(np.float32)
    r[::97] = 0.0
    r[5000] = np.inf
    q[4001] = np.nan
    active = np.ones(9000, bool)
    active[::13] = False
    active[4001] = False                # NaN queries are refused in active lanes
    forest = build_forest(pts)
    w = rng.random(20_000).astype(np.float32)
    wt = mi.Float(w[forest.order])
    p = mi.Point3f(*[mi.Float(q[:, k]) for k in range(3)])

    def query(walk):
        total, stats = radius_query(forest, p, mi.Float(r), lambda i, d2, a, s: dr.gather(
            mi.Float, wt, i, a), active=mi.Bool(active), with_stats=True, walk=walk)
        return total.numpy(), stats.photons_found.numpy(), stats.photons_tested.numpy(), \
            stats.nodes_visited.numpy()
    total, found, tested, nodes = query("group")
    own_total, own_found, own_tested, own_nodes = query("own")

    finite = active & np.isfinite(q).all(1) & np.isfinite(r)
    lo, hi, n_lo, n_hi = _reference(pts, w.astype(np.float64), q[finite].astype(np.float64),
                                    r[finite].astype(np.float64))
    assert np.all(found[finite] >= n_lo) and np.all(found[finite] <= n_hi)
    tol = 1e-5 * np.maximum(hi, 1) + 1e-6
    assert np.all(total[finite] >= lo - tol) and np.all(total[finite] <= hi + tol)
    assert found[5000] == 20_000 and found[4001] == 0 and found[~active].sum() == 0
    assert np.array_equal(own_found, found)
    assert np.allclose(own_total, total, rtol=1e-5, atol=1e-6)
    # The group's ball reaches every leaf a member's own ball reaches, and more; a lane scans
    # only those whose box its own ball reaches, so it tests the photons its own walk tests.
    assert np.array_equal(tested, own_tested) and np.mean(nodes != own_nodes) > 0.5

    # The own walk tests the photons of the leaves whose box its ball reaches (up to float
    # rounding at the box's surface), no more.
    boxes = forest.leaf_boxes.numpy().reshape(-1, 8)
    sizes = np.diff(forest.leaf_start.astype(np.int64))
    for lane in np.flatnonzero(finite & (r < 1))[::50]:
        gap = np.maximum(np.maximum(boxes[:, :3] - q[lane], q[lane] - boxes[:, 4:7]), 0)
        d = np.sqrt((gap.astype(np.float64) ** 2).sum(1))
        lo = sizes[d <= r[lane] * (1 - 1e-5)].sum()
        hi = sizes[d <= r[lane] * (1 + 1e-5)].sum()
        assert lo <= own_tested[lane] <= hi, lane


def test_a_group_ball_holds_every_member_ball_in_float32():
    """The walk of a group passes a plane or a box wherever a member's own walk would, also
    after float32 rounding: for every member and axis, centre - R <= p - r and centre + R >=
    p + r as float32 computes them (the group radius is widened by GROUP_MARGIN; without it,
    a sum such as 1 + (1 + 2^-23) rounds down to 2 and a photon at the edge is missed)."""
    from mi_partpm.kdtree import radius as radius_module
    rng = np.random.default_rng(13)
    count = 80_000
    # Groups along a line (where |p - centre| is one coordinate's difference and every
    # rounding of the group's radius shows), radii of one scale.
    size = radius_module.group_lanes(mi.Float(0.0))
    q = np.repeat(rng.random((count // size, 3)) * 8 - 4, size, axis=0)
    q[:, 0] += rng.random(count) * 2 - 1
    q = q.astype(np.float32)
    r = (0.75 + 0.5 * rng.random(count)).astype(np.float32)
    centre, radius = radius_module.group_balls(
        mi.Point3f(*[mi.Float(q[:, k]) for k in range(3)]), mi.Float(r), mi.Bool(True), count)
    c = np.stack([centre.x.numpy(), centre.y.numpy(), centre.z.numpy()], axis=1)
    big = radius.numpy()
    grouped = big != r
    assert grouped.mean() > 0.9
    with np.errstate(over="ignore"):
        assert np.all((c - big[:, None] <= q - r[:, None])[grouped])
        assert np.all((c + big[:, None] >= q + r[:, None])[grouped])


def test_groups_are_one_simd_packet_of_dr_jit():
    """On the LLVM backend a group is one SIMD packet: packet_lanes() applies Dr.Jit's rule
    to the host's CPU flags, and gives the width of the vectors in the IR of a kernel Dr.Jit
    compiles here (16 lanes of AVX-512 would otherwise hold two groups of 8 that walk two
    paths, 12% slower on the room workload)."""
    import re
    assert packet_lanes(["sse4_2"]) == 4
    assert packet_lanes(["sse4_2", "avx", "avx2"]) == 8
    assert packet_lanes(["avx", "avx2", "avx512f", "avx512vl"]) == 16
    if mi.variant().startswith("cuda"):
        assert group_lanes(dr.arange(mi.Float, 4)) == 32       # a warp; no packets to read
        return
    flag = dr.flag(dr.JitFlag.KernelHistory)
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        dr.kernel_history()
        x = dr.arange(mi.Float, 1000) * dr.opaque(mi.Float, 3.0) + 0.25
        dr.eval(x)
        ir = [str(k["ir"].read() if hasattr(k["ir"], "read") else k["ir"])
              for k in dr.kernel_history() if "ir" in k]
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, flag)
    assert ir, "no LLVM kernel recorded"
    widths = {int(w) for w in re.findall(r"<(\d+) x float>", ir[-1])}
    assert widths == {packet_lanes()}, widths
    assert group_lanes(x) == packet_lanes()


@pytest.mark.parametrize("walk", ["group", "own"])
def test_contributions_get_the_payload_read_with_the_position(walk):
    """With ``with_payload`` the queries hand each photon's 32-bit payload (the direction code
    of a photon map) to the contribution, read by the distance test's load: the sums of the
    payloads equal those of payloads gathered by index, for the fixed-radius and the kNN
    query, in both walks and over a range of maps."""
    rng = np.random.default_rng(31)
    n = 20_000
    pts = rng.random((n, 3)).astype(np.float32)
    pts[:, 2] *= 0.05
    payload = (rng.integers(0, 1 << 20, n)).astype(np.uint32)
    forest = build_forest(pts, rng.integers(0, 3, n), 3, payload=mi.UInt32(payload),
                          layout="shared")
    by_index = mi.Float(payload[forest.order].astype(np.float32))
    q = np.c_[rng.random((6000, 2)), np.full(6000, 0.025)].astype(np.float32)
    p = mi.Point3f(*[mi.Float(q[:, k]) for k in range(3)])
    with_payload = lambda i, d2, a, s, code: mi.Float(code)
    gathered = lambda i, d2, a, s: dr.gather(mi.Float, by_index, i, a)
    for maps in (None, (1, 3)):
        a = radius_query(forest, p, 0.04, with_payload, maps=maps, walk=walk, with_payload=True)
        b = radius_query(forest, p, 0.04, gathered, maps=maps, walk=walk)
        assert np.array_equal(a.numpy(), b.numpy()) and b.numpy().max() > 0
        a = knn_query(forest, p, 20, with_payload, maps=maps, walk=walk, with_payload=True)
        b = knn_query(forest, p, 20, gathered, maps=maps, walk=walk)
        assert np.array_equal(a.total.numpy(), b.total.numpy()) and b.total.numpy().max() > 0


def test_photon_maps_read_each_photons_power_and_direction():
    """The maps hold every photon's power packed (RGB and one unused float: one 16-byte load)
    and its direction code in its record: read back by tree-order index they are the traced
    photon's own, and a photon costs 32 bytes (16 of record, 16 of power)."""
    from mi_partpm.photonmap import POWER_FLOATS, power_floats, record_bytes
    from mi_partpm.photons import decode_direction
    from mi_partpm.scenes import load_scene
    traced = trace_photons(load_scene("cornell_box"), 20_000, 3, 4)
    maps = build_photon_maps(traced)
    order = maps.forest.order
    index = dr.arange(mi.UInt32, len(traced))
    power = np.array(maps.photon_power(index))
    assert np.array_equal(power, np.array(traced.flux)[:, order])
    code = traced.code.numpy()[order]
    np.testing.assert_array_equal(np.array(maps.photon_direction(index)),
                                  np.array(decode_direction(mi.UInt32(code))))
    assert POWER_FLOATS == 4
    assert record_bytes() == 16 + 4 * power_floats() and record_bytes(True) == record_bytes() + 4
    if power_floats() == POWER_FLOATS:                  # RGB: three channels and the pad
        assert record_bytes() == 32
        assert maps.power.numpy().reshape(-1, POWER_FLOATS)[:, 3].max() == 0


@pytest.mark.parametrize("kind", ["radius", "knn"])
def test_a_contribution_of_another_type_names_result_type(kind):
    """A contribution that returns a colour for a scalar total is a TypeError that says to
    pass result_type; Dr.Jit's loop said only that its state changed type."""
    from mi_partpm.kdtree.radius import ResultTypeError
    forest = build_forest(np.random.default_rng(0).random((200, 3)))
    colour = lambda i, d2, a, s: mi.Color3f(1.0)      # noqa: E731
    with pytest.raises(ResultTypeError, match=r"contribution returned Color3f, which "
                                              r"result_type = Float cannot hold: pass "
                                              r"result_type=Color3f"):
        if kind == "radius":
            radius_query(forest, np.zeros((3, 3)), 0.2, colour)
        else:
            knn_query(forest, np.zeros((3, 3)), 4, colour)
    # Given result_type, the same contribution sums colours.
    total = radius_query(forest, np.zeros((3, 3)), 0.2, colour, result_type=mi.Color3f)
    assert isinstance(total, mi.Color3f)


def test_radius_neighbours_answers_as_query_ball_point(monkeypatch):
    """The NumPy front end of the radius query gives scipy's query_ball_point: the indices
    of every query's photons (sorted) and, with return_length, their counts; over unsorted
    queries (more than sort them), per-query radii, several maps and a range of maps."""
    from mi_partpm.kdtree import radius_neighbours
    rng = np.random.default_rng(5)
    pts, q = rng.random((5000, 3)), rng.random((3000, 3))
    r = rng.uniform(0.02, 0.08, 3000)
    maps = rng.integers(0, 4, 5000)
    forest = build_forest(pts, maps, 4)
    tree = cKDTree(pts)
    lists = radius_neighbours(forest, q, r)
    ref = tree.query_ball_point(q, r)
    assert len(lists) == 3000 and sum(len(a) for a in lists) > 5000
    differ = sum(not np.array_equal(a, np.sort(b)) for a, b in zip(lists, ref))
    assert differ <= 3, differ                        # float32 rounding at the sphere
    lengths = radius_neighbours(forest, q, r, return_length=True)
    assert np.abs(lengths - tree.query_ball_point(q, r, return_length=True)).sum() <= 3
    some = radius_neighbours(forest, q[:50], 0.1, maps=(1, 3))
    keep = np.isin(maps, [1, 2])
    sub = cKDTree(pts[keep])
    for got, want in zip(some, sub.query_ball_point(q[:50], 0.1)):
        np.testing.assert_array_equal(got, np.sort(np.nonzero(keep)[0][want]))
    # A photon at exactly r (in float32) is in the list and in the count alike (the two
    # walks squared r apart, in float64 and in float32, and disagreed at 0.1).
    at_r = build_forest(np.array([[0.1, 0, 0], [0.7, 0.7, 0.7]], np.float32))
    for r_at in (0.1, np.float32(0.1), 0.3):
        lists_at = radius_neighbours(at_r, np.zeros((1, 3)), r_at)
        assert [len(a) for a in lists_at] == radius_neighbours(
            at_r, np.zeros((1, 3)), r_at, return_length=True).tolist() == [1]
    assert radius_neighbours(forest, np.zeros((0, 3)), 0.1) == []
    assert [len(a) for a in radius_neighbours(forest, q[:3], 0)] == [0, 0, 0]
    # A query that finds every photon: the lists are written by a second walk, not
    # gathered as the k nearest (which refused more than 16383 and took seconds for 1000).
    every = radius_neighbours(forest, q[:2], 10.0)
    assert all(np.array_equal(a, np.arange(5000)) for a in every)
    # Many photons on few spots (ties everywhere), as scipy lists them.
    spots = rng.integers(0, 3, (20000, 3)).astype(float)
    near = rng.random((20, 3)) * 2
    got = radius_neighbours(build_forest(spots), near, 0.9)
    want = cKDTree(spots).query_ball_point(near, 0.9)
    assert max(len(a) for a in got) > 2000
    assert all(np.array_equal(a, np.sort(b)) for a, b in zip(got, want))
    # More indices in all than one 32-bit index array holds: refused before the second walk,
    # pointing to the counts (here with the bound lowered).
    from mi_partpm.kdtree import radius as radius_module
    monkeypatch.setattr(radius_module, "MAX_INDICES", 9999)
    with pytest.raises(ValueError, match=r"the queries find 10,000 photons in all, more than "
                                         r"the 9,999 .* return_length=True"):
        radius_neighbours(forest, q[:2], 10.0)


def test_a_callback_that_cannot_be_called_as_the_query_calls_it_is_named():
    """A contribution that is not a function, or takes other arguments than the walk
    gives, was a Dr.Jit loop error ("encountered an exception (see above)") whose cause lay
    two exceptions down; now it is a TypeError naming the callback and its arguments."""
    from mi_partpm.kdtree import CallbackError
    forest = build_forest(np.random.default_rng(2).random((300, 3)))
    q = np.full((1, 3), 0.5)
    with pytest.raises(CallbackError, match=r"contribution must be a function \(a callback\), "
                                            r"got NoneType"):
        radius_query(forest, q, 0.1, None)
    with pytest.raises(CallbackError, match=r"accept must be a function"):
        radius_query(forest, q, 0.1, lambda i, d2, a, s: mi.Float(1), accept=3)
    # Refused before anything is walked, also where nothing would be (an empty forest).
    empty = build_forest(np.zeros((0, 3)))
    with pytest.raises(CallbackError, match=r"accept must be a function"):
        knn_query(empty, q, 3, accept=3)
    with pytest.raises(CallbackError, match=r"contribution must be a function"):
        knn_query(empty, q, 3, "sum")
    for call, args in ((lambda: radius_query(forest, q, 0.1, lambda i, d2: mi.Float(1)),
                        r"contribution is called with 4 arguments \(index, dist2, active, "
                        r"state\), and cannot take them"),
                       (lambda: radius_query(forest, q, 0.1, lambda i, d2, a, s: mi.Float(1),
                                             with_payload=True),
                        r"contribution is called with 5 arguments \(index, dist2, active, "
                        r"state, payload\)"),
                       (lambda: knn_query(forest, q, 3, lambda i, d2, a, s, x: mi.Float(1)),
                        r"contribution is called with 4 arguments"),
                       (lambda: knn_query(forest, q, 3, lambda i, d2, a, s: mi.Float(1),
                                          with_payload=True),
                        r"contribution is called with 5 arguments"),
                       (lambda: radius_query(forest, q, 0.1, lambda i, d2, a, s: mi.Float(1),
                                             accept=lambda i: mi.Bool(True)),
                        r"accept is called with 3 arguments \(index, active, state\)")):
        with pytest.raises(CallbackError, match=args):
            call()


@pytest.mark.parametrize("queries", [100, 5000])
def test_knn_leaves_the_radii_in_the_callers_state_at_any_query_count(queries):
    """The contribution's state holds the final squared radii in ``radius2``, and so does
    the object passed in afterwards: it did below 4096 queries (walked in the given order)
    but kept its zeros above (sorted, a copy)."""
    class State:
        DRJIT_STRUCT = {"radius2": mi.Float}

        def __init__(self, radius2=None):
            self.radius2 = radius2
    rng = np.random.default_rng(3)
    forest = build_forest(rng.random((2000, 3)))
    q = rng.random((queries, 3))
    state = State(dr.zeros(mi.Float, queries))
    res = knn_query(forest, q, 4, lambda i, d2, a, s: d2 / s.radius2, state=state)
    kth = cKDTree(forest.points).query(q, [4])[0][:, 0] ** 2
    np.testing.assert_allclose(res.radius2.numpy(), kth, rtol=1e-5)
    np.testing.assert_array_equal(state.radius2.numpy(), res.radius2.numpy())
    total = res.total.numpy()                        # sum of d2 / r2 over 4: in (0, 4]
    assert np.all((total > 0) & (total <= 4 + 1e-5))
    # An empty forest: the radii are the cap's, in the state too.
    state = State(dr.zeros(mi.Float, queries))
    res = knn_query(build_forest(np.zeros((0, 3))), q, 4, max_radius=0.5, state=state)
    assert np.all(state.radius2.numpy() == 0.25) and np.all(res.radius2.numpy() == 0.25)


def test_morton_codes_take_what_morton_order_takes():
    from mi_partpm.kdtree import morton_codes
    pts = np.random.default_rng(4).random((50, 3))
    codes = morton_codes(pts).numpy()
    assert np.array_equal(codes, morton_codes(mi.Point3f(*pts.T.astype(np.float32))).numpy())
    assert np.array_equal(np.argsort(codes, kind="stable"), morton_order(pts))


def test_morton_codes_over_a_given_box_equal_those_over_the_points_own():
    """A box known beforehand (the bench's sort key gives the scene's) spares the six
    reductions and, being the points' own box, gives the same codes bit for bit; a box
    four times as wide puts the points in the middle of its grid, short of its far corner:
    a lower largest code."""
    from mi_partpm.kdtree import morton_codes
    pts = (np.random.default_rng(5).random((20_000, 3)) * 5 - 2).astype(np.float32)
    own = mi.ScalarBoundingBox3f(mi.ScalarPoint3f(pts.min(0)), mi.ScalarPoint3f(pts.max(0)))
    assert np.array_equal(morton_codes(pts).numpy(), morton_codes(pts, own).numpy())
    wide = mi.ScalarBoundingBox3f(mi.ScalarPoint3f(-10, -10, -10), mi.ScalarPoint3f(10, 10, 10))
    assert morton_codes(pts, wide).numpy().max() < morton_codes(pts).numpy().max()
