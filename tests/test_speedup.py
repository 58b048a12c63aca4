"""The speedup experiment: per-map estimates gather to the one-map estimate, workloads load."""
import json

import numpy as np
import pytest

from hwsim.workload import load_workloads
from mi_partpm.cli import main
from mi_partpm.experiments.speedup import run_speedup


def test_speedup_per_map_estimates_gather_to_one_map(tmp_path):
    result = run_speedup("cornell_box", [1, 2, 4, 7], tmp_path, photons=28_000,
                         resolution=(40, 40), repeats=1, progress=None)
    rows = {r["n"]: r for r in result["rows"]}
    # Eq. (2): the n partial estimates of every hit point add up to the one-map estimate.
    for n, row in rows.items():
        assert row["gather_max_rel_error"] < 1e-5, (n, row["gather_max_rel_error"])
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


def test_bench_smoke(tmp_path, capsys):
    """Every benchmark runs at a tiny size and reports a consistent row (the figures mean
    nothing at this size; the full run is `partpm bench`): the ratio is the baseline over ours
    (or ours over the baseline where lower is better), "met" is the ratio against the target,
    and the memory rows come from a real measurement in another process."""
    out = tmp_path / "bench.json"
    assert main(["bench", "--smoke", "--out", str(out), "-q"]) == 0
    result = json.loads(out.read_text())
    rows = {r["benchmark"]: r for r in result["rows"]}
    groups = ["radius sums, cornell_box, unsorted", "radius sums, cornell_box, sorted",
              "radius sums, room, unsorted", "kNN k=50, room, sorted",
              "integrator estimate, 32 maps in turn / 1 map", "build, 5,000 photons",
              "build, 20,000 photons", "tracing, 20,000 photons", "emitting, sunsky",
              "memory, 20,000 photons emitted"]
    for name in groups:
        assert name in rows, name
    for r in rows.values():
        assert np.isfinite([r["ours"], r["baseline"], r["ratio"]]).all() and r["ours"] > 0
        if r["ratio_meaning"] == "baseline time / ours":
            assert r["ratio"] == pytest.approx(r["baseline"] / r["ours"])
        assert r["met"] == (r["ratio"] >= r["target"] if r["target_is"] == "at least"
                            else r["ratio"] <= r["target"])
    memory = rows["memory, 20,000 photons emitted"]
    assert memory["stored"] > 20_000 and memory["peak_rss_bytes"] >= memory["baseline_rss_bytes"]
    assert memory["ratio"] == pytest.approx(memory["peak_rss_bytes"] / memory["stored"])
    assert result["code"] and result["machine"]["cores"] >= 1
    assert "baseline time / ours" in capsys.readouterr().out
