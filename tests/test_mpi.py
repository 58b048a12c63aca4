"""The MPI backend: the same image as the local backend, clear errors, no hang on failure."""
import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import mitsuba as mi

from mi_partpm.cli import main
from mi_partpm.backends import find_mpiexec

HERE = Path(__file__).parent
RENDER = ["cornell_box", "--maps", "5", "--photons", "20000", "--resolution", "48x40",
          "--spp", "2", "--seed", "3"]


def _mpi(n, *args, timeout=300):
    cmd = [find_mpiexec(), "-n", str(n), sys.executable, *args]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)


def _exr(path):
    return np.array(mi.Bitmap(str(path)), dtype=np.float64)


@pytest.mark.parametrize("direct", ["photons", "nee"])
def test_mpi_two_ranks_give_the_local_image(tmp_path, direct):
    """Rank j traces maps j, j+2, ... from their own streams; the reduction of the partial
    images must be the local image to float rounding (1e-5 relative; measured 4e-6).
    With nee, emission and direct light come from rank 0 only."""
    local = tmp_path / "local.exr"
    assert main(["render", *RENDER, "--direct", direct, "-q", "-o", str(local)]) == 0
    out = tmp_path / "mpi.exr"
    stats = tmp_path / "stats.json"
    done = _mpi(2, "-m", "mi_partpm.cli", "render", *RENDER, "--direct", direct,
                "--backend", "mpi", "-o", str(out), "--stats-json", str(stats))
    assert done.returncode == 0, done.stderr
    a, b = _exr(local), _exr(out)
    rel = np.abs(b - a) / np.maximum(np.abs(a), 1e-3)
    print(f"mpi vs local ({direct}): max relative difference {rel.max():.2e}")
    assert a.mean() > 0.05 and rel.max() < 1e-5
    # Per-rank figures: rank 0 owns maps 0, 2, 4 and rank 1 maps 1, 3; 20000 photons in 5
    # maps of 4000; both send every eye path's flux and photon count (48 x 40 pixels x 2 spp
    # x 4 float32) to the one reduction of the pass.
    s = json.loads(stats.read_text())
    ranks = s["ranks"]
    assert [r["maps_owned"] for r in ranks] == [[0, 2, 4], [1, 3]]
    assert [r["photons_traced"] for r in ranks] == [12000, 8000]
    assert s["photons_stored"] == sum(r["photons_stored"] for r in ranks)
    assert all(r["reduce_bytes"] == 48 * 40 * 2 * 4 * 4 for r in ranks)
    assert all(r["time_reduce"] >= 0 and r["map_bytes"] > 0 for r in ranks)
    assert [r["rank"] for r in ranks] == [0, 1] and not any("ranks" in r for r in ranks)
    assert "reduce MB" in done.stdout   # the per-rank table


def test_mpi_progressive_equals_local(tmp_path):
    """Three progressive passes on two ranks: one allreduce per pass sums every eye path's flux
    and photon count, every rank updates the same radii, and rank 0's image is the local one
    (1e-5 relative). The radii shrink the same way (the final mean radius is in the stats)."""
    args = [*RENDER, "--passes", "3"]
    local, out, stats = tmp_path / "local.exr", tmp_path / "mpi.exr", tmp_path / "s.json"
    local_stats = tmp_path / "local.json"
    assert main(["render", *args, "-q", "-o", str(local), "--stats-json",
                 str(local_stats)]) == 0
    done = _mpi(2, "-m", "mi_partpm.cli", "render", *args, "--backend", "mpi", "-q", "-o",
                str(out), "--stats-json", str(stats))
    assert done.returncode == 0, done.stderr
    a, b = _exr(local), _exr(out)
    rel = np.abs(b - a) / np.maximum(np.abs(a), 1e-3)
    print(f"progressive mpi vs local: max relative difference {rel.max():.2e}")
    assert a.mean() > 0.05 and rel.max() < 1e-5
    s, l = json.loads(stats.read_text()), json.loads(local_stats.read_text())
    assert s["passes"] == l["passes"] == 3
    assert abs(s["mean_final_radius"] / l["mean_final_radius"] - 1) < 1e-6
    # One reduction per pass: 3 x (48 x 40 x 2 paths x 4 float32) per rank.
    assert all(r["reduce_bytes"] == 3 * 48 * 40 * 2 * 4 * 4 for r in s["ranks"])


def test_mpi_sums_radiance_but_not_alpha(tmp_path):
    """With an RGBA film the ranks' alpha is not summed (it would be P x alpha): the MPI image,
    alpha included, is the local one."""
    import mi_partpm
    src = mi_partpm.scenes.scene_path("cornell_box").read_text()
    film = '<film type="hdrfilm">'
    assert film in src
    xml = tmp_path / "rgba.xml"
    xml.write_text(src.replace(film, film + '<string name="pixel_format" value="rgba"/>'))
    args = [str(xml), "--maps", "2", "--photons", "5000", "--resolution", "16x16", "--spp",
            "1"]
    local, out = tmp_path / "local.exr", tmp_path / "mpi.exr"
    assert main(["render", *args, "-q", "-o", str(local)]) == 0
    done = _mpi(2, "-m", "mi_partpm.cli", "render", *args, "--backend", "mpi", "-q", "-o",
                str(out))
    assert done.returncode == 0, done.stderr
    a, b = _exr(local), _exr(out)
    assert a.shape[2] == 4 and a[..., 3].max() == 1.0
    np.testing.assert_array_equal(b[..., 3], a[..., 3])
    np.testing.assert_allclose(b[..., :3], a[..., :3], rtol=1e-5, atol=1e-6)


def test_mpi_backend_refuses_develop_false():
    from mi_partpm.backends import Backend
    integrator = mi.load_dict({"type": "partpm", "map_count": 2})
    integrator.backend = type("FakeMPI", (Backend,), {"name": "mpi"})()
    scene = mi.load_dict({"type": "scene", "sensor": {"type": "perspective"},
                          "light": {"type": "constant"}})
    with pytest.raises(ValueError, match="develop=False is not supported with backend='mpi'"):
        integrator.render(scene, develop=False)


def mi_partpm_scenes():
    import mi_partpm
    return Path(mi_partpm.__file__).parent / "scenes"


def test_mpi_more_ranks_than_maps_is_a_clear_error(tmp_path):
    done = _mpi(3, "-m", "mi_partpm.cli", "render", "cornell_box", "--maps", "2",
                "--resolution", "8x8", "--backend", "mpi", "-o", str(tmp_path / "x.exr"))
    assert done.returncode != 0
    assert "the MPI job has 3 ranks but --maps is 2" in done.stderr
    # Every rank finds it; rank 0 alone says it (three copies ran together before).
    assert done.stderr.count("the MPI job has 3 ranks") == 1, done.stderr
    # The same of a scene file's own partpm moved onto the ranks: as the command line's,
    # naming the file (it read "ValueError: the MPI job ...").
    xml = tmp_path / "two_maps.xml"
    xml.write_text((Path(mi_partpm_scenes()) / "cornell_box.xml").read_text().replace(
        '<scene version="3.0.0">', '<scene version="3.0.0"><integrator type="partpm">'
        '<integer name="photon_count" value="3000"/><integer name="map_count" value="2"/>'
        '</integrator>', 1))
    done = _mpi(3, "-m", "mi_partpm.cli", "render", str(xml), "--resolution", "8x8",
                "--backend", "mpi", "-o", str(tmp_path / "x.exr"))
    assert done.returncode == 2
    assert f"the MPI job has 3 ranks but map_count is 2: every rank owns at least one map, " \
        f"so use at most 2 ranks or raise map_count to >= 3 (map_count of {xml})" \
        in done.stderr, done.stderr[-2000:]
    assert "ValueError" not in done.stderr


@pytest.mark.parametrize("how, said", [
    ("error", "error on MPI rank 1 of 2: MemoryError: cannot allocate the photon map "
              "(simulated)"),
    ("exit", "error on MPI rank 1 of 2: the rank exited (SystemExit 3) during the render"),
    ("interrupt", "error on MPI rank 1 of 2: interrupted (Ctrl-C)")])
def test_a_failing_rank_aborts_the_job_with_its_message(how, said):
    """An exception on one rank ends the job, and so do sys.exit and KeyboardInterrupt
    there: those two passed by the abort before, and the other rank waited in the
    reduction until killed."""
    done = _mpi(2, str(HERE / "mpi_scripts" / "failing_rank.py"), how, timeout=120)
    assert done.returncode != 0
    assert said in done.stderr, done.stderr[-2000:]
    assert "finished" not in done.stdout


@pytest.mark.parametrize("ranks", [1, 2])
def test_bad_input_found_during_an_mpi_render_reads_as_the_command_lines(tmp_path, ranks):
    """The memory guard refuses the photons on every rank: the job ends with exit 2 and the
    message the local command gives (with the rank's share of the maps), naming --photons
    (it named the prop photon_count with the exception's class before, and exit 1); a job
    of one rank ends as cleanly (its MPI_Abort ran C++ exit handlers under Dr.Jit's threads: 'terminate called', exit 6)."""
    env = {**__import__("os").environ, "PARTPM_MEMORY_LIMIT": "3000000"}
    cmd = [find_mpiexec(), "-n", str(ranks), *CLI, "--maps", "4", "--photons", "100000",
           "--resolution", "16x16", "-o", str(tmp_path / "x.exr")]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=120, env=env)
    assert done.returncode == 2, done.stderr[-2000:]
    where = ":" if ranks == 1 else f" on MPI rank 0 of {ranks}:"   # one rank: as locally
    # A rank plans its own maps: the figures are its share's, and the message says so (the
    # photons of 2 maps of 4 read as the whole job's).
    share = "" if ranks == 1 else " (this process's 2 of the 4 maps)"
    assert f"partpm: error{where} --photons 100000{share} needs about" in done.stderr
    assert "MemoryGuardError" not in done.stderr and "photon_count" not in done.stderr
    assert "terminate called" not in done.stderr


NOTHING_STORES = """<scene version="3.0.0">
    <sensor type="perspective">
        <transform name="to_world"><lookat origin="0, 0, -3" target="0, 0, 0" up="0, 1, 0"/>
        </transform>
        <film type="hdrfilm"><integer name="width" value="8"/><integer name="height" value="8"/>
        </film>
    </sensor>
    <shape type="sphere"><bsdf type="conductor"/></shape>
    <emitter type="constant"/>
</scene>
"""


def test_a_job_that_stores_no_photon_warns_and_ends(tmp_path):
    """A mirror under a sky stores no photon on any rank: only rank 0 asked the job for the
    photons traced, for its warning (a collective), while rank 1 went on to the image's
    reduction, and the job hung. Every rank now asks; rank 0 warns and the job ends."""
    scene = tmp_path / "mirror.xml"
    scene.write_text(NOTHING_STORES)
    done = _mpi(2, "-m", "mi_partpm.cli", "render", str(scene), "--maps", "2", "--photons",
                "2000", "--backend", "mpi", "-o", str(tmp_path / "m.exr"), timeout=60)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "no photon was stored of the 2000 traced" in done.stderr + done.stdout


def test_a_stop_asked_on_any_rank_stops_every_rank_after_the_same_pass():
    """A stop asked on rank 1 alone (a Ctrl-C sent to it) stops the job after that pass;
    only rank 0's was heard before, so the job said it would stop and ran all its passes."""
    done = _mpi(2, str(HERE / "mpi_scripts" / "stopping_rank.py"), timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    line = next(x for x in done.stdout.splitlines() if x.startswith("passes per rank:"))
    assert line.split(":")[1].split() == ["3", "3"], line


def _mpmd(first, second, timeout=120):
    """mpiexec with rank 0 running ``first`` and rank 1 ``second`` (each a list of the
    command's arguments, optionally after an ``-env NAME VALUE`` of its own)."""
    cmd = [find_mpiexec(), "-n", "1", *first, ":", "-n", "1", *second]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)


CLI = [sys.executable, "-m", "mi_partpm.cli", "render", "cornell_box", "--maps", "2",
       "--photons", "2000", "--spp", "1", "--backend", "mpi", "-q"]


def test_a_rank_that_fails_before_the_render_aborts_the_job(tmp_path):
    """A rank that cannot load the scene (its data folder is missing: a cluster node set up
    differently) ends the job with its message; the other rank waited in its first
    collective call for as long as the job ran before."""
    args = [sys.executable, "-m", "mi_partpm.cli", "render", "happy_buddha", "--maps", "2",
            "--photons", "2000", "--spp", "1", "--resolution", "8x8", "--backend", "mpi",
            "-o", str(tmp_path / "x.exr")]
    done = _mpmd(args, ["-env", "PARTPM_DATA", str(tmp_path / "missing"), *args])
    assert done.returncode != 0
    assert "error on MPI rank 1 of 2: data file 'happy_buddha_20k.ply' not found" in done.stderr


def test_ranks_given_different_arguments_are_refused(tmp_path):
    out = ["-o", str(tmp_path / "x.exr")]
    done = _mpmd([*CLI, "--resolution", "8x8", *out], [*CLI, "--resolution", "12x12", *out])
    assert done.returncode != 0
    assert "the ranks of the MPI job were started with different arguments" in done.stderr
    assert "--resolution 12x12" in done.stderr


def test_a_render_split_into_sets_of_eye_samples_gives_the_local_image():
    """samples_per_pass on the MPI backend: every rank estimates each set against its own
    maps and the sets are gathered one by one; the image is the local render's to float
    rounding (1e-5 relative of the largest pixel, as for a render in one set; measured
    1.0e-7), and the photons are counted once over the ranks."""
    done = _mpi(2, str(HERE / "mpi_scripts" / "split_sets.py"), timeout=180)
    assert done.returncode == 0, done.stderr[-2000:]
    # (Mitsuba's coloured warnings may end on the same line: read the figures by name)
    difference = re.search(r"relative difference: (\S+)", done.stdout)
    traced = re.search(r"photons traced: (\d+)", done.stdout)
    assert difference and float(difference.group(1)) < 1e-5, done.stdout
    assert traced and int(traced.group(1)) == 20_000, done.stdout


def test_an_experiment_under_mpiexec_is_refused_before_it_runs(tmp_path):
    """Only a render splits its work over the ranks: partpm compare under mpiexec ran whole
    on every rank, both writing the same files and printing the table twice."""
    done = _mpi(2, "-m", "mi_partpm.cli", "compare", "cornell_box", "--maps", "2",
                "--photons", "2000", "--resolution", "8x8", "--spp", "1", "--reference-spp",
                "4", "--no-best", "--out", str(tmp_path / "c"), timeout=120)
    assert done.returncode == 2
    assert "'partpm compare' runs in one process: under mpiexec every one of the 2 ranks " \
        "would run it whole" in done.stderr
    assert not (tmp_path / "c").exists()


def test_mpiexec_with_the_local_backend_is_refused_and_one_rank_is_warned(tmp_path):
    """Under mpiexec with the local backend every rank would render and write the whole
    image; --backend mpi outside mpiexec is a job of one rank, which works but is said."""
    done = _mpi(2, "-m", "mi_partpm.cli", "render", "cornell_box", "--photons", "2000",
                "--resolution", "8x8", "--spp", "1", "-o", str(tmp_path / "x.exr"),
                timeout=120)
    assert done.returncode == 2
    assert "one of the 2 ranks of an MPI job (mpiexec), but the integrator (partpm) renders " \
        "locally" in done.stderr
    assert not (tmp_path / "x.exr").exists()
    done = subprocess.run([*CLI, "--resolution", "8x8", "-o", str(tmp_path / "y.exr")],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "--backend mpi in an MPI job of one rank: start it with mpiexec -n P" in done.stderr


def test_a_rank_that_cannot_parse_its_arguments_ends_the_job(tmp_path):
    """Arguments are compared, and parsed, once the ranks are one job: a rank whose options
    are refused (here rank 0's) ends it instead of leaving the others in their first
    collective call."""
    out = ["-o", str(tmp_path / "x.exr")]
    done = _mpmd([*CLI, "--resolution", "8x8", "--bogus", *out],
                 [*CLI, "--resolution", "8x8", *out], timeout=60)
    assert done.returncode != 0
    assert "different arguments" in done.stderr
    done = _mpi(2, "-m", "mi_partpm.cli", "render", "cornell_box", "--bogus", "-o",
                str(tmp_path / "x.exr"), timeout=60)
    assert done.returncode == 2 and "unrecognized arguments: --bogus" in done.stderr
    # Said once, by rank 0, as the job's other errors are (every rank said it).
    assert done.stderr.count("partpm render: error") == 1, done.stderr
    done = _mpi(2, "-m", "mi_partpm.cli", "render", "cornell_box", "--spp", "0", "-o",
                str(tmp_path / "x.exr"), timeout=60)
    assert done.returncode == 2 and done.stderr.count("--spp must be") == 1, done.stderr


def _mpi_partpm_scene(tmp_path):
    """A scene file whose partpm (2 maps of 2,000 photons) says backend = mpi."""
    xml = tmp_path / "mpi.xml"
    xml.write_text('<scene version="3.0.0"><integrator type="partpm"><integer '
                   'name="photon_count" value="2000"/><integer name="map_count" value="2"/>'
                   '<string name="backend" value="mpi"/></integrator><sensor type="perspective">'
                   '<film type="hdrfilm"><integer name="width" value="8"/><integer name="height" '
                   'value="8"/></film></sensor><shape type="sphere"><emitter type="area"/>'
                   '</shape><shape type="rectangle"><transform name="to_world"><translate '
                   'z="-3"/><scale value="5"/></transform></shape></scene>')
    return xml


def test_a_scene_files_mpi_integrator_renders_on_the_ranks(tmp_path):
    """The scene file's own partpm with backend = mpi is what runs on the ranks (no command
    line option needed)."""
    xml = _mpi_partpm_scene(tmp_path)
    done = _mpi(2, "-m", "mi_partpm.cli", "render", str(xml), "-o", str(tmp_path / "s.exr"),
                timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "rank " in done.stdout and (tmp_path / "s.exr").exists()


def test_backend_local_overrides_a_scene_files_mpi_partpm(tmp_path):
    """--backend local runs a scene file's partpm with backend = mpi in this one process (it
    used to stay on the MPI backend, a job of one rank); the stats name the backend that ran
    (they named the command line's default)."""
    xml = _mpi_partpm_scene(tmp_path)
    for given, ran in ((["--backend", "local"], "local"), ([], "mpi")):
        assert main(["render", str(xml), *given, "-o", str(tmp_path / "s.exr"),
                     "--stats-json", str(tmp_path / "s.json")]) == 0
        stats = json.loads((tmp_path / "s.json").read_text())
        assert stats["backend"] == ran and stats["photons_traced"] == 2000


def test_only_rank_0_reports_progress(tmp_path):
    done = _mpi(2, "-m", "mi_partpm.cli", "render", "cornell_box", "--maps", "2", "--photons",
                "2000", "--spp", "1", "--resolution", "8x8", "--passes", "2", "--backend", "mpi",
                "-o", str(tmp_path / "x.exr"), timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stderr.count("pass 2 of 2:") == 1 and done.stderr.count("scene cornell_box") == 1


def test_ranks_stop_after_the_same_pass_at_a_time_limit():
    done = _mpi(2, str(HERE / "mpi_scripts" / "late_rank.py"), timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    line = next(x for x in done.stdout.splitlines() if x.startswith("passes per rank:"))
    passes = line.split(":")[1].split()
    assert len(passes) == 2 and passes[0] == passes[1], line   # the same passes on both


def test_ranks_stop_by_the_roots_clock_which_leaves_out_on_pass():
    done = _mpi(2, str(HERE / "mpi_scripts" / "slow_on_pass.py"), timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    line = next(x for x in done.stdout.splitlines() if x.startswith("stopped by:"))
    assert line.split(":")[1].split() == ["time_limit", "time_limit"], line


def test_mpi_backend_without_mpi4py_says_what_to_install(monkeypatch):
    monkeypatch.setitem(sys.modules, "mpi4py", None)    # import mpi4py now fails
    with pytest.raises(Exception, match=r"backend 'mpi' needs mpi4py .*pip install mpi4py "
                                        r"mpich"):
        mi.load_dict({"type": "partpm", "map_count": 2, "backend": "mpi"})


def test_the_cli_prints_an_error_without_its_class_name(monkeypatch, tmp_path, capsys):
    monkeypatch.setitem(sys.modules, "mpi4py", None)
    assert main(["render", "cornell_box", "--maps", "2", "--resolution", "8x8", "--backend",
                 "mpi", "-o", str(tmp_path / "x.exr")]) == 2
    err = capsys.readouterr().err
    assert "partpm: error: backend 'mpi' needs mpi4py" in err and "MPIUnavailable" not in err


def test_backend_prop_is_checked():
    with pytest.raises(Exception, match=r"backend must be one of 'local', 'mpi', got 'gpu'"):
        mi.load_dict({"type": "partpm", "backend": "gpu"})


def test_scaling_command_small(tmp_path, capsys):
    assert main(["scaling", "cornell_box_diffuse", "--ranks", "1,2", "--maps", "2",
                 "--photons", "200000", "--resolution", "32x32", "--spp", "1", "--repeats", "5",
                 "--bench-repeats", "3", "--out", str(tmp_path)]) == 0
    text = capsys.readouterr().out
    assert "effic." in text
    rows = json.loads((tmp_path / "scaling.json").read_text())
    assert [r["ranks"] for r in rows] == [1, 2]
    # The two ranks' sums meet in one float32 addition instead of one running sum: a pixel
    # of m photons may round by about (2 m + 4) 2^-24 (m up to about 5,000 here: 6e-4).
    assert rows[1]["max_rel_diff_vs_first"] < 1e-3
    # The render time of P = 2 is predicted from P = 1's CPU seconds per phase and the
    # reduction benchmark alone (mi_partpm.experiments.mpimodel). P = 1 reproduces itself
    # by construction, up to the medians of its parts over the repeats against the median of
    # their sums: at this size a run is a tenth of a second and the two medians differ by
    # the repeats' spread (measured 0.0-0.3% over 5 repeats; 5.8% was seen once over 3, one
    # slow round of one phase moving a median of three, and 13.8% while another process
    # shared the 2 cores: bound 25%, still far below the 2x of a wrong model); P = 2 is out of
    # sample. At this tiny size start-up costs weigh more than at the README's (where the
    # command reports the error), so the bound is loose: 50% (measured -20%). A model that
    # forgot the replicated eye pass or the shared cores misses by 2x.
    assert abs(rows[0]["render_pred_rel_error"]) < 0.25
    assert rows[1]["render_pred_out_of_sample"] and not rows[0]["render_pred_out_of_sample"]
    assert abs(rows[1]["render_pred_rel_error"]) < 0.5, rows[1]
    for r in rows:
        assert r["time_reduce_pred_transport"] >= 0 and r["time_reduce_pred_in_situ"] >= 0
    info = json.loads((tmp_path / "collective.json").read_text())
    assert set(info) == {"transport", "in_situ", "model"}
    assert 0 < info["model"]["efficiency_p1"] <= 1
    assert info["transport"]["image"]["reduce_seconds"]["1024"] > \
        info["transport"]["image"]["reduce_seconds"]["2"] > 0
    assert main(["scaling", "cornell_box", "--ranks", "1,3", "--maps", "2",
                 "--out", str(tmp_path)]) == 2
    assert "every P in --ranks must be in [1, maps = 2], got 3" in capsys.readouterr().err
    # The speedups are against one rank: a list without 1 gave them against its first P
    # under the heading of P = 1, and a P given twice was rendered twice.
    for ranks, said in [("2,4", "--ranks must include 1"), ("1,2,2", "--ranks lists 2 more "
                                                                      "than once")]:
        assert main(["scaling", "cornell_box", "--ranks", ranks, "--maps", "4",
                     "--out", str(tmp_path)]) == 2
        assert said in capsys.readouterr().err
    # Camera samples one wavefront cannot hold are refused before mpiexec starts, in the
    # command's options (its first launch said "lower spp or the resolution").
    assert main(["scaling", "cornell_box", "--ranks", "1,2", "--maps", "4", "--resolution",
                 "16000x16000", "--spp", "64", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "lower --spp or --resolution" in err and "mpiexec" not in err
    # A variant the plugins do not run on is refused before mpiexec starts, as render's
    # --variant is (its ranks said so, one after the other).
    assert main(["scaling", "cornell_box", "--ranks", "1,2", "--maps", "4", "--variant",
                 "scalar_rgb", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "needs a JIT RGB or mono Mitsuba variant" in err and "mpiexec" not in err


def test_the_reduction_benchmark_reduces_arrays_of_the_variant_it_is_given(tmp_path):
    """scaling --variant rendered in that variant but benchmarked (and loaded, in situ) the
    reduction of LLVM arrays whatever the variant (drjit.llvm's Float): on a GPU variant the
    wrong device's arrays. One rank, one round, in a process of its own (it sets the
    variant)."""
    out = tmp_path / "rb.json"
    done = subprocess.run([sys.executable, "-m", "mi_partpm.experiments.reducebench",
                           "--repeats", "1", "--condition", "in_situ", "--variant",
                           "llvm_ad_mono", "--out", str(out)], capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    result = json.loads(out.read_text())
    assert result["variant"] == "llvm_ad_mono" and len(result["reduce"]) == len(result["sizes"])


def test_a_failed_scaling_run_is_named_by_the_ranks_own_line():
    """What mpiexec's stderr says of a failed render: the first rank's own error line, not
    the MPI or Dr.Jit lines about the abort that may come after it."""
    from mi_partpm.experiments.scaling import _failure
    stderr = ("scene cornell_box: 8x8\n"
              "partpm: error on MPI rank 1 of 2: --photons 100 needs about 1 GB\n"
              "partpm: error on MPI rank 0 of 2: --photons 100 needs about 1 GB\n"
              "Abort(2) on node 1 (rank 1 in comm 0): application called MPI_Abort\n"
              "terminate called without an active exception\n")
    assert _failure(stderr) == "error on MPI rank 1 of 2: --photons 100 needs about 1 GB"
    # No rank started (a host mpiexec cannot reach): its first line says why, its last
    # where it gave up (only the last was shown, 'process manager error waiting for
    # completion').
    assert _failure("ssh: Could not resolve hostname badhost\n\n[mpiexec@vm] main: process "
                    "manager error waiting for completion\n") == \
        "ssh: Could not resolve hostname badhost ... [mpiexec@vm] main: process manager " \
        "error waiting for completion"
    assert _failure("one line\n") == "one line"
    # A rank that died in Python's traceback before it could say its error: the exception.
    assert _failure("Traceback (most recent call last):\n  File \"x.py\", line 1\n"
                    "ValueError: bad\n") == "ValueError: bad"
    assert _failure("") == "(no message)"


def test_render_prediction_from_one_rank_by_hand():
    """The MPI render model (mi_partpm.experiments.mpimodel) on numbers worked by hand: a
    P = 1 run of 8 maps on 2 cores with CPU seconds trace 2, build 2, estimate 8, eye 2 and a
    wall time of 8 s (efficiency 14 / (2 x 8) = 0.875). P = 1 reproduces its own 8 s; P = 2
    (one core each, 4 maps each): 2 + 12 x 4/8 = 8 s of work at efficiency 1, plus one
    reduction; P = 4 (half a core each, 2 maps): (2 + 3) / 0.5 = 10 s; P = 3 owns at most 3
    maps: (2 + 12 x 3/8) / (2/3) = 9.75 s."""
    from mi_partpm.experiments.mpimodel import PhaseWork, predict
    work = PhaseWork(cpu={"trace": 2.0, "build": 2.0, "estimate": 8.0, "eye": 2.0},
                     wall=8.0, maps=8, passes=1, cores=2)
    assert work.efficiency == pytest.approx(0.875)

    def reduce(nbytes):
        return 1e-9 * nbytes
    assert predict(work, 1, reduce, 10**6)["render"] == pytest.approx(8.0)
    two = predict(work, 2, reduce, 10**6)
    assert two["compute"] == pytest.approx(8.0) and two["reduce"] == pytest.approx(1e-3)
    assert predict(work, 4, reduce, 10**6)["compute"] == pytest.approx(10.0)
    assert predict(work, 3, reduce, 10**6)["compute"] == pytest.approx(9.75)


@pytest.mark.parametrize("case, said", [
    ("seed", "the ranks of the MPI job render different things (seed: rank 0 0, rank 1 1)"),
    ("film", "film size: rank 0 (16, 16), rank 1 (16, 12)"),
    ("light", "the ranks of the MPI job render different things (scene content: rank 0")])
def test_ranks_that_render_different_things_are_refused(case, said):
    """Ranks whose eye paths differ cannot add up their partial images: another seed on one
    rank gave a silent blend of two images (65 of 256 pixels off by more than half), another
    film size a crash inside MPI's reduction ('Message truncated'), another copy of the
    scene file with a light 4 times brighter an image between the two. All are now refused
    before any photon is traced, with what differs."""
    done = _mpi(2, str(HERE / "mpi_scripts" / "job_checks.py"), case, timeout=120)
    assert done.returncode != 0
    assert said in done.stderr, done.stderr[-2000:]
    assert "passes per rank" not in done.stdout and "Message truncated" not in done.stderr


def test_cancel_from_on_pass_stops_every_rank_after_that_pass():
    """cancel() in on_pass after pass 3 ends the render there on every rank, as locally (the
    ranks agreed on it only after the next pass before: 4 passes)."""
    done = _mpi(2, str(HERE / "mpi_scripts" / "job_checks.py"), "cancel", timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    line = next(x for x in done.stdout.splitlines() if x.startswith("passes per rank:"))
    assert line.split(":")[1].split() == ["3", "3"], line


def test_the_stats_top_level_is_the_whole_jobs():
    """rank 0's stats hold the job's figures: photons traced and stored, segments and CPU
    seconds summed over the ranks, wall times and peak memory the largest rank's (they were
    rank 0's own, half the photons traced)."""
    done = _mpi(2, str(HERE / "mpi_scripts" / "job_checks.py"), "totals", timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    lines = {x.split(":", 1)[0]: x.split(":", 1)[1] for x in done.stdout.splitlines()
             if x.startswith(("stats:", "ranks:"))}
    job, ranks = json.loads(lines["stats"]), json.loads(lines["ranks"])
    assert job["photons_traced"] == 2 * 4000 and job["caustic_photons_traced"] == 2 * 4000
    for key in ("photons_stored", "caustic_photons_stored", "segments", "map_bytes",
                "cpu_trace"):
        assert job[key] == sum(r[key] for r in ranks), key
    for key in ("time_trace", "time_estimate", "peak_memory_bytes"):
        assert job[key] == max(r[key] for r in ranks), key
    assert job["maps_owned"] == [0, 1, 2, 3]
    assert 0 < ranks[0]["caustic_photons_stored"] < job["caustic_photons_stored"]


def test_warnings_of_the_whole_job_are_said_once_and_only_when_true(tmp_path):
    """Few caustic photons in four maps on four ranks: some ranks store none, but the job
    does; no rank may say that the caustic maps add nothing (two of four did), and a
    warning of the scene (here: more sensors than one) is said once, by rank 0."""
    xml = tmp_path / "two_sensors.xml"
    src = __import__("mi_partpm").scenes.scene_path("caustic_glass").read_text()
    start = src.index("<sensor")
    end = src.index("</sensor>") + len("</sensor>")
    xml.write_text(src[:end] + src[start:end] + src[end:])
    done = _mpi(4, "-m", "mi_partpm.cli", "render", str(xml), "--maps", "4", "--photons",
                "2000", "--caustic-photons", "60", "--seed", "3", "--resolution", "16x16",
                "--backend", "mpi", "-o", str(tmp_path / "x.exr"),
                "--stats-json", str(tmp_path / "s.json"), timeout=180)
    assert done.returncode == 0, done.stderr[-2000:]
    ranks = json.loads((tmp_path / "s.json").read_text())["ranks"]
    stored = [r["caustic_photons_stored"] for r in ranks]
    print("caustic photons stored per rank:", stored)
    assert 0 in stored and sum(stored) > 0     # the case: a rank without, the job with
    assert "caustic photon was stored" not in done.stderr, done.stderr
    assert done.stderr.count("has 2 sensors") == 1, done.stderr


def test_backend_mpi_moves_a_scene_files_own_partpm_onto_the_ranks(tmp_path):
    """--backend mpi says where to run: with a scene file's partpm (and no other integrator
    option) its props stay (it rendered the command line's defaults, 8 maps of 10^5
    photons, with a warning); a scene file's pm is refused with a clear message."""
    body = ('<sensor type="perspective"><film type="hdrfilm"><integer name="width" value="8"/>'
            '<integer name="height" value="8"/></film></sensor><shape type="sphere"><emitter '
            'type="area"/></shape><shape type="rectangle"><transform name="to_world">'
            '<translate z="-3"/><scale value="5"/></transform></shape></scene>')
    xml = tmp_path / "own.xml"
    xml.write_text('<scene version="3.0.0"><integrator type="partpm"><integer '
                   'name="photon_count" value="3000"/><integer name="map_count" value="3"/>'
                   '</integrator>' + body)
    done = _mpi(2, "-m", "mi_partpm.cli", "render", str(xml), "--backend", "mpi", "-o",
                str(tmp_path / "s.exr"), "--stats-json", str(tmp_path / "s.json"),
                timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    stats = json.loads((tmp_path / "s.json").read_text())
    assert stats["map_count"] == 3 and stats["photons_traced"] == 3000
    assert "replaces" not in done.stderr
    pm = tmp_path / "pm.xml"
    pm.write_text('<scene version="3.0.0"><integrator type="pm"><integer name="photon_count" '
                  'value="3000"/></integrator>' + body)
    done = _mpi(2, "-m", "mi_partpm.cli", "render", str(pm), "--backend", "mpi", "-o",
                str(tmp_path / "p.exr"), timeout=120)
    assert done.returncode == 2
    assert "--backend mpi runs partpm's maps on the ranks; the scene file's integrator is " \
        "pm" in done.stderr
    assert done.stderr.count("partpm: error") == 1, done.stderr


def test_only_rank_0_checks_and_makes_the_output_folders(tmp_path):
    """Rank 0 alone writes the image; every rank checked (and made) the output's folder
    before, so a node where the output path is not writable (here: rank 1 runs where 'out'
    is a file) ended a job that rank 0 could finish."""
    a, b = tmp_path / "a", tmp_path / "b"
    a.mkdir()
    b.mkdir()
    (b / "out").write_text("a file where rank 1 would make its folder")
    args = [*CLI, "--resolution", "8x8", "-o", "out/x.exr"]
    done = _mpmd(["-wdir", str(a), *args], ["-wdir", str(b), *args], timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    assert (a / "out" / "x.exr").exists() and (b / "out").is_file()


SHARE_CORES = """
import os
import drjit as dr
import mitsuba as mi
mi.set_variant("llvm_ad_rgb")
from mpi4py import MPI
from mi_partpm.backends import share_cores
os.environ["PARTPM_THREADS"] = "3"
print(share_cores(MPI.COMM_WORLD), dr.thread_count())
os.environ["PARTPM_THREADS"] = "abc"
try:
    share_cores(MPI.COMM_WORLD)
except ValueError as e:
    print(e)
del os.environ["PARTPM_THREADS"]
print(share_cores(MPI.COMM_WORLD) == max(2, os.cpu_count()))
"""


def test_each_rank_takes_partpm_threads_where_it_is_set():
    """A rank's Dr.Jit threads: its share of the node's cores, or PARTPM_THREADS (checked).
    The share was skipped where DRJIT_NUM_THREADS was set, a variable Dr.Jit 1.5 does not
    read, so every rank then kept a thread per core."""
    import subprocess
    import sys
    done = subprocess.run([sys.executable, "-c", SHARE_CORES], capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.splitlines() == [
        "3 3", "PARTPM_THREADS (Dr.Jit threads per MPI rank) must be an integer >= 1, got "
        "'abc'", "True"]


ONE_RANK_MAKES = """
import mitsuba as mi
mi.set_variant("llvm_ad_rgb")
import mi_partpm
from mpi4py import MPI
comm = MPI.COMM_WORLD
if comm.rank == 0:
    extra = mi.load_dict({"type": "partpm", "photon_count": 3000, "map_count": 4,
                          "backend": "mpi"})
comm.Barrier()
integrator = mi.load_dict({"type": "partpm", "photon_count": 3000, "map_count": 4,
                           "backend": "mpi"})
scene = mi_partpm.load_scene("cornell_box", resolution=(8, 8), spp=1)
image = mi.render(scene, integrator=integrator)
if comm.rank == 0:
    print("rendered", float(image.numpy().mean()) > 0)
"""


def test_an_mpi_partpm_made_on_one_rank_only_does_not_wait_for_the_others(tmp_path):
    """Making a partpm of backend "mpi" split the ranks by node (a collective call) in its
    constructor: a script that made one on rank 0 alone hung there until killed. The split
    is now made at the start of a render, which every rank makes together."""
    script = tmp_path / "one_rank.py"
    script.write_text(ONE_RANK_MAKES)
    done = _mpi(2, str(script), timeout=60)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "rendered True" in done.stdout


def test_mitsubas_own_warnings_are_said_by_rank_0_only(tmp_path):
    """Mitsuba's warnings (a mono film's: 'Monochrome mode enabled') were printed by every
    rank, while the package's own are rank 0's."""
    done = _mpi(2, *CLI[1:], "--variant", "llvm_ad_mono", "--resolution", "8x8", "-o",
                str(tmp_path / "m.exr"), timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    assert (done.stdout + done.stderr).count("Monochrome mode enabled") == 1, done.stderr


def test_the_jobs_stopped_by_is_the_reason_of_a_rank_that_stopped_on_its_own():
    """A Ctrl-C to rank 2 of 3: ranks 0 and 1 stop because it did ("another_process"),
    and the job's stopped_by (the top level of rank 0's stats) said so too, where the
    job was stopped by a request."""
    from mi_partpm.backends import job_stats
    ranks = [{"stopped_by": "another_process"}, {"stopped_by": "another_process"},
             {"stopped_by": "request"}]
    assert job_stats(ranks)["stopped_by"] == "request"
    assert job_stats([{"stopped_by": "time_limit"}] * 2)["stopped_by"] == "time_limit"
    assert "stopped_by" not in job_stats([{"passes": 3}, {"passes": 3}])
