"""The speedup experiment: per-map estimates gather to the one-map estimate, workloads load."""
import json
import re

import numpy as np
import pytest

from hwsim.workload import load_workloads
from mi_partpm.cli import main
from mi_partpm.experiments import speedup
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
                + ["integrator estimate, 32 maps in turn / 1 map"]
                + [f"build, {n:,} photons" for n in smoke["builds"]]
                + [f"tracing, {smoke['trace']:,} photons"]
                + [f"emitting, {kind}" for kind in EMITTER_KINDS if kind != "area_rectangle"]
                + [f"memory, {n:,} photons emitted" for n in smoke["memory"]])
    assert len(names) == len(set(names)), "a benchmark name appears twice"
    assert sorted(names) == sorted(expected), (set(names) ^ set(expected))
    for name, r in rows.items():
        assert r["ratio_meaning"] in RATIO_OF, (name, r["ratio_meaning"])
        ratio, unit = RATIO_OF[r["ratio_meaning"]]
        assert np.isfinite([r["ours"], r["baseline"], r["ratio"], r["target"]]).all(), name
        assert r["ours"] > 0 and r["baseline"] > 0 and r["target"] > 0, name
        assert r["ratio"] == pytest.approx(ratio(r), rel=1e-9), name
        assert r["unit"] == unit, (name, r["unit"])
        assert r["target_is"] in ("at least", "at most"), name
        assert r["met"] is (r["ratio"] >= r["target"] if r["target_is"] == "at least"
                            else r["ratio"] <= r["target"]), name
        assert r["baseline_name"], name
    for name in expected[:4]:
        assert rows[name]["photons_per_query"] > 0, name
    assert rows["integrator estimate, 32 maps in turn / 1 map"]["visible_points"] > 0
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
