"""hwsim: configuration checks and the analytic model against hand-computed cycle counts."""
import numpy as np
import pytest

from hwsim.config import HardwareConfig, load_config
from hwsim.model import simulate
from hwsim.networks import gather_cycles
from hwsim.workload import MapWorkloads


def workload(nodes, tested, found, map_bytes=None, bytes_per_node=8, bytes_per_photon=28):
    """n maps x Q queries from nested lists (nodes of 8 bytes, photon records of 28)."""
    nodes, tested, found = (np.array(a, dtype=np.uint32) for a in (nodes, tested, found))
    n = nodes.shape[0]
    return MapWorkloads(n=n, nodes_visited=nodes, photons_tested=tested, photons_found=found,
                        map_photons=np.full(n, 100), map_bytes=np.array(
                            map_bytes if map_bytes is not None else [1000] * n),
                        map_seconds=np.zeros((n, 0)), bytes_per_node=bytes_per_node,
                        bytes_per_photon=bytes_per_photon)


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
    r = simulate(cfg, w)
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


def _random_workload(seed, n=8, q=300, map_bytes=None):
    rng = np.random.default_rng(seed)
    return workload(rng.integers(5, 50, (n, q)), rng.integers(0, 100, (n, q)),
                    rng.integers(0, 30, (n, q)),
                    map_bytes=map_bytes if map_bytes is not None else
                    rng.integers(100, 5000, n).tolist())


@pytest.mark.parametrize("topology", ["bus", "tree", "ring"])
@pytest.mark.parametrize("schedule", ["after", "tiles"])
@pytest.mark.parametrize("pes", [1, 3, 8])
def test_event_model_agrees_with_the_analytic_one_without_contention(topology, schedule, pes):
    """Private DRAM channels: the discrete-event model must give the analytic frame exactly,
    with maps in SRAM and maps in DRAM (SRAM 2500 bytes: about half the maps spill)."""
    cfg = BASE.with_(pe_count=pes, gather_schedule=schedule, tile_queries=37,
                     outstanding_queries=2, gather={"topology": topology},
                     memory={"sram_bytes": 2500, "dram_bytes_per_cycle": 2,
                             "dram_latency_cycles": 30})
    w = _random_workload(pes)
    assert 0 < np.sum(w.map_bytes > 2500) < w.n
    a = simulate(cfg, w, model="analytic")
    e = simulate(cfg, w, model="events")
    assert (a.model, e.model) == ("analytic", "events")
    assert e.frame_cycles == a.frame_cycles and e.compute_cycles == a.compute_cycles
    np.testing.assert_array_equal(e.pe_busy, a.pe_busy)
    np.testing.assert_allclose(e.pe_stall, a.pe_stall, rtol=1e-12, atol=1e-6)
    np.testing.assert_allclose(e.dram_channel_busy, a.dram_channel_busy, rtol=1e-12)
    assert a.pe_stall.sum() > 0


def test_two_pes_sharing_one_dram_channel_by_hand():
    cfg = BASE.with_(pe_count=2, outstanding_queries=2,
                     memory={"sram_bytes": 500, "dram_bytes_per_cycle": 1,
                             "dram_latency_cycles": 10, "dram_burst_bytes": 64},
                     gather={"topology": "bus", "link_bytes_per_cycle": 12,
                             "hop_latency_cycles": 0, "adder_latency_cycles": 0})
    # Each map: 1 query of (2 nodes, 4 tested, 1 found), 1000 bytes, so in DRAM: compute 22,
    # 128 bytes = 128 cycles of transfer, latency 10. Gather on the bus: 2 x 12 / 12 = 2.
    w = workload([[2], [2]], [[4], [4]], [[1], [1]], map_bytes=[1000, 1000])
    private = simulate(cfg, w)
    assert private.model == "analytic" and private.frame_cycles == 128 + 2
    # One channel: PE 0 is served in [0, 128], PE 1 queues and is served in [128, 256].
    shared = simulate(cfg.with_(memory={"dram_channels": 1}), w)
    assert shared.model == "events" and shared.frame_cycles == 256 + 2
    assert shared.pe_stall.tolist() == [128 - 22, 256 - 22]
    assert shared.dram_channel_busy.tolist() == [256]
    with pytest.raises(ValueError, match="analytic model has no DRAM contention"):
        simulate(cfg.with_(memory={"dram_channels": 1}), w, model="analytic")


@pytest.mark.parametrize("channels", [1, 2, 3])
def test_sharing_dram_channels_only_slows_and_is_bandwidth_bound(channels):
    cfg = BASE.with_(pe_count=6, tile_queries=25,
                     memory={"sram_bytes": 0, "dram_bytes_per_cycle": 4})
    w = _random_workload(11, n=6, q=200)
    private = simulate(cfg, w)
    shared = simulate(cfg.with_(memory={"dram_channels": channels}), w)
    assert shared.compute_cycles >= private.compute_cycles
    # No channel transfers more than the frame lasts, and the busiest one bounds the frame.
    assert shared.dram_channel_busy.size == channels
    assert shared.dram_channel_busy.max() <= shared.compute_cycles
    assert shared.dram_channel_busy.sum() == pytest.approx(private.dram_channel_busy.sum())


def test_energy_by_hand():
    cfg = BASE.with_(pe_count=2, energy={"pj_per_node": 1, "pj_per_test": 2,
                                         "pj_per_accumulate": 3, "pj_per_dram_byte": 0,
                                         "pj_per_link_byte": 0.5, "pj_per_add": 4,
                                         "static_watts_per_pe": 0.01},
                     gather={"topology": "tree", "link_bytes_per_cycle": 12,
                             "hop_latency_cycles": 0, "adder_latency_cycles": 0})
    w = workload([[10, 6], [4, 4]], [[20, 8], [2, 2]], [[5, 2], [1, 1]])
    r = simulate(cfg, w)
    # Dynamic: 24 nodes x 1 + 32 tests x 2 + 9 found x 3 = 115 pJ; gather: one PE sends
    # 2 results x 12 bytes over one link (12 pJ) and 2 results are added (8 pJ).
    assert r.energy["nodes"] + r.energy["tests"] + r.energy["accumulates"] == \
        pytest.approx(115e-12)
    assert r.energy["gather"] == pytest.approx(20e-12)
    # Static: 2 PEs x 10 mW over the frame: 162 compute + 2 gather cycles at 100 Hz.
    assert r.frame_cycles == 164 and r.energy["static"] == pytest.approx(2 * 0.01 * 1.64)
    assert r.energy_joules == pytest.approx(sum(r.energy.values()))


@pytest.mark.parametrize("changes, message", [
    ({"pe_count": 0}, r"pe_count must be an integer >= 1, got 0"),
    ({"clock_hz": -1}, r"clock_hz must be a finite number > 0, got -1"),
    ({"gather_schedule": "never"}, r"gather_schedule must be one of after, tiles"),
    ({"gather": {"topology": "mesh"}}, r"gather.topology must be one of bus, tree, ring"),
    ({"memory": {"dram_bytes_per_cycle": 0}}, r"memory.dram_bytes_per_cycle must be"),
    ({"cycles_per_node": float("nan")}, r"cycles_per_node must be a finite number"),
    ({"memory": {"dram_channels": -1}}, r"memory.dram_channels must be an integer >= 0"),
    ({"energy": {"pj_per_node": -1}}, r"energy.pj_per_node must be a finite number >= 0"),
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


def test_the_shipped_default_toml_spells_out_the_defaults():
    from pathlib import Path
    import hwsim
    path = Path(hwsim.__file__).parent / "default.toml"
    assert load_config(path) == HardwareConfig()


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
    # Every map in DRAM: sharing channels uses the event model and never beats private ones.
    cont = {(c["dram_channels"], c["pe_count"]): c for c in result["contention"]}
    assert cont[(1, 8)]["model"] == "events" and cont[(0, 8)]["model"] == "analytic"
    for (channels, p), c in cont.items():
        assert c["frame_cycles"] >= cont[(0, p)]["frame_cycles"] * (1 - 1e-12)
    # The synthetic times follow known costs exactly: the calibration explains them.
    assert result["calibration"]["self"]["r2"] > 0.999


def test_hwsim_cli(tmp_path, capsys):
    from mi_partpm.cli import main
    assert main(["hwsim", str(_synthetic_dir(tmp_path)), "--out", str(tmp_path / "r")]) == 0
    assert "w/o gather" in capsys.readouterr().out
    # --check: costs fitted on one workload predict another's measured times.
    from hwsim.calibrate import synthetic_workloads
    from hwsim.workload import save_workloads
    other = save_workloads(tmp_path / "other", synthetic_workloads(seed=8, queries=200),
                           scene="synthetic seed 8")
    assert main(["hwsim", str(tmp_path / "workloads"), "--check", str(other), "--out",
                 str(tmp_path / "r2")]) == 0
    assert "predicts synthetic seed 8 with R^2 1.000" in capsys.readouterr().out
    cfg = tmp_path / "bad.toml"
    cfg.write_text('[gather]\ntopology = "mesh"\n')
    assert main(["hwsim", str(tmp_path / "workloads"), "--config", str(cfg), "--out",
                 str(tmp_path / "r")]) == 2
    assert "gather.topology must be one of bus, tree, ring" in capsys.readouterr().err


def test_hwsim_never_imports_mitsuba():
    import subprocess
    import sys
    code = ("import sys, hwsim.config, hwsim.model, hwsim.events, hwsim.networks, hwsim.work, hwsim.collective, "
            "hwsim.report, hwsim.calibrate, "
            "hwsim.workload; bad = [m for m in ('mitsuba', 'drjit', 'mi_partpm') "
            "if m in sys.modules]; print(bad); sys.exit(1 if bad else 0)")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert done.returncode == 0, done.stdout + done.stderr


def test_collective_fit_recovers_two_regimes_and_scales_with_tree_steps():
    from hwsim.collective import fit_collective, fit_line, tree_steps
    sizes = [4 ** i for i in range(1, 13)]
    # Short messages: 5 us + 0.2 ns/B; from 64 KiB on: 1 ns/B (ping-pong); the reduction
    # adds 0.5 ns/B of summing on top (gamma) in both regimes, and 2 us of start-up.
    def pingpong(m):
        return 5e-6 + 2e-10 * m if m < 65536 else 1e-9 * m
    bench = {"ranks": 2, "sizes": sizes, "pingpong": [pingpong(m) for m in sizes],
             "reduce": [pingpong(m) + 2e-6 * (m < 65536) + 5e-10 * m for m in sizes]}
    c = fit_collective(bench)
    assert c.pingpong.split == 65536 and c.reduce.split == 65536
    assert c.alpha_beta_gamma(100) == pytest.approx((5e-6, 2e-10, 5e-10), rel=1e-6)
    assert c.alpha_beta_gamma(1 << 20) == pytest.approx((0.0, 1e-9, 5e-10), rel=1e-6,
                                                        abs=1e-12)
    m = 2_764_800
    assert c.reduce_seconds(2, m) == pytest.approx(1.5e-9 * m, rel=1e-6)
    assert c.reduce_seconds(1024, m) == pytest.approx(10 * 1.5e-9 * m, rel=1e-6)
    assert [tree_steps(p) for p in (1, 2, 3, 4, 5, 8, 9)] == [0, 1, 2, 2, 3, 3, 4]
    with pytest.raises(ValueError, match="need >= 2 sizes with positive times"):
        fit_line([1], [1.0])
    with pytest.raises(ValueError, match="need a micro-benchmark on >= 2 ranks"):
        fit_collective({**bench, "ranks": 1})
