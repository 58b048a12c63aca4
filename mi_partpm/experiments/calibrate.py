"""The calibration experiment: per-map times and traversal counts at several leaf sizes and
radii, so that the costs per node, per photon tested and per photon found can be told apart.

One speedup run (:mod:`.speedup`) moves nodes, tests and found photons together as n grows:
fitted to it, the costs are nearly collinear. Here the same photons and hit points are
measured on a grid of (leaf size, radius): small leaves visit many nodes per photon tested,
large ones test many photons per node, and the radius moves the photons found against both
(found grows as r^2, tests per found shrink). Each (leaf size, radius) is a *set*: for every
n, every map's counts and its measured time, saved as a workloads directory with its leaf
size and radius (:func:`hwsim.workload.save_workload_sets`, format in hwsim/WORKLOAD.md).
:mod:`hwsim.calibrate` then fits the costs to every map of every set and writes them as the
file hwsim's ``[pe] costs = "fitted"`` runs on.

**What is timed** is what hwsim models and what the speedup experiment times: one map
answering every hit point's query (:func:`.speedup.time_map`), the median over ``repeats``.
The timed runs of all sets are interleaved: every repeat runs every (set, n, map) once, in a
seeded random order, so that a burst of load from other processes on the machine spreads
over all sets instead of biasing the one measured at that moment. By default Dr.Jit runs
these kernels on one thread (``threads``): the fitted costs are then one thread's, with no
assumption about how threads scale, and on a shared 2-core machine one thread is the
steadier clock (a map that took 123 ms +- 25% on two threads took 55 ms +- 6% on one while
another process kept a core busy). The tracing and the builds use every thread.

With several scenes (``partpm calibrate A B``), their maps are timed interleaved in one run
and each scene's files go into ``out_dir/SCENE/``, with a ``calibration.json`` of the
cross-scene check in ``out_dir``. For one scene, writes into ``out_dir``: ``sets/``
(``sets.json`` and one workloads folder per set),
``calibration.json`` (settings, per-set summaries, the fit, its design and, given
``check_dir``, the cross-scene check both ways), ``fitted_costs.toml`` (the costs file) and
``hwsim_fitted.toml`` (an hwsim config that runs on them).
"""
from __future__ import annotations

import json
import math
import time
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from hwsim.calibrate import (calibrate, cross_check, format_check, format_cross, format_fit,
                             write_costs)
from hwsim.workload import (SETS_FILE, WorkloadSet, load_workload_sets, save_workload_sets,
                            set_name)
from .provenance import code_version, l1_data_bytes, simd_lanes

# The measuring functions import Mitsuba and Dr.Jit (and need a variant) when they run:
# refitting and formatting need neither.

__all__ = ["run_calibration", "run_calibrations", "scene_dir_name", "refit", "format_calibration", "format_readme_table",
           "check_grid", "DEFAULTS"]

#: The default grid and size: 3 leaf sizes x 3 radii, n = 1..32, 240 x 240 hit points.
DEFAULTS = {"leaf_sizes": (8, 32, 128), "radius_fractions": (0.025, 0.05, 0.1),
            "maps": (1, 2, 4, 8, 16, 32), "resolution": (240, 240), "repeats": 3,
            "threads": 1}


def check_grid(leaf_sizes, radius_fractions):
    """The grid as sorted tuples; ValueError unless the leaf sizes are distinct integers
    >= 1 and the radius fractions distinct numbers in (0, 1]."""
    leaves = [int(v) for v in leaf_sizes] if all(
        isinstance(v, (int, np.integer)) and not isinstance(v, bool) for v in leaf_sizes) else []
    if not leaves or min(leaves) < 1 or len(set(leaves)) != len(leaves):
        raise ValueError(f"--leaf-sizes must be distinct integers >= 1, got "
                         f"{list(leaf_sizes)}")
    fracs = [float(v) for v in radius_fractions]
    if not fracs or not all(math.isfinite(f) and 0 < f <= 1 for f in fracs) \
            or len(set(fracs)) != len(fracs):
        raise ValueError(f"--radius-fractions must be distinct numbers in (0, 1], got "
                         f"{list(radius_fractions)}")
    return tuple(sorted(leaves)), tuple(sorted(fracs))


def _sets_dir(path) -> Path:
    """The sets directory of a calibration run's ``out_dir`` (or that directory itself)."""
    p = Path(path)
    return p / "sets" if (p / "sets" / SETS_FILE).is_file() else p


def run_calibration(scene_name: str, out_dir, leaf_sizes: Sequence[int] = (8, 32, 128),
                    radius_fractions: Sequence[float] = (0.025, 0.05, 0.1),
                    maps_list: Sequence[int] = (1, 2, 4, 8, 16, 32), photons: int = 100_000,
                    resolution=(240, 240), spp: int = 1, repeats: int = 3,
                    threads: Optional[int] = 1, seed: int = 0,
                    data_dir: Optional[str] = None, check_dir=None,
                    progress=print) -> dict:
    """Measure one scene's sets, fit the costs, write the files into ``out_dir`` (see the
    module's text).

    ``threads``: Dr.Jit threads for the timed kernels (None: Dr.Jit's default).
    ``check_dir``: another scene's calibration (its ``out_dir`` or ``sets/``), measured
    earlier: the fit is checked on it and its own fit on this one."""
    return run_calibrations([scene_name], out_dir, leaf_sizes, radius_fractions, maps_list,
                            [photons], resolution, spp, repeats, threads, seed, data_dir,
                            check_dir, progress)


def scene_dir_name(scene_name: str) -> str:
    """The folder of a scene in a several-scene run: a built-in name, or an XML file's
    stem."""
    return Path(scene_name).stem if scene_name.lower().endswith(".xml") else scene_name


def run_calibrations(scene_names: Sequence[str], out_dir,
                     leaf_sizes: Sequence[int] = (8, 32, 128),
                     radius_fractions: Sequence[float] = (0.025, 0.05, 0.1),
                     maps_list: Sequence[int] = (1, 2, 4, 8, 16, 32),
                     photons: Sequence[int] = (100_000,), resolution=(240, 240), spp: int = 1,
                     repeats: int = 3, threads: Optional[int] = 1, seed: int = 0,
                     data_dir: Optional[str] = None, check_dir=None,
                     progress=print) -> dict:
    """Measure the sets of one or more scenes in one run, fit each, write the files.

    With one scene the files go into ``out_dir``. With several, each scene's go into
    ``out_dir/SCENE/``, every scene's timed runs are interleaved with the others' (one
    random order per repeat over all scenes' maps), each scene's fit is checked against the
    next scene's maps and that one's fit against its own (both ways; the last scene is
    checked against the first), and ``out_dir/calibration.json`` holds the first scene's
    check. Timed in one
    run, both scenes meet the same state of the machine: timed an hour apart, the same
    scene's costs moved by about 10% here (a shared 2-core machine), as much as the
    difference the check is meant to find. ``photons``: one count for all scenes or one
    per scene."""
    import drjit as dr

    from .speedup import _setup, build_maps, check_maps
    from ..photonmap import fixed_radius
    names = list(scene_names)
    if not names:
        raise ValueError("calibrate needs at least one SCENE")
    from ..scenes import scene_path
    if len({scene_path(n).resolve() for n in names}) != len(names):
        raise ValueError(f"calibrate's scenes must be distinct, got {names}")
    folders = [scene_dir_name(n) for n in names]
    if len(set(folders)) != len(names):
        same = sorted({f for f in folders if folders.count(f) > 1})
        clash = [n for n in names if scene_dir_name(n) in same]
        raise ValueError(f"calibrate writes each scene into a folder of --out named after it "
                         f"({', '.join(same)}), and {', '.join(clash)} would share one: give "
                         f"the scene files different names")
    counts_ = [int(v) for v in photons]
    if len(counts_) == 1:
        counts_ *= len(names)
    if len(counts_) != len(names):
        raise ValueError(f"--photons must give one count or one per scene ({len(names)}), "
                         f"got {len(counts_)}")
    if len(names) > 1 and check_dir is not None:
        raise ValueError("--check compares one scene with an earlier run: with several "
                         "scenes, each already predicts the others")
    leaves, fracs = check_grid(leaf_sizes, radius_fractions)
    checked = [check_maps(maps_list, n, repeats) for n in counts_]
    maps_list, lcms = checked[0][0], [lcm for _, lcm in checked]
    if threads is not None and (not isinstance(threads, int) or threads < 1):
        raise ValueError(f"--threads must be an integer >= 1, got {threads!r}")
    other = load_workload_sets(_sets_dir(check_dir)) if check_dir is not None else None
    say = progress or (lambda *a: None)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    runs = []
    for name, n_photons, lcm in zip(names, counts_, lcms):
        kept = len(leaves) * len(maps_list)
        s = _setup(name, n_photons, lcm, resolution, spp, fracs[0], seed, data_dir, say, kept,
                   f", or fewer --leaf-sizes or --maps (a forest is kept for each pair: "
                   f"{len(leaves)} x {len(maps_list)} here)" if kept > 1 else "")
        radii = {f: fixed_radius(s.scene, None, f) for f in fracs}
        say(f"building {len(leaves)} x {len(maps_list)} forests of {name} (leaf sizes "
            f"{', '.join(map(str, leaves))}; n = {', '.join(map(str, maps_list))}) ...")
        forests = {(leaf, n): build_maps(s, n, leaf) for leaf in leaves for n in maps_list}
        runs.append(_Run(name, n_photons, s, radii, forests))
    previous = dr.thread_count()
    if threads is not None:
        dr.set_thread_count(threads)
    try:
        for run in runs:
            run.counts = _count(run.setup, run.forests, run.radii, maps_list, say)
        _time(runs, repeats, seed, say)
    finally:
        dr.set_thread_count(previous)
    used_threads = threads if threads is not None else previous
    order = ("interleaved: every repeat times every (set, n, map) once, in a seeded random "
             "order" + (f", over the maps of {len(runs)} scenes" if len(runs) > 1 else ""))
    made = [_sets_of(run, leaves, fracs, maps_list, resolution, spp, repeats, used_threads,
                     seed, order) for run in runs]
    # Each scene checked against the next: one cross-check per pair, read both ways.
    checks = {}
    if len(runs) > 1:
        for i in range(len(runs)):
            j = (i + 1) % len(runs)
            if (j, i) in checks:
                c = checks[j, i]
                checks[i, j] = {**c, "scenes": c["scenes"][::-1],
                                "directions": c["directions"][::-1]}
            else:
                checks[i, j] = cross_check(made[i][0], made[j][0], runs[i].name, runs[j].name)
    results = []
    for i, (run, (sets, settings)) in enumerate(zip(runs, made)):
        where = out if len(runs) == 1 else out / scene_dir_name(run.name)
        where.mkdir(parents=True, exist_ok=True)
        save_workload_sets(where / "sets", sets, scene=run.name, settings=settings)
        result = {"scene": run.name, "code": code_version(), "settings": settings,
                  "photons_stored": len(run.setup.traced), "sets": _summaries(sets)}
        check = checks.get((i, (i + 1) % len(runs)))
        results.append(_fit_and_write(where, result, sets, other, say, check))
    if len(runs) == 1:
        return results[0]
    combined = {"scenes": names, "code": code_version(),
                "dirs": {r["scene"]: scene_dir_name(r["scene"]) for r in results},
                "runs": results, "check": results[0]["check"], "settings": made[0][1]}
    (out / "calibration.json").write_text(json.dumps(combined, indent=2) + "\n")
    return combined


class _Run:
    """One scene of a calibration run: its setup, radii, forests and, once measured, its
    counts and times."""

    def __init__(self, name, photons, setup, radii, forests):
        self.name, self.photons, self.setup = name, photons, setup
        self.radii, self.forests = radii, forests
        self.counts, self.times = None, None


def _sets_of(run: _Run, leaves, fracs, maps_list, resolution, spp, repeats, threads, seed,
             order):
    """The scene's workload sets and the settings recorded with them."""
    from .speedup import map_workloads
    lanes, l1 = simd_lanes(), l1_data_bytes()
    s = run.setup
    sets = []
    for leaf in leaves:
        for f in fracs:
            loads = {n: map_workloads(n, run.forests[leaf, n], run.times[leaf, f, n],
                                      run.counts[leaf, f, n]) for n in maps_list}
            sets.append(WorkloadSet(set_name(leaf, f), {
                "leaf_size": leaf, "radius": run.radii[f], "radius_fraction": f,
                "photons_emitted": run.photons, "photons_stored": len(s.traced),
                "threads": threads, "lanes": lanes, "l1_bytes": l1}, loads))
    settings = {"photons": run.photons, "resolution": list(resolution), "spp": spp,
                "repeats": repeats, "threads": threads, "seed": seed,
                "lanes": lanes, "l1_bytes": l1, "maps": list(maps_list),
                "leaf_sizes": list(leaves), "radius_fractions": list(fracs),
                "queries": int(s.queries), "order": order}
    return sets, settings


def _count(s, forests, radii, maps_list, say) -> dict:
    """Counts of every (leaf, radius fraction, n); the n per-map estimates must add up to
    the first n's (eq. 2; :class:`~.speedup.GatherError` otherwise)."""
    from .speedup import GatherError, _check_gather, map_counts
    out, reference = {}, {}
    for (leaf, n), maps in forests.items():
        for f, r in radii.items():
            c, gathered = map_counts(s, maps, r)
            out[leaf, f, n] = c
            if n == maps_list[0]:
                reference[leaf, f] = gathered
                if c[2].any() and not np.any(gathered):
                    raise GatherError(f"leaf size {leaf}, r = {r:.4g}: the n = {n} estimate "
                                      f"is 0 at every hit point although its queries found "
                                      f"{int(c[2].sum())} photons")
            else:
                _check_gather(n, maps_list[0], gathered, reference[leaf, f],
                              c[2].sum(axis=0))
        say(f"counted leaf size {leaf}, n = {n}")
    return out


def _time(runs, repeats, seed, say):
    """Set each run's ``times``: (repeats,) seconds per map of every (leaf, radius fraction,
    n). Every repeat times every (scene, set, n, map) once, in a seeded random order."""
    from .speedup import time_map
    jobs = [(k, leaf, f, n, m) for k, run in enumerate(runs) for (leaf, n) in run.forests
            for f in run.radii for m in range(n)]
    for run in runs:                                  # warm-up: compile each radius' kernel
        for (leaf, n), maps in run.forests.items():
            for r in run.radii.values():
                time_map(run.setup, maps, 0, r)
        run.times = {(leaf, f, n): np.zeros((n, repeats)) for (leaf, n) in run.forests
                     for f in run.radii}
    rng = np.random.default_rng(seed)
    start = time.perf_counter()
    for rep in range(repeats):
        for i in rng.permutation(len(jobs)):
            k, leaf, f, n, m = jobs[i]
            run = runs[k]
            run.times[leaf, f, n][m, rep] = time_map(run.setup, run.forests[leaf, n], m,
                                                     run.radii[f])
        spent = time.perf_counter() - start
        say(f"repeat {rep + 1}/{repeats}: {len(jobs)} map runs timed, {spent:.0f} s so far"
            + (f", about {spent / (rep + 1) * (repeats - rep - 1):.0f} s to go"
               if rep + 1 < repeats else ""))


def _summaries(sets) -> list:
    """Per set and n: the median map time and the mean counts per query."""
    out = []
    for st in sets:
        rows = []
        for n, w in sorted(st.loads.items()):
            rows.append({"n": n, "map_ms": float(np.median(np.median(w.map_seconds, axis=1)))
                         * 1e3, "nodes": float(w.nodes_visited.mean()),
                         "tested": float(w.photons_tested.mean()),
                         "found": float(w.photons_found.mean())})
        out.append({"name": st.name, "leaf_size": st.leaf_size, "radius": st.radius,
                    "radius_fraction": st.meta.get("radius_fraction"), "rows": rows})
    return out


def _fit_and_write(out: Path, result: dict, sets, other, say, check=None) -> dict:
    """Fit ``sets``, write the costs, the hwsim config and ``calibration.json`` into ``out``;
    the cross-scene check is ``check`` if given, else made against ``other`` (index, sets)
    if given."""
    scene = result["scene"]
    say(f"fitting {sum(w.n for st in sets for w in st.loads.values())} maps of {len(sets)} "
        f"sets ...")
    f = calibrate(sets)
    result["fit"] = f.as_dict()
    threads = result["settings"].get("threads") or 1
    write_costs(out / "fitted_costs.toml", f, scene=scene, threads=threads,
                source=f"partpm calibrate {scene}: {len(sets)} sets, {f.rows} maps")
    (out / "hwsim_fitted.toml").write_text(
        "# hwsim on the costs fitted to this calibration: partpm hwsim WORKLOAD_DIR --config "
        "this.toml --out DIR\n[pe]\ncosts = \"fitted\"\nfitted_costs = \"fitted_costs.toml\"\n")
    result["check"] = check
    if check is None and other is not None:
        other_index, other_sets = other
        result["check"] = cross_check(sets, other_sets, scene,
                                      other_index.get("scene", "other"))
    (out / "calibration.json").write_text(json.dumps(result, indent=2) + "\n")
    return result


def refit(out_dir, check_dir=None, progress=print) -> dict:
    """Fit again the sets an earlier :func:`run_calibration` wrote into ``out_dir`` (no
    measuring), checking on ``check_dir``; rewrite its fit, costs file and check. A
    several-scene run's ``out_dir`` is refitted scene by scene, each checked on the next."""
    out = Path(out_dir)
    saved = out / "calibration.json"
    result = json.loads(saved.read_text()) if saved.is_file() else {}
    if "dirs" in result:
        if check_dir is not None:
            raise ValueError("--check compares one scene with an earlier run: this run's "
                             "scenes already predict each other")
        dirs = [out / d for d in result["dirs"].values()]
        results = [refit(d, dirs[(i + 1) % len(dirs)], progress)
                   for i, d in enumerate(dirs)]
        result.update(code=code_version(), runs=results, check=results[0]["check"])
        saved.write_text(json.dumps(result, indent=2) + "\n")
        return result
    index, sets = load_workload_sets(_sets_dir(out))
    result.update(scene=index.get("scene", ""), settings=index.get("settings", {}),
                  sets=_summaries(sets))
    other = load_workload_sets(_sets_dir(check_dir)) if check_dir is not None else None
    return _fit_and_write(out, result, sets, other, progress or (lambda *a: None))


def format_calibration(result) -> str:
    """The run as text: per set the median map time per n, the fit and, if checked, the
    cross-scene check (once for a several-scene run)."""
    if "runs" in result:
        parts = [format_calibration({**r, "check": None}) for r in result["runs"]]
        return "\n".join(parts + ([format_cross(result["check"])] if result["check"] else []))
    st = result["settings"]
    lines = [f"{result['scene']}: {st.get('queries', '?')} hit points, n = "
             f"{', '.join(map(str, st.get('maps', [])))}, {st.get('repeats', '?')} repeats "
             f"(medians), {st.get('threads', '?')} thread(s); one map's time (ms) per set"]
    ns = [r["n"] for r in result["sets"][0]["rows"]] if result["sets"] else []
    lines.append(f"{'set':<18} " + " ".join(f"{'n=' + str(n):>8}" for n in ns))
    for s in result["sets"]:
        lines.append(f"{s['name']:<18} " + " ".join(f"{r['map_ms']:8.1f}" for r in s["rows"]))
    lines += format_fit(result["fit"], result["scene"])
    lines += format_check(result["fit"]["self"])
    if result.get("check"):
        lines.append(format_cross(result["check"]))
    return "\n".join(lines)


def format_readme_table(result) -> str:
    """The README's calibration table from a ``calibration.json`` with a cross-scene check
    (``partpm calibrate A B``'s, or ``partpm calibrate B --check A``'s): per direction the fitted costs, the fit on its own
    maps and the prediction of the other scene's, and whether the goal is met."""
    cross = result.get("check")
    if not cross:
        raise ValueError("this calibration has no cross-scene check: run 'partpm calibrate "
                         "SCENE OTHER_SCENE' (or 'SCENE --check OTHER_DIR')")
    head = ("| fitted on | ns / node | ns / test | ns / found | ms / map run | ns / node, per "
            "doubling beyond L1 | ns / test, per doubling | R^2 on itself | largest error | "
            "predicts | R^2 | largest error | median error | goal met |")
    lines = [head, "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | --- | ---: "
                   "| ---: | ---: | --- |"]
    for d in cross["directions"]:
        f, p = d["fit"], d["prediction"]
        c = f["costs"]

        def shown(k, scale, digits):                 # a cost fitted to 0 is flagged
            return f"{c[k] * scale:.{digits}f}" + (" (0!)" if k in f["zero"] else "")
        cost = [shown(k, 1e9, 2) for k in ("per_node", "per_test", "per_found")]
        cache = [shown(k, 1e9, 3) if k in c else "not modelled"
                 for k in ("per_node_cache", "per_test_cache")]
        lines.append(
            f"| {d['fit_on']} | {' | '.join(cost)} | {shown('fixed', 1e3, 1)} | "
            f"{' | '.join(cache)} | "
            f"{f['self']['r2']:.3f} | {f['self']['max_rel_error'] * 100:.0f}% | {d['predicts']} "
            f"| {p['r2']:.3f} | {p['max_rel_error'] * 100:.0f}% | "
            f"{p['median_rel_error'] * 100:.1f}% | {'yes' if d['goal']['met'] else 'no'} |")
    return "\n".join(lines)
