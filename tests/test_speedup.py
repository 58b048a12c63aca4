"""The speedup experiment: per-map estimates gather to the one-map estimate, workloads load."""
import json

import numpy as np

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
    """Every benchmark runs and reports a ratio (tiny sizes: the figures mean nothing)."""
    out = tmp_path / "bench.json"
    assert main(["bench", "--smoke", "--out", str(out), "-q"]) == 0
    rows = json.loads(out.read_text())["rows"]
    names = [r["benchmark"] for r in rows]
    assert names[0] == "radius sums, n=1" and "32 maps in turn / 1 map" in names
    assert any(n.startswith("tracing") for n in names)
    assert all(r["ratio"] > 0 and r["ours"] > 0 for r in rows)
    assert "baseline time / ours" in capsys.readouterr().out
