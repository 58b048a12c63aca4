"""hwsim: configuration checks and the analytic model against hand-computed cycle counts."""
import numpy as np
import pytest

from hwsim.config import HardwareConfig, load_config
from hwsim.model import gather_cycles, simulate
from hwsim.workload import MapWorkloads


def workload(nodes, tested, found, map_bytes=None):
    """n maps x Q queries from nested lists."""
    nodes, tested, found = (np.array(a, dtype=np.uint32) for a in (nodes, tested, found))
    n = nodes.shape[0]
    return MapWorkloads(n=n, nodes_visited=nodes, photons_tested=tested, photons_found=found,
                        map_photons=np.full(n, 100), map_bytes=np.array(
                            map_bytes if map_bytes is not None else [1000] * n),
                        map_seconds=np.zeros((n, 0)))


BASE = HardwareConfig(pe_count=1, clock_hz=100.0, cycles_per_node=4, cycles_per_test=3,
                      cycles_per_accumulate=2)


def test_one_pe_by_hand():
    # Map 0, two queries: (10 nodes, 20 tested, 5 found), (6, 8, 2).
    # Cycles: 10*4 + 20*3 + 5*2 = 110 and 6*4 + 8*3 + 2*2 = 52: 162 in all, no gather.
    r = simulate(BASE, workload([[10, 6]], [[20, 8]], [[5, 2]]))
    assert r.frame_cycles == 162 and r.gather_cycles == 0
    assert r.seconds == pytest.approx(1.62) and r.queries_per_second == pytest.approx(2 / 1.62)
    assert r.utilisation.tolist() == [1.0] and r.load_imbalance == 1.0


def test_two_pes_with_imbalance_and_a_bus_gather():
    # Map 0 on PE 0: 1 query, 10 nodes -> 40 cycles; map 1 on PE 1: 1 query, 5 nodes -> 20.
    cfg = BASE.with_(pe_count=2, gather={"topology": "bus", "link_bytes_per_cycle": 4,
                                         "hop_latency_cycles": 1, "adder_latency_cycles": 2})
    r = simulate(cfg, workload([[10], [5]], [[0], [0]], [[0], [0]]))
    # Bus: 2 PEs x 1 result x 12 bytes / 4 bytes per cycle = 6, + hop 1 + adder 2 = 9.
    assert r.compute_cycles == 40 and r.gather_cycles == 9 and r.frame_cycles == 49
    assert r.pe_idle.tolist() == [9, 29]
    assert r.load_imbalance == pytest.approx(40 / 30)
    assert r.gather_share == pytest.approx(9 / 49)


def test_tree_gather_store_and_forward_vs_pipelined():
    cfg = BASE.with_(gather={"topology": "tree", "link_bytes_per_cycle": 12,
                             "hop_latency_cycles": 2, "adder_latency_cycles": 3})
    # 8 PEs, 100 results: transfer 100 * 12 / 12 = 100 cycles; 3 levels of (2 + 3).
    assert gather_cycles(cfg, 8, 100) == 100 + 3 * 5
    cfg = cfg.with_(gather={"pipelined": False})
    assert gather_cycles(cfg, 8, 100) == 3 * (100 + 5)
    assert gather_cycles(cfg.with_(gather={"topology": "bus"}), 8, 100) == 8 * 100 + 5
    assert gather_cycles(cfg.with_(gather={"topology": "ring"}), 8, 100) == 7 * (100 + 5)
    assert gather_cycles(cfg, 1, 100) == 0


def test_a_map_that_spills_to_dram_stalls():
    cfg = BASE.with_(memory={"sram_bytes": 500, "dram_bytes_per_cycle": 1,
                             "dram_latency_cycles": 10, "dram_burst_bytes": 64},
                     outstanding_queries=2)
    w = workload([[2]], [[4]], [[1]], map_bytes=[1000])
    r = simulate(cfg, w, bytes_per_node=8, bytes_per_photon=28)
    # Compute 2*4 + 4*3 + 1*2 = 22. Bytes: 2*8 + 4*12 + 1*16 = 80 -> 2 bursts = 128 bytes,
    # 128 cycles at 1 byte per cycle; latency 2 nodes * 10 / 2 = 10. Memory 128, stall 106.
    assert r.pe_busy.tolist() == [22] and r.pe_stall.tolist() == [106]
    assert r.frame_cycles == 128 and r.dram_bytes.tolist() == [128]
    fits = simulate(cfg.with_(memory={"sram_bytes": 1000}), w)
    assert fits.frame_cycles == 22 and fits.sram_bytes.tolist() == [1000]


def test_tiled_gather_overlaps_the_compute():
    cfg = BASE.with_(pe_count=2, gather_schedule="tiles", tile_queries=1,
                     gather={"topology": "bus", "link_bytes_per_cycle": 12,
                             "hop_latency_cycles": 0, "adder_latency_cycles": 0})
    w = workload([[10, 10], [10, 10]], [[0, 0]] * 2, [[0, 0]] * 2)
    r = simulate(cfg, w)
    # Compute 80 per PE; gather of 2 results from 2 PEs: 4 cycles; one tile: 2 cycles.
    assert r.frame_cycles == 80 + 2 and r.exposed_gather_cycles == 2


def test_more_pes_never_slow_the_frame_unless_the_gather_grows():
    rng = np.random.default_rng(3)
    n, q = 16, 200
    w = workload(rng.integers(5, 50, (n, q)), rng.integers(0, 100, (n, q)),
                 rng.integers(0, 30, (n, q)))
    frames = [simulate(BASE.with_(pe_count=p), w) for p in (1, 2, 4, 8, 16)]
    for a, b in zip(frames, frames[1:]):
        assert b.compute_cycles <= a.compute_cycles
        assert b.frame_cycles <= a.frame_cycles or \
            b.gather_cycles - a.gather_cycles >= b.frame_cycles - a.frame_cycles


@pytest.mark.parametrize("changes, message", [
    ({"pe_count": 0}, r"pe_count must be an integer >= 1, got 0"),
    ({"clock_hz": -1}, r"clock_hz must be a finite number > 0, got -1"),
    ({"gather_schedule": "never"}, r"gather_schedule must be one of after, tiles"),
    ({"gather": {"topology": "mesh"}}, r"gather.topology must be one of bus, tree, ring"),
    ({"memory": {"dram_bytes_per_cycle": 0}}, r"memory.dram_bytes_per_cycle must be"),
    ({"cycles_per_node": float("nan")}, r"cycles_per_node must be a finite number"),
])
def test_invalid_configs_name_the_field(changes, message):
    with pytest.raises(ValueError, match=message):
        load_config(**changes)


def test_config_from_toml(tmp_path):
    path = tmp_path / "hw.toml"
    path.write_text('pe_count = 8\n[gather]\ntopology = "ring"\n[memory]\nsram_bytes = 1024\n')
    cfg = load_config(path)
    assert cfg.pe_count == 8 and cfg.gather.topology == "ring" and cfg.memory.sram_bytes == 1024
    path.write_text("pe_cuont = 8\n")
    with pytest.raises(ValueError, match="unknown key in the top level: pe_cuont"):
        load_config(path)
    with pytest.raises(ValueError, match="pe_count must be <= the number of maps n = 2"):
        simulate(BASE.with_(pe_count=4), workload([[1], [1]], [[1], [1]], [[1], [1]]))


def test_calibration_recovers_known_costs_and_predicts_another_workload():
    from hwsim.calibrate import check, fit, synthetic_workloads
    truth = (2e-8, 1e-8, 5e-9, 1e-4)
    costs = fit(synthetic_workloads(seed=1, costs=truth))
    np.testing.assert_allclose([costs.per_node, costs.per_test, costs.per_found, costs.fixed],
                               truth, rtol=1e-3)
    other = synthetic_workloads(seed=2, queries=800, costs=truth, noise=0.02)
    report = check(costs, other)
    assert report["r2"] > 0.98 and report["max_rel_error"] < 0.1
    assert set(report["per_n"]) == {1, 2, 4, 8}


def test_synthetic_workload_is_seeded():
    from hwsim.calibrate import synthetic_workloads
    a, b = synthetic_workloads(seed=5), synthetic_workloads(seed=5)
    assert all(np.array_equal(a[n].nodes_visited, b[n].nodes_visited) for n in a)


def _synthetic_dir(tmp_path):
    from hwsim.calibrate import synthetic_workloads
    from hwsim.workload import save_workloads
    return save_workloads(tmp_path / "workloads", synthetic_workloads(
        maps=(1, 2, 4, 8), queries=300, seed=7), scene="synthetic seed 7")


def test_report_on_a_seeded_workload_matches_the_golden_report(tmp_path):
    """The golden file pins the model's numbers on a fixed workload: a change of the model
    shows up here, and then the file is regenerated on purpose (see the test's end)."""
    import json
    from pathlib import Path
    from hwsim.report import run_report
    result = run_report(_synthetic_dir(tmp_path), HardwareConfig(), tmp_path / "out")
    keep = ("n", "frame_cycles", "compute_cycles", "gather_cycles", "speedup",
            "load_imbalance")
    got = [{k: r[k] for k in keep} for r in result["rows"]]
    golden = Path(__file__).parent / "golden" / "hwsim_synthetic_seed7.json"
    if not golden.exists():      # first run: write it, and fail so that it gets reviewed
        golden.write_text(json.dumps(got, indent=1) + "\n")
        pytest.fail(f"wrote {golden}; review and commit it")
    want = json.loads(golden.read_text())
    for g, w in zip(got, want):
        for k in keep:
            assert g[k] == pytest.approx(w[k], rel=1e-9), (g["n"], k)
    assert (tmp_path / "out" / "hwsim.png").stat().st_size > 1000


def test_hwsim_cli(tmp_path, capsys):
    from mi_partpm.cli import main
    assert main(["hwsim", str(_synthetic_dir(tmp_path)), "--out", str(tmp_path / "r")]) == 0
    assert "w/o gather" in capsys.readouterr().out
    cfg = tmp_path / "bad.toml"
    cfg.write_text('[gather]\ntopology = "mesh"\n')
    assert main(["hwsim", str(tmp_path / "workloads"), "--config", str(cfg), "--out",
                 str(tmp_path / "r")]) == 2
    assert "gather.topology must be one of bus, tree, ring" in capsys.readouterr().err


def test_hwsim_never_imports_mitsuba():
    import subprocess
    import sys
    code = ("import sys, hwsim.config, hwsim.model, hwsim.report, hwsim.calibrate, "
            "hwsim.workload; bad = [m for m in ('mitsuba', 'drjit', 'mi_partpm') "
            "if m in sys.modules]; print(bad); sys.exit(1 if bad else 0)")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert done.returncode == 0, done.stdout + done.stderr
