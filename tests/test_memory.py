"""The memory guard and the waves of photon maps: maps traced, built and queried a wave at a
time give the image of all maps at once (eq. 2), a tight memory limit makes waves instead of
failing, and what cannot fit even one map per wave is refused before any work."""
import numpy as np
import pytest

import mitsuba as mi

import mi_partpm
from conftest import render
from mi_partpm import memory
from mi_partpm.memory import MemoryGuardError, plan_waves, wave_bytes


def test_plan_waves_by_hand():
    """Maps of 10^6 photons emitted, 3 stored each at WAVE_BYTES_PER_STORED bytes, plus one
    trace batch: a budget of exactly two maps makes waves of two, the last one shorter; no
    budget is one wave; an explicit maps_per_wave wins; a budget below one map still gives
    one map per wave; max_depth 2 stores at most 2 per emitted photon, so three maps fit."""
    sizes = [1_000_000] * 5
    one = wave_bytes(1_000_000, -1)
    per_path = max(memory.TRACE_BATCH_BYTES / memory.TRACE_BATCH,
                   3 * memory.BATCH_BYTES_PER_STORED)
    assert one == int(3e6 * memory.WAVE_BYTES_PER_STORED + per_path * 1e6)
    two = wave_bytes(2_000_000, -1)
    assert two == int(6e6 * memory.WAVE_BYTES_PER_STORED + per_path * memory.TRACE_BATCH)
    assert plan_waves(sizes, -1, two) == [[0, 1], [2, 3], [4]]
    assert plan_waves(sizes, -1, two - 1) == [[0], [1], [2], [3], [4]]
    assert plan_waves(sizes, -1, None) == [[0, 1, 2, 3, 4]]
    assert plan_waves(sizes, -1, 10 * one, maps_per_wave=3) == [[0, 1, 2], [3, 4]]
    assert plan_waves(sizes, -1, one // 2) == [[0], [1], [2], [3], [4]]
    # (a batch of paths that store 2 photons each takes TRACE_BATCH_BYTES, not 2 x 110)
    three = wave_bytes(3_000_000, 2)
    assert three == int(6e6 * memory.WAVE_BYTES_PER_STORED + memory.TRACE_BATCH_BYTES) \
        < wave_bytes(4_000_000, 2)
    assert plan_waves(sizes, 2, three) == [[0, 1, 2], [3, 4]]


@pytest.fixture(scope="module")
def cornell():
    return mi_partpm.load_scene("cornell_box", resolution=(24, 24), spp=2)


def _same(a, b):
    """Equal up to the order of float additions: the maps' terms are summed wave by wave,
    not photon after photon in one sum. A float32 sum of m terms is good to about
    m 2^-24 of its size; these pixels sum up to about 3,000 photons each (up to 1.8e-4):
    bound 3e-4. Another photon set or a term counted twice is off by percent."""
    np.testing.assert_allclose(a, b, rtol=3e-4, atol=1e-6 * float(np.max(b)))


@pytest.mark.parametrize("extra", [{}, {"passes": 2},
                                   {"direct": "nee", "final_gather": 2},
                                   {"caustic_photon_count": 20_000}])
def test_waves_give_the_image_of_all_maps_at_once(cornell, extra):
    desc = {"type": "partpm", "photon_count": 20_000, "map_count": 4, **extra}
    whole = mi.load_dict(desc)
    a = render(cornell, whole)
    waved = mi.load_dict({**desc, "maps_per_wave": 1})
    b = render(cornell, waved)
    assert whole.stats["waves"] == 1 and waved.stats["waves"] == 4
    assert a.mean() > 0
    _same(b, a)


def test_a_tight_memory_limit_makes_waves_instead_of_failing(cornell, monkeypatch):
    """Free memory for about two of the four maps: the render runs in waves and gives the
    same image; its stats say so."""
    desc = {"type": "partpm", "photon_count": 400_000, "map_count": 4}
    whole = mi.load_dict(desc)
    a = render(cornell, whole)
    eye = memory.eye_bytes(24, 24, 2)
    monkeypatch.setenv("PARTPM_MEMORY_LIMIT", str(eye + int(2.2 * wave_bytes(100_000, -1))))
    waved = mi.load_dict(desc)
    b = render(cornell, waved)
    print(f"waves: {waved.stats['waves']}")
    assert whole.stats["waves"] == 1 and waved.stats["waves"] == 2
    _same(b, a)


def test_memory_guard_stops_an_oversize_request_before_tracing(monkeypatch, capsys, tmp_path):
    """50 MB free and one map of 2 x 10^6 photons (about 1.5 GB): not even one map per wave
    fits, so the render stops before tracing, naming the props to change."""
    from mi_partpm.cli import main
    monkeypatch.setenv("PARTPM_MEMORY_LIMIT", "50e6")     # pretend 50 MB are free
    assert main(["render", "cornell_box", "--photons", "2000000", "--maps", "1",
                 "--resolution", "16x16", "-o", str(tmp_path / "x.exr")]) == 2
    err = capsys.readouterr().err
    print(err.strip().splitlines()[-1])
    assert "--photons 2000000 needs about" in err
    assert "only 50.0 MB are free: lower --photons" in err
    assert "raise --maps" in err
    assert "trace: emitting" not in err                   # stopped before any tracing


def test_an_eye_pass_too_large_alone_asks_for_fewer_samples(monkeypatch, capsys, tmp_path):
    """50 MB free and an eye pass of 480 x 480 x 64 samples: fewer photons cannot help, so
    the message asks for fewer samples only."""
    from mi_partpm.cli import main
    monkeypatch.setenv("PARTPM_MEMORY_LIMIT", "50e6")
    assert main(["render", "cornell_box", "--photons", "1000", "--maps", "1", "--spp", "64",
                 "--resolution", "480x480", "-o", str(tmp_path / "x.exr")]) == 2
    err = capsys.readouterr().err
    assert "the eye pass (the camera's samples) alone needs about" in err
    assert "are free: lower the resolution or spp" in err
    assert "lower --photons" not in err


def test_an_eye_pass_that_fits_with_little_room_asks_for_fewer_photons(monkeypatch, capsys,
                                                                       tmp_path):
    """An eye pass of 4.6 MB where 5 MB are free (now: its estimate, and 0.4 MB more) leaves
    room for a few thousand photons:
    the message said that the eye pass 'alone needs about 4.6 MB, but only 5.0 MB are free'
    and that fewer photons would not help (the branch took any eye pass over 90% of the
    free memory), while 4,000 photons render there. It now asks for fewer photons; an eye
    pass larger than what is free still asks for fewer samples only."""
    from mi_partpm.cli import main
    eye = memory.eye_bytes(64, 64, 4)
    monkeypatch.setenv("PARTPM_MEMORY_LIMIT", str(eye + 400_000))
    argv = ["render", "cornell_box", "--resolution", "64x64", "-q", "-o",
            str(tmp_path / "x.exr")]
    assert main([*argv, "--photons", "10000"]) == 2
    err = capsys.readouterr().err
    assert "lower --photons (to about" in err and "alone needs" not in err
    # The count is one for --photons, the whole render's (it was one wave's: 494 of the 8
    # waves' 10,000, where 4,000 render), and it renders.
    target = int(err.split("lower --photons (to about ")[1].split(" here")[0].replace(",", ""))
    assert 2000 < target < 10_000, err
    assert main([*argv, "--photons", str(target)]) == 0
    assert main([*argv, "--photons", "4000"]) == 0
    monkeypatch.setenv("PARTPM_MEMORY_LIMIT", str(eye - 100_000))
    assert main([*argv, "--photons", "10000"]) == 2
    assert f"alone needs about {memory.size_text(eye)}, but only " \
        f"{memory.size_text(eye - 100_000)} are free" in capsys.readouterr().err


def test_many_small_maps_fit_where_one_large_map_does_not(monkeypatch):
    """The same 2 x 10^6 photons in 64 maps fit 400 MB, wave by wave."""
    monkeypatch.setenv("PARTPM_MEMORY_LIMIT", "400e6")
    scene = mi_partpm.load_scene("cornell_box", resolution=(8, 8), spp=1)
    with pytest.raises(Exception) as e:
        mi.render(scene, integrator=mi.load_dict({"type": "partpm",
                                                   "photon_count": 2_000_000}))
    assert "needs about" in str(e.value) or isinstance(e.value.__cause__, MemoryGuardError)
    integrator = mi.load_dict({"type": "partpm", "photon_count": 2_000_000, "map_count": 64})
    img = render(scene, integrator)
    assert integrator.stats["waves"] > 1 and img.mean() > 0


def test_caustic_maps_are_planned_at_their_own_photons_stored_per_emitted(monkeypatch):
    """A caustic path stores a photon only after a mirror or glass (0.07 per emitted in the
    Cornell box), and the layers are traced one after the other: 200,000 caustic photons
    beside 200,000 global ones fit where the global ones alone fit, in as many waves (the
    guard took them at the global maps' 3 per emitted, and traced at once, and refused).
    Where they do not fit, the message names both counts and a target below the wave's."""
    scene = mi_partpm.load_scene("cornell_box", resolution=(32, 32), spp=16)
    # the eye pass and one map of both layers at a time (50,000 photons emitted each: 45 MB
    # planned), not two maps of the global layer alone (78 MB)
    limit = memory.eye_bytes(32, 32, 16) + 50e6
    monkeypatch.setenv("PARTPM_MEMORY_LIMIT", str(int(limit)))
    waves = []
    for extra in ({}, {"caustic_photon_count": 200_000}):
        integrator = mi.load_dict({"type": "partpm", "photon_count": 200_000, "map_count": 4,
                                   **extra})
        assert render(scene, integrator).mean() > 0
        waves.append(integrator.stats["waves"])
    assert waves == [4, 4]
    assert integrator.stats["caustic_photons_stored"] < 0.2 * 200_000
    monkeypatch.setenv("PARTPM_MEMORY_LIMIT", "20e6")
    with pytest.raises(Exception) as e:
        render(scene, mi.load_dict({"type": "partpm", "photon_count": 200_000,
                                    "caustic_photon_count": 200_000}))
    assert isinstance(e.value.__cause__, MemoryGuardError)
    text = str(e.value.__cause__)
    assert "photon_count = 200000, caustic_photon_count = 200000 needs about" in text
    target = int(text.split("lower photon_count + caustic_photon_count (to about ")[1]
                 .split(" here")[0].replace(",", ""))
    assert 0 < target < 400_000


def test_mpi_ranks_on_one_machine_share_its_free_memory(monkeypatch):
    """P ranks of an MPI job on one machine each planned their waves and checked their
    render against all of its free memory (P times what was there); each now has its share,
    and the guard's message says so. PARTPM_MEMORY_LIMIT stays each process's own."""
    from mi_partpm import memory
    monkeypatch.delenv("PARTPM_MEMORY_LIMIT", raising=False)
    whole = memory.available_bytes()
    if whole is None:
        pytest.skip("no /proc/meminfo here: the free memory cannot be read")
    try:
        memory.share_memory(4)
        assert abs(memory.available_bytes() - whole / 4) < 0.05 * whole   # it moves a little
        estimate = memory.estimate_render(10**12, 8, 16, 16, 1)
        with pytest.raises(memory.MemoryGuardError, match=r"are free \(this process's share: "
                                                          r"the machine's free memory over "
                                                          r"the 4 MPI ranks on it\)"):
            memory.check_fits(estimate)
        monkeypatch.setenv("PARTPM_MEMORY_LIMIT", "8e9")
        assert memory.available_bytes() == 8_000_000_000
    finally:
        memory.share_memory(1)


def test_a_wave_that_stores_more_than_planned_is_split_not_refused(monkeypatch, caplog):
    """caustic_glass stores about 4 photons per photon emitted where the plan assumes 3: at
    60 MB the first of 2 planned waves (80 MB: the one wave) projected past the free memory
    once traced and the render was refused, while 40 MB (more waves from the start)
    rendered. The wave is now planned again with what it measured and traced in smaller
    waves; the image is the one of the other plans (the same photons, summed in another
    order: within 1e-4 of the largest pixel)."""
    scene = mi_partpm.load_scene("caustic_glass", resolution=(32, 32), spp=2)
    images, waves = [], []
    for limit in ("40e6", "60e6", "80e6"):
        monkeypatch.setenv("PARTPM_MEMORY_LIMIT", limit)
        integrator = mi.load_dict({"type": "partpm", "photon_count": 100_003, "map_count": 6})
        with caplog.at_level("INFO", logger="mi_partpm"):
            images.append(render(scene, integrator))
        waves.append(integrator.stats["waves"])
        assert integrator.stats["photons_traced"] == 100_003     # a retried wave once
    assert "stores more photons per photon emitted than planned" in caplog.text
    assert all(w >= 2 for w in waves), waves
    for img in images[1:]:
        assert np.abs(img - images[0]).max() < 1e-4 * images[0].max()


def test_a_wave_that_outgrows_the_wave_budget_is_split_where_memory_is_free(monkeypatch,
                                                                             caplog):
    """The wave budget (WAVE_BUDGET_BYTES) holds while a wave is traced, not only in its
    plan: a wave of several maps that stores more photons per photon emitted than planned
    and so outgrows the budget is planned again in smaller waves, however much memory is
    free (a closed white room stored 24 per emitted photon, planned as 3, and took 3 GB in
    one wave under a 1.5 GiB budget). caustic_glass stores about 4 per emitted photon: a
    budget between its plan (3 per emitted) and what it needs (4) made one wave of all maps;
    the image is that of one map per wave (within 1e-4 of the largest pixel)."""
    scene = mi_partpm.load_scene("caustic_glass", resolution=(32, 32), spp=2)
    desc = {"type": "partpm", "photon_count": 100_003, "map_count": 6}
    monkeypatch.delenv("PARTPM_MEMORY_LIMIT", raising=False)
    monkeypatch.setattr(memory, "WAVE_BUDGET_BYTES",
                        (wave_bytes(100_003, -1, 3.0) + wave_bytes(100_003, -1, 3.8)) // 2)
    integrator = mi.load_dict(desc)
    with caplog.at_level("INFO", logger="mi_partpm"):
        image = render(scene, integrator)
    stats = integrator.stats
    assert stats["photons_stored"] / stats["photons_traced"] > 3.8
    assert "stores more photons per photon emitted than planned" in caplog.text
    assert stats["waves"] >= 2 and stats["photons_traced"] == 100_003
    expected = render(scene, mi.load_dict({**desc, "maps_per_wave": 1}))
    assert np.abs(image - expected).max() < 1e-4 * expected.max()


def test_a_wave_stopped_in_its_caustic_layer_is_halved_and_counted_once():
    """The caustic layer is traced after the global one: a wave stopped there had its
    global photons counted, then counted again by the smaller waves (photons_traced 2x);
    and with maps_per_wave the plan gave the same wave back, to stop again where it did.
    Forced here once: the wave is halved, and the counts and image are the whole wave's."""
    scene = mi_partpm.load_scene("caustic_glass", resolution=(16, 16), spp=1)
    desc = {"type": "partpm", "photon_count": 20_000, "caustic_photon_count": 100_000,
            "map_count": 4, "maps_per_wave": 4}
    whole = mi.load_dict(desc)
    expected = render(scene, whole)
    integrator = mi.load_dict(desc)
    original, tripped = integrator._tracing_guard, []

    def guard(scene, sensor, spp, maps, layer, budget=None):
        check = original(scene, sensor, spp, maps, layer, budget)
        if layer.name != "caustic" or tripped:
            return check

        def trip(ratio, done):
            tripped.append(done)
            raise MemoryGuardError("forced for the test")
        return trip
    integrator._tracing_guard = guard
    image = render(scene, integrator)
    assert tripped and integrator.stats["waves"] == 2
    for key in ("photons_traced", "photons_stored", "caustic_photons_traced",
                "caustic_photons_stored", "segments"):
        assert integrator.stats[key] == whole.stats[key], key
    assert np.abs(image - expected).max() < 1e-4 * expected.max()


def test_a_progressive_eye_pass_is_planned_at_its_own_bytes_per_sample(monkeypatch):
    """Eye paths that keep their state between passes take more per sample (measured 669-737
    bytes against 285-514 for one pass, with Dr.Jit's allocation counter; the guard took
    280 for both and let 1.75 GB renders through a 1.2 GB limit): where the single pass's
    eye pass fits and the progressive one's does not, the progressive render is refused
    before anything is traced, and the single pass renders."""
    scene = mi_partpm.load_scene("cornell_box", resolution=(64, 64), spp=4)
    single, kept = memory.eye_bytes(64, 64, 4), memory.eye_bytes(64, 64, 4, kept=True)
    assert kept > 1.3 * single
    monkeypatch.setenv("PARTPM_MEMORY_LIMIT", str(int(single + 0.5 * (kept - single))))
    desc = {"type": "partpm", "photon_count": 2000, "map_count": 8}
    assert render(scene, mi.load_dict(desc)).mean() > 0
    with pytest.raises(Exception) as e:
        render(scene, mi.load_dict({**desc, "passes": 2}))
    assert isinstance(e.value.__cause__, MemoryGuardError)
    assert "the eye pass (the camera's samples) alone needs about" in str(e.value.__cause__)


def test_a_long_trace_says_where_it_is(monkeypatch, caplog):
    """A wave traced in several batches says at info level how far it is, every 10 s (a
    closed white room traced for 16 s without a line; its batches were logged at debug
    only). The heartbeat is made due at once here: two batches, a line each."""
    from mi_partpm.timing import Heartbeat
    monkeypatch.setattr(Heartbeat, "due", lambda self: 12.0)
    scene = mi_partpm.load_scene("cornell_box_diffuse", resolution=(8, 8), spp=1)
    with caplog.at_level("INFO", logger="mi_partpm"):
        render(scene, mi.load_dict({"type": "partpm", "photon_count": memory.TRACE_BATCH + 1000,
                                    "map_count": 2, "max_depth": 3}))
    lines = [r.getMessage() for r in caplog.records if r.levelname == "INFO"
             and r.getMessage().startswith("trace: batch:")]
    assert len(lines) == 2, lines
    for line, done in zip(lines, (memory.TRACE_BATCH, memory.TRACE_BATCH + 1000)):
        assert line.startswith(f"trace: batch: {done} of {memory.TRACE_BATCH + 1000} photons "
                               f"traced, ") and line.endswith(" stored, 12 s"), line


def test_where_photons_are_stored_follows_what_reads_them():
    """glossy = trace reads the maps at surfaces with a diffuse lobe only, so photons are
    stored only there; a final gather without caustic maps reads them on glossy surfaces
    too (its rays stop there), so they are stored there (storing on diffuse lobes alone
    made it miss the glossy caustic under a rough glass ball: 0.67 of path there); pm
    follows glossy alone."""
    def store_on(**props):
        return mi.load_dict(props).store_on()
    assert store_on(type="partpm") == "smooth"
    assert store_on(type="partpm", glossy="trace") == "diffuse"
    assert store_on(type="partpm", glossy="trace", direct="nee", final_gather=4) == "smooth"
    assert store_on(type="partpm", glossy="trace", direct="nee", final_gather=4,
                    caustic_photon_count=1000) == "diffuse"
    assert store_on(type="pm", glossy="trace") == "diffuse"


def test_build_maps_called_alone_is_held_to_the_free_memory_only(monkeypatch):
    """build_maps called by hand (no plan of waves) traces every map it is given however
    small a wave's budget is: only a render's plan holds its waves to one (it raised
    WaveOverBudget, naming no option)."""
    monkeypatch.setattr(memory, "WAVE_BUDGET_BYTES", 1000)
    scene = mi_partpm.load_scene("cornell_box", resolution=(8, 8), spp=1)
    # (over 2^16 photons: the trace measures a pilot first, and checks the memory then)
    integrator = mi.load_dict({"type": "partpm", "photon_count": 100_000, "map_count": 4})
    maps = integrator.build_maps(scene)
    assert maps.map_count == 4 and integrator.stats["photons_stored"] > 100_000


def test_the_render_s_own_memory_counts_as_free_to_it(monkeypatch):
    """Free memory (MemAvailable) falls as the render allocates, so the checks made after its
    eye pass (while a wave is traced, a wave planned again, the next pass's plan) must count
    what the render already holds as its own: a 1920 x 1080 x 16 render that fitted its plan
    was refused after its eye pass (the eye pass counted twice: once held, once estimated).
    Here the machine has a fixed amount, of which MemAvailable reports what this process
    does not hold: a render planned within it is not refused later."""
    status = memory._proc_bytes
    start = status("/proc/self/status", "VmRSS")
    eye = memory.eye_bytes(128, 128, 64, kept=True)
    machine = eye + int(1.3 * wave_bytes(50_000, -1)) + 150_000_000

    def fake(path, key):
        if key == "MemAvailable":
            return machine - max(0, status("/proc/self/status", "VmRSS") - start)
        return status(path, key)
    monkeypatch.delenv("PARTPM_MEMORY_LIMIT", raising=False)
    monkeypatch.setattr(memory, "_proc_bytes", fake)
    scene = mi_partpm.load_scene("cornell_box", resolution=(128, 128), spp=64)
    integrator = mi.load_dict({"type": "partpm", "photon_count": 50_000, "map_count": 2,
                                  "passes": 2})
    image = render(scene, integrator)
    assert integrator.stats["photons_traced"] == 100_000 and np.isfinite(image).all()
    # The eye pass did take memory: without counting it as the render's own the checks
    # after it saw less free than the plan did.
    assert status("/proc/self/status", "VmRSS") - start > 0.25 * eye


def test_an_eye_pass_too_large_for_memory_is_traced_in_sets(monkeypatch, caplog):
    """Where the eye pass of a render of one pass would not fit beside its maps, its samples
    are traced in sets that fit (as Mitsuba's path picks the passes it needs) instead of
    being refused: 128 x 128 at 16 spp, with room beside the maps for 6 samples per pixel,
    is traced in 4 sets of 4 (the most that divide 16 and fit), and gives the image of the
    whole pass (mean within 1%: other eye samples, the same photons; measured 0.1%)."""
    scene = mi_partpm.load_scene("cornell_box_diffuse", resolution=(128, 128), spp=16)
    desc = {"type": "partpm", "photon_count": 20_000, "hide_emitters": True}
    whole = render(scene, mi.load_dict(desc), seed=2)
    monkeypatch.setenv("PARTPM_MEMORY_LIMIT",
                       str(wave_bytes(20_000, -1) + memory.eye_bytes(128, 128, 6)))
    with pytest.raises(MemoryGuardError):      # the whole eye pass does not fit
        memory.check_fits(memory.estimate_render(20_000, -1, 128, 128, 16))
    integrator = mi.load_dict(desc)
    with caplog.at_level("INFO", logger="mi_partpm"):
        split = render(scene, integrator, seed=2)
    assert "its samples are traced in 4 sets of 4 per pixel" in caplog.text
    assert abs(split.mean() / whole.mean() - 1) < 0.01
    assert integrator.stats["photons_traced"] == 20_000
