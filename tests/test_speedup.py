"""The speedup experiment: per-map estimates gather to the one-map estimate, workloads load."""
import json
import re
from pathlib import Path

import numpy as np
import pytest

from hwsim.workload import load_workloads
from mi_partpm.cli import main
from mi_partpm.experiments import speedup
from mi_partpm.kdtree import LEAF_SIZE
from mi_partpm.experiments.provenance import code_version
from mi_partpm.experiments.speedup import GatherError, gather_bound, gather_excess, run_speedup


def test_speedup_per_map_estimates_gather_to_one_map(tmp_path):
    """Eq. (2): the n partial estimates of every hit point add up to the one-map estimate,
    to float32 rounding (the run itself stops beyond :func:`gather_bound`). Measured here:
    3.7e-6 - 5.7e-6 of the image's brightest estimate (bound 1e-5, the README's figure),
    0.07 - 0.10 of the rounding bound at the worst hit point. (Had the estimate been 0 at
    every hit point, as it was while the scene owning the hit points' BSDFs was freed, the
    run would have stopped: see test_speedup_stops_when_the_estimate_is_zero.)"""
    result = run_speedup("cornell_box", [1, 2, 4, 7], tmp_path, photons=28_000,
                         resolution=(40, 40), repeats=1, progress=None)
    rows = {r["n"]: r for r in result["rows"]}
    for n, row in rows.items():
        print(f"n = {n}: gather error {row['gather_max_rel_error']:.2e} of the brightest, "
              f"{row['gather_rounding_share']:.3f} of float32's bound at the worst hit point")
        assert row["gather_max_rel_error"] < 1e-5, (n, row["gather_max_rel_error"])
        assert row["gather_rounding_share"] <= 1.0
    assert rows[1]["gather_rounding_share"] == 0.0        # n = 1 is the reference itself
    # The run records the code that made it (the notebooks reuse a run only for that code).
    assert result["code"] == code_version()
    assert json.loads((tmp_path / "speedup.json").read_text())["code"] == code_version()
    meta, loads = load_workloads(tmp_path / "workloads")
    assert sorted(loads) == [1, 2, 4, 7] and meta["queries"] == result["queries"] > 1000
    # Format version 3: the radius as a fraction of the scene, the timing threads and the
    # SIMD lanes that ran the queries.
    assert meta["version"] == 3 and meta["radius_fraction"] == 0.05 and meta["threads"] >= 1
    assert meta["lanes"] in (4, 8, 16, 32)
    assert meta["leaf_size"] == LEAF_SIZE
    one = loads[1]
    for n, w in loads.items():
        # Same photons, same radius: the photons found per query split exactly over the maps.
        np.testing.assert_array_equal(w.photons_found.sum(axis=0), one.photons_found[0])
        assert w.map_photons.sum() == result["photons_stored"]
        assert w.map_seconds.shape == (n, 1) and (w.map_seconds > 0).all()
        # Every map visits at least its root for every query; more maps, fewer photons each.
        assert (w.nodes_visited >= 1).all()
    assert abs(rows[7]["mean_photons_found"] * 7 / rows[1]["mean_photons_found"] - 1) < 1e-9
    assert rows[4]["mean_nodes_visited"] < rows[1]["mean_nodes_visited"]
    assert (tmp_path / "speedup.png").stat().st_size > 1000
    assert (tmp_path / "speedup.csv").read_text().startswith("n,per_map_seconds")


def _perturb(monkeypatch, change):
    """Replace the experiment's estimate by one whose per-map terms (the counted,
    untimed ones) go through ``change(L, maps, map_range)``."""
    real = speedup.radiance_estimate

    def estimate(maps, si, bsdf, radius, active=True, map_range=None, with_stats=False,
                 **kwargs):
        out = real(maps, si, bsdf, radius, active, map_range, with_stats, **kwargs)
        return (change(out[0], maps, map_range), out[1]) if with_stats else out
    monkeypatch.setattr(speedup, "radiance_estimate", estimate)


def test_speedup_stops_when_the_maps_do_not_add_up(tmp_path, monkeypatch):
    """An experiment whose per-map terms do not sum to the one-map estimate would record a
    workload that is not the one-map workload split n ways: it stops, naming n, the error
    and the tolerance, and writes nothing. Map 1 of 2's term scaled by 1 + 1e-3 puts a hit
    point's sum off by up to 1e-3 (its share of photons in map 1, times 1e-3), against a
    rounding bound (2 m + 4) 2^-24 of 7e-7 - 1.2e-5 for the 4 - 100 photons a hit point finds
    here: measured 1400 times the bound at the worst hit point."""
    _perturb(monkeypatch, lambda L, maps, maps_range:
             L * 1.001 if maps.map_count == 2 and maps_range == (1, 2) else L)
    with pytest.raises(GatherError) as e:
        run_speedup("cornell_box_diffuse", [1, 2], tmp_path, photons=4000,
                    resolution=(16, 16), repeats=1, progress=None)
    message = str(e.value)
    print(message)
    assert message.startswith("eq. (2) fails at n = 2: at hit point ")
    assert "relative, " in message and "times the tolerance (2 m + 4) 2^-24 = " in message
    relative = float(re.search(r": ([-+.e0-9]+) relative", message).group(1))
    assert 2e-4 < relative <= 1.001e-3, relative
    assert not (tmp_path / "speedup.json").exists()
    assert not (tmp_path / "workloads").exists()


def test_speedup_stops_when_the_estimate_is_zero(tmp_path, monkeypatch):
    """Photons found but an estimate of 0 everywhere (what freed BSDFs gave): the sums of 0
    agree, so only this check can see it."""
    _perturb(monkeypatch, lambda L, maps, maps_range: L * 0.0)
    with pytest.raises(GatherError, match=r"the n = 1 estimate is 0 at every hit point "
                                          r"although its queries found \d+ photons"):
        run_speedup("cornell_box_diffuse", [1, 2], tmp_path, photons=4000,
                    resolution=(16, 16), repeats=1, progress=None)
    assert not (tmp_path / "speedup.json").exists()


def test_gather_bound_is_float32_rounding_of_both_sums():
    ref = np.array([[1.0, 0.5, 0.0], [2.0, 2.0, 2.0]])
    found = np.array([10, 1000])
    np.testing.assert_allclose(gather_bound(ref, found),
                               [[24 * 2.0 ** -24, 12 * 2.0 ** -24, 0.0],
                                [2 * 2004 * 2.0 ** -24] * 3])
    assert gather_excess(ref, ref, found) == (0.0, -1)
    # Off by half the bound at hit point 1: explained by rounding.
    assert gather_excess(ref + [[0, 0, 0], [2004 * 2.0 ** -24] * 3], ref, found) == \
        pytest.approx((0.5, 1))
    # Twice the bound at hit point 0, or light where the reference has none: not explained.
    assert gather_excess(ref + [[48 * 2.0 ** -24, 0, 0], [0, 0, 0]], ref, found)[0] == \
        pytest.approx(2.0)
    assert gather_excess(ref + [[0, 0, 1e-9], [0, 0, 0]], ref, found) == (np.inf, 0)


def test_speedup_cli_and_errors(tmp_path, capsys):
    assert main(["speedup", "cornell_box_diffuse", "--maps", "1,2", "--photons", "4000",
                 "--resolution", "16x16", "--repeats", "1", "--out", str(tmp_path)]) == 0
    assert "one map ms" in capsys.readouterr().out
    saved = json.loads((tmp_path / "speedup.json").read_text())
    assert [r["n"] for r in saved["rows"]] == [1, 2]
    assert main(["speedup", "cornell_box", "--maps", "1,0", "--out", str(tmp_path)]) == 2
    assert "--maps must be comma-separated integers >= 1" in capsys.readouterr().err
    assert main(["speedup", "cornell_box", "--maps", "1,3,7", "--photons", "20",
                 "--out", str(tmp_path)]) == 2
    assert "lcm = 21" in capsys.readouterr().err
    # The speedup is against one map: a list without 1 is refused, not measured against its
    # smallest n under a "1 map" label; a count given twice too, before the out folder is made.
    for maps, said in (("4,2", "--maps must include 1"), ("1,2,2", "--maps lists 2 more than "
                                                                   "once")):
        assert main(["speedup", "cornell_box", "--maps", maps, "--photons", "2000",
                     "--out", str(tmp_path / "new")]) == 2
        assert said in capsys.readouterr().err
        assert not (tmp_path / "new").exists()


@pytest.mark.parametrize("command", ["speedup", "calibrate"])
def test_speedup_and_calibrate_stop_an_oversize_request_before_tracing(command, tmp_path,
                                                                       capsys, monkeypatch):
    """They trace every photon at once: 2 x 10^6 photons where 50 MB are free is refused
    before tracing with the option to lower (both used to trace until memory ran out)."""
    monkeypatch.setenv("PARTPM_MEMORY_LIMIT", "50e6")
    assert main([command, "cornell_box", "--maps", "1,2", "--photons", "2000000",
                 "--resolution", "16x16", "--out", str(tmp_path)]) == 2
    out, err = capsys.readouterr()
    kept = " with 6 forests kept" if command == "calibrate" else ""    # 3 leaf sizes x 2
    assert f"--photons 2000000{kept} needs about" in err and "lower --photons (to about" in err
    assert "tracing" not in out and "max_depth" not in err and "map_count" not in err
    assert "per wave" not in err                      # they trace in one go


def test_calibrate_guard_counts_the_forests_it_keeps(tmp_path, capsys, monkeypatch):
    """calibrate keeps a forest per leaf size and map count (18 by default) beside the
    photons: 3 x 10^5 photons pass a guard of one forest in 400 MB and take about 0.9 GB
    (measured peak: 0.94 GB), so they are refused before tracing, naming the grid."""
    monkeypatch.setenv("PARTPM_MEMORY_LIMIT", "400e6")
    assert main(["calibrate", "cornell_box", "--photons", "300000", "--resolution", "16x16",
                 "--out", str(tmp_path / "c")]) == 2
    out, err = capsys.readouterr()
    assert "--photons 300000 with 18 forests kept needs about" in err
    assert "fewer --leaf-sizes or --maps (a forest is kept for each pair: 3 x 6 here)" in err
    assert "tracing" not in out


CALIBRATE_TINY = ["--leaf-sizes", "4,16", "--radius-fractions", "0.05,0.1", "--maps", "1,2",
                  "--photons", "4000", "--resolution", "16x16", "--repeats", "2"]


def test_calibrate_writes_sets_with_their_leaf_size_and_radius(tmp_path, capsys):
    """`partpm calibrate` at a tiny size: one set per (leaf size, radius), each a workloads
    folder recording both, loaded back by hwsim. The same photons and radius find the same
    photons per query at every leaf size (the tree changes what is tested, not what is
    found), a 4-photon leaf tests fewer photons than a 16-photon one and visits more nodes,
    and twice the radius finds more; every map is timed twice on one thread. The costs file
    and the hwsim config beside it load, the config running on the fitted costs; --refit
    with --check fits again without measuring and checks both ways."""
    from hwsim.calibrate import read_costs
    from hwsim.config import load_config
    from hwsim.workload import load_workload_sets
    out = tmp_path / "cal"
    assert main(["calibrate", "cornell_box_diffuse", *CALIBRATE_TINY, "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "leaf4_r0.05" in text and "condition number" in text and "ns/node" in text
    index, sets = load_workload_sets(out / "sets")
    assert index["scene"] == "cornell_box_diffuse" and index["settings"]["threads"] == 1
    by = {(st.leaf_size, st.meta["radius_fraction"]): st for st in sets}
    assert sorted(by) == [(4, 0.05), (4, 0.1), (16, 0.05), (16, 0.1)]
    for (leaf, frac), st in by.items():
        assert st.name == f"leaf{leaf}_r{frac:g}" and st.meta["threads"] == 1
        assert st.radius == pytest.approx(by[4, 0.05].radius * frac / 0.05, rel=1e-6)
        assert sorted(st.loads) == [1, 2]
        for n, w in st.loads.items():
            assert w.map_seconds.shape == (n, 2) and (w.map_seconds > 0).all()
            np.testing.assert_array_equal(w.photons_found.sum(axis=0),
                                          st.loads[1].photons_found[0])
    for frac in (0.05, 0.1):
        small, large = by[4, frac].loads[1], by[16, frac].loads[1]
        np.testing.assert_array_equal(small.photons_found, large.photons_found)
        assert small.photons_tested.sum() < large.photons_tested.sum()
        assert small.nodes_visited.sum() > large.nodes_visited.sum()
    assert by[4, 0.1].loads[1].photons_found.sum() > by[4, 0.05].loads[1].photons_found.sum()
    saved = json.loads((out / "calibration.json").read_text())
    assert saved["code"] == code_version() and saved["check"] is None
    assert saved["fit"]["rows"] == 4 * (1 + 2) and len(saved["fit"]["design"]["vif"]) == 3
    costs = read_costs(out / "fitted_costs.toml")
    assert costs["threads"] == 1 and costs["scene"] == "cornell_box_diffuse"
    assert costs["seconds_per_map"] == pytest.approx(saved["fit"]["costs"]["fixed"])
    cfg = load_config(out / "hwsim_fitted.toml")
    assert cfg.compute_cycles()["source"] == "fitted"
    assert cfg.compute_cycles()["map"] == pytest.approx(costs["seconds_per_map"] * cfg.clock_hz)
    # Fit again, checked on itself as "the other scene": both directions, no new times.
    before = (out / "sets" / "leaf4_r0.05" / "n1.npz").read_bytes()
    assert main(["calibrate", "--refit", "--check", str(out), "--out", str(out), "-q"]) == 0
    again = json.loads((out / "calibration.json").read_text())
    # A scene with --refit would be ignored: refused instead.
    assert main(["calibrate", "cornell_box", "--refit", "--out", str(out), "-q"]) == 2
    assert "SCENE (cornell_box) does not apply" in capsys.readouterr().err
    assert (out / "sets" / "leaf4_r0.05" / "n1.npz").read_bytes() == before
    assert [d["fit_on"] for d in again["check"]["directions"]] == ["cornell_box_diffuse"] * 2
    d = again["check"]["directions"][0]
    assert d["prediction"]["r2"] == pytest.approx(again["fit"]["self"]["r2"])
    assert set(d["prediction"]["per_set"]) == {st.name for st in sets}
    # The README's table: one row per direction, from the check's own figures.
    from mi_partpm.experiments.calibrate import format_readme_table
    table = format_readme_table(again).splitlines()
    assert table[0].startswith("| fitted on | ns / node |") and len(table) == 4
    cells = [c.strip() for c in table[2].split("|")[1:-1]]
    assert cells[0] == cells[9] == "cornell_box_diffuse"
    assert cells[10] == f"{d['prediction']['r2']:.3f}"
    assert cells[13] == ("yes" if d["goal"]["met"] else "no")
    # Where the run could read this machine's L1 data cache, the cache costs are modelled.
    from mi_partpm.experiments.provenance import l1_data_bytes
    assert all((c != "not modelled") is (l1_data_bytes() is not None) for c in cells[5:7])
    with pytest.raises(ValueError, match="no cross-scene check"):
        format_readme_table(saved)


def test_calibrate_two_scenes_in_one_run(tmp_path, capsys):
    """`partpm calibrate A B`: both scenes' maps timed in one interleaved run, each scene's
    files in its own folder, each fit predicting the other (both directions in the top
    calibration.json, which the README's table reads); --refit fits both again without
    measuring; one --photons count per scene."""
    from mi_partpm.experiments.calibrate import format_readme_table
    from hwsim.workload import load_workload_sets
    out = tmp_path / "both"
    args = [a if a != "4000" else "4000,3000" for a in CALIBRATE_TINY]
    assert main(["calibrate", "cornell_box_diffuse", "cornell_box", *args, "--out",
                 str(out)]) == 0
    text = capsys.readouterr().out
    assert "fitted on cornell_box_diffuse, predicts cornell_box" in text
    assert "fitted on cornell_box, predicts cornell_box_diffuse" in text
    top = json.loads((out / "calibration.json").read_text())
    assert top["scenes"] == ["cornell_box_diffuse", "cornell_box"]
    assert [d["fit_on"] for d in top["check"]["directions"]] == top["scenes"]
    for scene, photons in (("cornell_box_diffuse", 4000), ("cornell_box", 3000)):
        index, sets = load_workload_sets(out / scene / "sets")
        assert index["scene"] == scene and index["settings"]["photons"] == photons
        assert "over the maps of 2 scenes" in index["settings"]["order"]
        assert all((w.map_seconds > 0).all() for st in sets for w in st.loads.values())
        assert (out / scene / "fitted_costs.toml").is_file()
    assert len(format_readme_table(top).splitlines()) == 4
    before = (out / "cornell_box" / "sets" / "leaf4_r0.05" / "n1.npz").read_bytes()
    assert main(["calibrate", "--refit", "--out", str(out), "-q"]) == 0
    again = json.loads((out / "calibration.json").read_text())
    assert again["check"]["directions"][0]["prediction"]["r2"] == pytest.approx(
        top["check"]["directions"][0]["prediction"]["r2"])
    assert (out / "cornell_box" / "sets" / "leaf4_r0.05" / "n1.npz").read_bytes() == before
    assert main(["calibrate", "cornell_box", "cornell_box_diffuse", "--photons", "1,2,3",
                 "--out", str(tmp_path / "x")]) == 2
    assert "--photons must give one count or one per scene (2), got 3" in \
        capsys.readouterr().err
    assert main(["calibrate", "cornell_box", "cornell_box", "--out", str(tmp_path / "x")]) \
        == 2
    assert "calibrate's scenes must be distinct" in capsys.readouterr().err
    # Two different scene files of one name: their folders of --out would clash, and the
    # message says so (it called them 'not distinct').
    for folder in ("a", "b"):
        (tmp_path / folder).mkdir()
        (tmp_path / folder / "scene.xml").write_text("<scene version='3.0.0'/>")
    files = [str(tmp_path / "a" / "scene.xml"), str(tmp_path / "b" / "scene.xml")]
    assert main(["calibrate", *files, "--out", str(tmp_path / "x")]) == 2
    assert f"calibrate writes each scene into a folder of --out named after it (scene), and " \
        f"{files[0]}, {files[1]} would share one: give the scene files different names" in \
        capsys.readouterr().err
    assert main(["calibrate", "cornell_box", "cornell_box_diffuse", "--check", str(out),
                 "--out", str(tmp_path / "x")]) == 2
    assert "each already predicts the others" in capsys.readouterr().err


def test_calibrate_cli_errors(tmp_path, capsys):
    assert main(["calibrate", "cornell_box", "--leaf-sizes", "8,0", "--out", str(tmp_path)]) \
        == 2
    assert "--leaf-sizes must be comma-separated integers >= 1" in capsys.readouterr().err
    assert main(["calibrate", "cornell_box", "--leaf-sizes", "8,8", "--out", str(tmp_path)]) \
        == 2
    assert "--leaf-sizes must be distinct integers >= 1" in capsys.readouterr().err
    assert main(["calibrate", "cornell_box", "--radius-fractions", "0.05,x", "--out",
                 str(tmp_path)]) == 2
    assert "--radius-fractions must be comma-separated numbers" in capsys.readouterr().err
    assert main(["calibrate", "cornell_box", "--radius-fractions", "0.05,2", "--out",
                 str(tmp_path)]) == 2
    assert "--radius-fractions must be distinct numbers in (0, 1]" in capsys.readouterr().err
    # A map count given twice was dropped without a word (and passed the fit's size check).
    assert main(["calibrate", "cornell_box", "--maps", "1,1,1,1,1,1,1", "--leaf-sizes", "8",
                 "--radius-fractions", "0.05", "--photons", "2000", "--out",
                 str(tmp_path)]) == 2
    assert "--maps lists 1 more than once" in capsys.readouterr().err
    assert main(["calibrate", "cornell_box", "--maps", "1,1", "--leaf-sizes", "8",
                 "--radius-fractions", "0.05", "--out", str(tmp_path)]) == 2
    assert "--maps lists 1 more than once" in capsys.readouterr().err   # not "give more"
    assert main(["calibrate", "--out", str(tmp_path)]) == 2
    assert "calibrate needs SCENE" in capsys.readouterr().err
    assert main(["calibrate", "--refit", "--out", str(tmp_path)]) == 2
    assert "holds neither sets.json" in capsys.readouterr().err


#: How each kind of bench row derives its ratio from its own figures, and its unit, by the
#: row's ``ratio_meaning`` (bench.py's ``_Bench.row`` callers).
RATIO_OF = {
    "baseline time / ours": (lambda r: r["baseline"] / r["ours"], "s"),
    "time of 32 maps / 1 map": (lambda r: r["ours"] / r["baseline"], "s"),
    "our rate / baseline rate": (lambda r: r["ours"] / r["baseline"], "M segments/s"),
    "photons/s over the area light's": (lambda r: r["ours"] / r["baseline"], "M photons/s"),
    "process peak, bytes per stored photon": (lambda r: r["peak_rss_bytes"] / r["stored"],
                                              "B/photon"),
}


def test_bench_refuses_an_empty_out_before_any_work(capsys):
    """--out '' ran the whole bench and wrote nothing, in silence."""
    assert main(["bench", "--smoke", "--out", ""]) == 2
    assert "--out needs a file name, got ''" in capsys.readouterr().err


def test_bench_smoke(tmp_path, capsys):
    """Every benchmark runs at a tiny size and reports a consistent row (the figures mean
    nothing at this size; the full run is `partpm bench`): exactly the expected rows, each
    with positive finite figures, its ratio recomputed from its own figures as its
    ``ratio_meaning`` says (baseline over ours for times, ours over the baseline for rates
    and for the 32-map estimate), the unit that meaning implies, and "met" the ratio against
    the target as ``target_is`` says. The memory row comes from a real measurement in
    another process: its peak above the resident memory it started the render with, both
    above 0, photons stored, and its ratio the peak per stored photon."""
    from mi_partpm.experiments.bench import SIZES
    from mi_partpm.scenes.emitters import EMITTER_KINDS
    out = tmp_path / "bench.json"
    assert main(["bench", "--smoke", "--out", str(out), "-q"]) == 0
    assert "baseline time / ours" in capsys.readouterr().out
    result = json.loads(out.read_text())
    names = [r["benchmark"] for r in result["rows"]]
    rows = dict(zip(names, result["rows"]))
    smoke = SIZES["smoke"]
    expected = ([f"radius sums, {w}, {o}" for w in ("cornell_box", "room")
                 for o in ("unsorted", "sorted")]
                + [f"kNN k=50, {w}, {o}" for w in ("cornell_box", "room")
                   for o in ("unsorted", "sorted")]
                + ["integrator estimate, 32 maps / 1 map",
                   "estimate, 32 separate trees in turn / 1 map"]
                + [f"build, {n:,} photons" for n in smoke["builds"]]
                + [f"tracing, {smoke['trace']:,} photons, vs path max_depth {d}" for d in (2, 8)]
                + [f"emitting, {kind}" for kind in EMITTER_KINDS if kind != "area_rectangle"]
                + [f"memory, {n:,} photons emitted" for n in smoke["memory"]])
    assert len(names) == len(set(names)), "a benchmark name appears twice"
    assert sorted(names) == sorted(expected), (set(names) ^ set(expected))
    for name, r in rows.items():
        assert r["ratio_meaning"] in RATIO_OF, (name, r["ratio_meaning"])
        ratio, unit = RATIO_OF[r["ratio_meaning"]]
        assert np.isfinite([r["ours"], r["baseline"], r["ratio"]]).all(), name
        assert r["ours"] > 0 and r["baseline"] > 0, name
        assert r["ratio"] == pytest.approx(ratio(r), rel=1e-9), name
        assert r["unit"] == unit, (name, r["unit"])
        if r["target"] is None:
            # The one reference row: the paper's layout beside the integrator's.
            assert name.startswith("estimate, 32 separate trees"), name
            assert r["target_is"] == "none" and r["met"] is None, name
            continue
        assert np.isfinite(r["target"]) and r["target"] > 0, name
        assert r["target_is"] in ("at least", "at most"), name
        assert r["met"] is None, name         # the smoke size judges no target
        assert r["baseline_name"], name
        if not name.startswith(("memory", "emitting")):
            # Timed in rounds beside its baseline: the medians' ratio lies within the rounds'
            # ratios (if every round's ratio is <= hi, so is the medians').
            lo, hi = r["ratio_range"]
            assert r["rounds"] == result["repeats"], name
            assert lo * (1 - 1e-9) <= r["ratio"] <= hi * (1 + 1e-9), (name, lo, r["ratio"], hi)
    for name in expected[:4]:
        assert rows[name]["photons_per_query"] > 0, name
    for name in ("integrator estimate, 32 maps / 1 map",
                 "estimate, 32 separate trees in turn / 1 map"):
        assert rows[name]["visible_points"] > 0
    for d in (2, 8):
        # Beside the tracing rows: the bare rate, and what sorting the rays would buy (their
        # rate once sorted, the cost of sorting them and moving a lane's state, and both).
        r = rows[f"tracing, {smoke['trace']:,} photons, vs path max_depth {d}"]
        sorted_rate, reorder = r["sorted_intersections_per_s"], r["reorder_ns_per_ray"]
        assert r["intersections_per_s"] > 0 and sorted_rate > 0 and reorder > 0
        assert r["sorted_with_reorder_per_s"] == pytest.approx(
            1 / (1 / sorted_rate + reorder * 1e-9), rel=1e-9)
    for n in smoke["memory"]:
        memory = rows[f"memory, {n:,} photons emitted"]
        print(f"memory, {n:,} photons: {memory['stored']:,} stored, resident "
              f"{memory['baseline_rss_bytes'] / 1e6:.0f} MB before the render, peak "
              f"{memory['peak_rss_bytes'] / 1e6:.0f} MB, Dr.Jit's peak "
              f"{memory['drjit_peak_bytes'] / 1e6:.1f} MB")
        assert memory["stored"] > n         # about 3 stored per photon emitted in the box
        assert memory["peak_rss_bytes"] > memory["baseline_rss_bytes"] > 0
        assert memory["drjit_peak_bytes"] > 0 and memory["seconds"] > 0
        assert memory["ours"] == pytest.approx(memory["peak_rss_bytes"] / memory["stored"])
        assert memory["baseline"] == pytest.approx(memory["drjit_peak_bytes"] /
                                                   memory["stored"])
    assert result["code"] and result["machine"]["cores"] >= 1


def test_paired_times_alternate_the_codes_round_by_round():
    """Every round runs each code once, the first one rotating, after the warm-up rounds;
    each time lands in its own code's row."""
    from mi_partpm.timing import paired_times
    calls = []

    def code(name):
        return lambda: calls.append(name)
    t = paired_times([(code("a"), False), (code("b"), False), (code("c"), False)], 4, warmup=1)
    assert t.shape == (3, 4) and np.all(t >= 0)
    assert calls[:3] == ["a", "b", "c"]                        # the warm-up round
    rounds = [calls[3 + 3 * r: 6 + 3 * r] for r in range(4)]
    assert rounds == [["a", "b", "c"], ["b", "c", "a"], ["c", "a", "b"], ["a", "b", "c"]]


def test_disturbed_timings_are_said():
    """A speedup above n, or one that falls as n grows, comes from timings disturbed by
    other work on the machine (a notebook run beside a build gave 2.56, 4.35, 10.0, 5.38
    and 7.09 at n = 2 ... 32, said by nothing); the paper-size runs of an idle machine
    (8.92x at n = 32, falling by at most 2% between neighbours at 1024 maps) are not."""
    from mi_partpm.experiments.speedup import format_speedup, timing_doubts

    def rows(speedups):
        return [{"n": 2 ** k, "speedup": s, "ideal": 2 ** k} for k, s in enumerate(speedups)]
    doubts = timing_doubts(rows([1.0, 2.56, 4.35, 10.0, 5.38, 7.09]))
    assert doubts[:3] == ["the speedup at n = 2 is 2.56, above n / 1 = 2",
                          "the speedup at n = 8 is 10.00, above n / 1 = 8",
                          "the speedup falls from 10.00 at n = 8 to 5.38 at n = 16"]
    assert "the timings look disturbed" in doubts[-1] and len(doubts) == 4
    assert timing_doubts(rows([1.0, 1.67, 2.75, 4.27, 6.25, 8.92])) == []
    assert timing_doubts(rows([1.0, 1.34, 1.71, 2.06, 2.32, 2.38, 2.67, 2.63])) == []
    result = {"scene": "s", "photons_emitted": 1, "photons_stored": 1, "queries": 1,
              "radius": 0.1, "rows": [], "timing_doubts": doubts}
    assert format_speedup(result).splitlines()[-1].startswith("note: the speedup at n = 2")


def test_bench_in_a_mono_variant_skips_only_the_emitter_it_cannot_load(tmp_path):
    """Mitsuba's sunsky loads in RGB and spectral variants only: `bench --variant
    llvm_ad_mono` ended in its traceback after every other row had run, and wrote nothing.
    It now skips that row, says so, and writes the others (in a process of its own: the
    variant is the process's). Its memory rows are measured in that variant too."""
    import subprocess
    import sys
    out = tmp_path / "bench.json"
    done = subprocess.run([sys.executable, "-m", "mi_partpm.cli", "bench", "--smoke",
                           "--variant", "llvm_ad_mono", "--out", str(out)],
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "emitting, sunsky: skipped (Mitsuba's sunsky renders in RGB and spectral " \
        "variants only)" in done.stdout + done.stderr
    rows = json.loads(out.read_text())["rows"]
    names = [r["benchmark"] for r in rows]
    assert "emitting, envmap" in names and "emitting, sunsky" not in names
    # The memory rows' probe process renders the bench's variant (it set llvm_ad_rgb).
    memory = [r for r in rows if r["benchmark"].startswith("memory")]
    assert memory and all(r["variant"] == "llvm_ad_mono" for r in memory)


def test_bench_smoke_takes_the_repeats_it_is_given(tmp_path):
    """--repeats with --smoke was checked and then dropped (the JSON said 1 round)."""
    out = tmp_path / "bench.json"
    assert main(["bench", "--smoke", "--repeats", "2", "--out", str(out), "-q"]) == 0
    assert json.loads(out.read_text())["repeats"] == 2


def test_experiments_say_they_do_not_use_a_scene_files_own_integrator(tmp_path, caplog):
    """compare, converge, speedup, calibrate and scaling render with their own options: a
    scene file's <integrator> (its map_count, radius, max_depth) was ignored in silence."""
    import mi_partpm
    from mi_partpm.cli.experiments import check_experiment_scene
    xml = tmp_path / "own.xml"
    xml.write_text((Path(mi_partpm.__file__).parent / "scenes" / "cornell_box.xml")
                   .read_text().replace('<scene version="3.0.0">', '<scene version="3.0.0">'
                                        '<integrator type="partpm"/>', 1))
    with caplog.at_level("WARNING", logger="mi_partpm"):
        check_experiment_scene("cornell_box", "compare")
        assert caplog.text == ""
        check_experiment_scene(str(xml), "compare")
    assert f'scene {xml} has an <integrator type="partpm"> of its own, which compare does ' \
        f'not use' in caplog.text


def _fake_maps(photons, bytes_, depths):
    """What ``speedup._row`` reads of n maps: their sizes, photons and tree depths."""
    from types import SimpleNamespace
    forest = SimpleNamespace(photon_count=np.array(photons), depth=lambda m: depths[m])
    return SimpleNamespace(map_bytes=np.array(bytes_), forest=forest)


def test_speedup_rows_are_medians_of_the_timings_and_ratios_against_one_map():
    """The figures of a speedup row, from timings and counts chosen so that a mean in place
    of a median, a median over the wrong axis, a ratio inverted or a count read from the
    wrong row each give another number. Worked by hand:

    n = 1, times (1 map x 3 repeats) 1.0, 1.2, 5.0: per-map median 1.2 (mean 2.4); all maps
    1.2. Counts over 2 queries: nodes 10, 20 (mean 15), tested 40, 60 (50), found 4, 6 (5).

    n = 2, times map 0: 1.0, 0.5, 0.6; map 1: 0.8, 3.0, 0.7. Per-map median of all six
    (0.5 0.6 0.7 0.8 1.0 3.0): (0.7 + 0.8) / 2 = 0.75 (mean 1.1); min 0.5, max 3.0. All maps
    in turn: each map's median over its repeats, 0.6 + 0.8 = 1.4 (the medians per repeat
    would give 0.9 + 1.75 + 0.65 = 3.3). Nodes 6, 8 and 4, 6 (mean 6), tested 20, 30 twice
    (25), found 2, 3 twice (2.5).

    Speedup 1.2 / 0.75 = 1.6 (not the ideal 2 / 1 = 2), nodes 15 / 6 = 2.5, tested 50 / 25 = 2.0.
    The README's speedup row prints them: 0.75 s = 750 ms, 1.60, 1.40, 6.0, 25.0, 2.5."""
    from mi_partpm.experiments import readme
    one = speedup._row(1, _fake_maps([100], [4000], [5]), np.array([[1.0, 1.2, 5.0]]),
                       np.array([[[10, 20]], [[40, 60]], [[4, 6]]]), 0.0, 0.0)
    two = speedup._row(2, _fake_maps([60, 40], [3000, 1000], [4, 3]),
                       np.array([[1.0, 0.5, 0.6], [0.8, 3.0, 0.7]]),
                       np.array([[[6, 8], [4, 6]], [[20, 30], [20, 30]], [[2, 3], [2, 3]]]),
                       1e-7, 0.25)
    rows = [one, two]
    speedup._add_ratios(rows)
    assert one["per_map_seconds"] == pytest.approx(1.2) and one["total_seconds"] == 1.2
    assert one["speedup"] == 1.0 and one["node_ratio"] == 1.0 and one["tested_ratio"] == 1.0
    assert two["per_map_seconds"] == pytest.approx(0.75)
    assert (two["per_map_seconds_min"], two["per_map_seconds_max"]) == (0.5, 3.0)
    assert two["total_seconds"] == pytest.approx(1.4)
    assert (two["mean_nodes_visited"], two["mean_photons_tested"],
            two["mean_photons_found"]) == (6.0, 25.0, 2.5)
    assert two["photons_per_map"] == 50.0 and two["map_bytes_mean"] == 2000.0
    assert two["tree_depth"] == 4
    assert two["speedup"] == pytest.approx(1.6) and two["ideal"] == 2.0
    assert two["node_ratio"] == pytest.approx(2.5) and two["tested_ratio"] == pytest.approx(2.0)
    table = readme.format_speedup({"speedup_x": {"rows": rows}}, scenes=("x",)).splitlines()
    assert table[3] == "|  | 2 | 750 | 1.60 | 1.40 | 6.0 | 25.0 | 2.5 | 4 |"


def test_a_bench_row_is_the_ratio_of_medians_with_its_rounds_range_and_met_at_the_target():
    """A timed bench row (``_Bench.faster``): the ratio is baseline over ours of the MEDIAN
    round times, the range spans every round's own ratio, and a ratio equal to its target
    meets it (the target is "at least" / "at most"). The README's bench table prints them.

    ours 1.0, 2.0, 6.0 s (median 2.0, mean 3.0), baseline 2.0, 3.0, 3.0 s (median 3.0, mean
    2.667): ratio 3.0 / 2.0 = 1.5 (means would give 0.889); rounds 2.0, 1.5, 0.5: range
    0.5 - 2.0. Target 1.5 "at least": met, exactly at it. An "at most" row of ratio 2.0
    against a target 2.0 is met too; one of 2.5 is not. (Their times, 4 and 5 s against
    2 s, differ from their ratios: a ratio equal to ``ours`` is printed as no ratio.)"""
    from mi_partpm.experiments import readme
    from mi_partpm.experiments.bench import _Bench
    b = _Bench(repeats=3, say=lambda *a: None)
    b.faster("x", [1.0, 2.0, 6.0], [2.0, 3.0, 3.0], "base", 1.5)
    r = b.rows[0]
    assert (r["ours"], r["baseline"], r["ratio"]) == (2.0, 3.0, 1.5)
    assert r["ratio_range"] == [0.5, 2.0] and r["rounds"] == 3
    assert r["met"] is True and r["target_is"] == "at least"
    b.row("y", 4.0, 2.0, "one map", 2.0, 2.0, "time of 32 maps / 1 map", at_least=False)
    b.row("z", 5.0, 2.0, "one map", 2.0, 2.5, "time of 32 maps / 1 map", at_least=False)
    assert b.rows[1]["met"] is True and b.rows[2]["met"] is False
    table = readme.format_bench({"bench": {"rows": b.rows}}).splitlines()
    assert table[2] == "| x | 2 s | base: 3 s | 1.50x faster (0.50-2.00) | 1.5x | yes |"
    assert table[3].endswith("| 2.00 | <= 2 | yes |")
    assert table[4].endswith("| 2.50 | <= 2 | no |")
