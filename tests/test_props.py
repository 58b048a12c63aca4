"""Bad props and bad command lines fail fast with a message naming the parameter."""
import math

import numpy as np
import pytest

import mitsuba as mi

from mi_partpm.cli import main
from mi_partpm.trace import map_seeds, map_sizes


@pytest.mark.parametrize("props, message", [
    ({"photon_count": 0}, r"photon_count must be an integer >= 1, got 0"),
    ({"photon_count": -5}, r"photon_count must be an integer >= 1, got -5"),
    ({"photon_count": 1.5}, r"photon_count must be an integer >= 1, got 1.5"),
    ({"map_count": 0}, r"map_count must be an integer in \[1, photon_count = 100000\], got 0"),
    ({"photon_count": 10, "map_count": 11}, r"map_count .* got 11"),
    ({"photon_count": 10**8, "map_count": 2**21},
     r"map_count must be an integer in \[1, 1048576\] \(the most maps a forest holds\), got "
     r"2097152"),
    ({"radius": 0.0}, r"radius must be a finite number in \[1e-15, 1e\+18\], got 0.0"),
    ({"radius": 1e-16}, r"radius must be a finite number in \[1e-15, 1e\+18\], got 1e-16"),
    ({"caustic_photon_count": 1000, "caustic_radius": 5e-19},
     r"caustic_radius must be a finite number in \[1e-15, 1e\+18\], got 5e-19"),
    ({"radius": -1.0}, r"radius must be .* got -1.0"),
    ({"radius": math.inf}, r"radius must be .* got inf"),
    ({"radius": math.nan}, r"radius must be .* got nan"),
    ({"radius_fraction": 0.0}, r"radius_fraction must be a finite number in \(0.0, 1.0\]"),
    ({"radius_fraction": 1.5}, r"radius_fraction .* got 1.5"),
    ({"radius": 0.1, "radius_fraction": 0.1}, r"either radius or radius_fraction"),
    # r^2 must be a finite float32: a larger radius divided every estimate by inf (black).
    ({"radius": 1e30}, r"radius must be a finite number in \[1e-15, 1e\+18\], got 1e\+30"),
    ({"caustic_photon_count": 1000, "caustic_radius": 1e30}, r"caustic_radius must be .*1e\+18"),
    ({"max_depth": -2}, r"max_depth must be an integer = -1 \(unlimited\) or in "
                        r"\[1, 2147483647\], got -2"),
    ({"max_depth": 0}, r"max_depth .* got 0"),
    # A 32-bit signed integer, as for path: a larger one failed inside Dr.Jit's tracer.
    ({"max_depth": 99999999999}, r"max_depth must be .* in \[1, 2147483647\], got 99999999999"),
    ({"rr_depth": 0}, r"rr_depth must be an integer in \[1, 2147483647\], got 0"),
    ({"rr_depth": 2**31}, r"rr_depth must be an integer in \[1, 2147483647\], got 2147483648"),
    # Mitsuba holds an integer beyond 64 bits as a float: said so, not as a float.
    ({"seed": 2**63}, r"seed must be an integer in \[0, 9223372036854775807\], got about "
                      r"9\.223e\+18 \(Mitsuba holds an integer beyond 64 bits as a float\)"),
    ({"direct": "both"}, r"direct must be one of 'photons', 'nee', got 'both'"),
    ({"hide_emitters": 1}, r"hide_emitters must be true or false, got 1"),
    # A scene file's <string> for a boolean: the message says which tag gives one (it
    # read "must be true or false, got 'true'").
    ({"hide_emitters": "true"}, r'hide_emitters must be true or false \(a boolean: <boolean '
                                r'name="hide_emitters" value="true"/> in a scene file\), '
                                r"got 'true'"),
    ({"passes": 0}, r"passes must be an integer >= 1, got 0"),
    ({"alpha": 1.0}, r"alpha must be a finite number in \(0.0, 1.0\), got 1.0"),
    ({"alpha": 0.0}, r"alpha must be .* got 0.0"),
    ({"time_limit": -1.0}, r"time_limit must be a finite number in \[0.0, inf\), got -1.0"),
    ({"kernel": "gauss"}, r"kernel must be one of 'box', 'simpson', 'epanechnikov', 'cone', "
                          r"got 'gauss'"),
    ({"caustic_photon_count": -1}, r"caustic_photon_count must be an integer >= 0, got -1"),
    ({"map_count": 8, "caustic_photon_count": 3},
     r"caustic_photon_count must be 0 \(off\) or in \[map_count = 8, ...\), got 3"),
    ({"caustic_radius": 0.1, "caustic_radius_fraction": 0.1},
     r"either caustic_radius or caustic_radius_fraction"),
    ({"caustic_radius_fraction": 2.0}, r"caustic_radius_fraction must be .* got 2.0"),
    ({"glossy": "blur"}, r"glossy must be one of 'map', 'trace', got 'blur'"),
    ({"glossy_samples": 0}, r"glossy_samples must be an integer in \[1, 4096\], got 0"),
    ({"final_gather": -2}, r"final_gather must be an integer in \[0, 4096\], got -2"),
    ({"final_gather": 100_000_000},
     r"final_gather must be an integer in \[0, 4096\], got 100000000"),
    ({"glossy": "trace", "glossy_samples": 5000},
     r"glossy_samples must be an integer in \[1, 4096\], got 5000"),
    ({"final_gather": 4}, r"final_gather = 4 needs direct = 'nee'"),
    ({"caustic_radius": 0.1}, r"caustic_radius and caustic_radius_fraction .* need caustic "
                              r"maps \(caustic_photon_count > 0\)"),
    # pm's props, named (Mitsuba's message said "unreferenced property in unknown plugin").
    ({"k": 10}, r"k applies to pm only: partpm searches every eye path's photons within a "
                r"radius"),
    ({"k": 10, "max_radius": 0.1}, r"k, max_radius apply to pm only"),
])
def test_bad_props_raise_clear_errors(props, message):
    with pytest.raises(Exception, match=message):
        mi.load_dict({"type": "partpm", **props})


def test_unknown_prop_is_rejected():
    with pytest.raises(Exception, match="photon_cuont"):
        mi.load_dict({"type": "partpm", "photon_cuont": 10})


def test_map_sizes_even_and_complete():
    sizes = map_sizes(100_003, 7)
    assert sizes.sum() == 100_003 and sizes.max() - sizes.min() <= 1
    assert list(map_sizes(5, 5)) == [1] * 5


def test_map_seed_depends_on_seed_and_index_only():
    assert np.array_equal(map_seeds(3, 8)[:4], map_seeds(3, 4))
    assert len(set(map_seeds(3, 64).tolist())) == 64
    assert not np.array_equal(map_seeds(3, 4), map_seeds(4, 4))


def test_cli_render_writes_exr_and_png(tmp_path, capsys):
    out = tmp_path / "cb.exr"
    assert main(["render", "cornell_box", "--maps", "2", "--photons", "3000",
                 "--resolution", "16x12", "--spp", "1", "-o", str(out)]) == 0
    assert out.is_file() and out.with_suffix(".png").is_file()
    img = np.array(mi.Bitmap(str(out)))
    assert img.shape[:2] == (12, 16) and img.mean() > 0
    text = capsys.readouterr().out
    for phase in ("trace", "build", "estimate"):
        assert phase in text


SMALL = ["render", "cornell_box", "--resolution", "8x8", "--spp", "1", "--photons", "1000"]


@pytest.mark.parametrize("argv, message", [
    (["render", "no_such_scene", "-o", "x.exr"], "neither a built-in scene"),
    (["render", "cornell_box"], "needs -o"),
    (["render", "cornell_box", "-o", "x.png"], "must name an .exr"),
    (["render", "cornell_box", "--maps", "20", "--photons", "10", "-o", "x.exr"],
     r"--maps must be an integer in \[1, --photons 10\], got 20"),
    (["render", "cornell_box", "--variant", "scalar_rgb", "-o", "x.exr"],
     "--variant llvm_ad_rgb"),
    # Options that would do nothing, and outputs that could not be written, are refused
    # before any work.
    (["render", "cornell_box", "--alpha", "0.5", "-o", "x.exr"], "--alpha .* needs a "
                                                                 "progressive render"),
    (["render", "cornell_box", "--caustic-radius", "0.01", "-o", "x.exr"],
     r"need caustic maps \(--caustic-photons N\)"),
    (["render", "cornell_box", "--passes", "3", "--checkpoint-every", "4", "-o", "x.exr"],
     "would write no checkpoint in 3 passes"),
    (["render", "cornell_box", "-o", "/proc/no_such_dir/x.exr"], "-o .* cannot be written"),
    # Radii whose squares float32 cannot compare, refused before any photon is traced.
    ([*SMALL, "--passes", "2", "--alpha", "1e-35", "-o", "x.exr"],
     r"--alpha 1e-35 shrinks the radius 0.05 to 1.58e-19 in the first pass, below 1e-15.*"
     r"raise --alpha"),
    ([*SMALL, "--radius", "2e-15", "--caustic-photons", "100", "-o", "x.exr"],
     r"the caustic maps' radius, a quarter of --radius 2e-15, is 5e-16: below 1e-15"),
    ([*SMALL, "--passes", "100", "--alpha", "0.01", "--final-gather", "1", "--direct", "nee",
      "-o", "x.exr"], r"--alpha 0.01 shrinks the final gather's radius 0.05 to .* by pass 100"),
    ([*SMALL, "--radius-fraction", "1e-20", "-o", "x.exr"],
     r"the radius, --radius-fraction 1e-20 of the scene's size 2, is 2e-20: below 1e-15, the "
     r"least radius whose squared distances float32 resolves \(raise --radius-fraction or "
     r"give --radius\)"),
    ([*SMALL, "--caustic-photons", "100", "--caustic-radius-fraction", "1e-20", "-o", "x.exr"],
     r"the caustic maps' radius, --caustic-radius-fraction 1e-20 of the scene's size 2, is "
     r"2e-20: .*\(raise --caustic-radius-fraction or give --caustic-radius\)"),
    ([*SMALL, "--caustic-photons", "100", "--radius-fraction", "1.6e-15", "-o", "x.exr"],
     r"the caustic maps' radius, a quarter of --radius-fraction 1.6e-15 of the scene's size "
     r"2, is 8e-16: .*\(raise --radius-fraction or give --caustic-radius\)"),
    (["render", "cornell_box", "-o", "x.exr", "--stats-json", "/proc/x.json"],
     "--stats-json .* cannot be written"),
    # The stats in the image's own file: the image replaced them (exit 0, no stats).
    (["render", "cornell_box", "-o", "x.exr", "--stats-json", "x.png"],
     r"--stats-json 'x.png' is where -o writes its image \(x.exr and x.png\)"),
    (["render", "cornell_box", "-o", "x.exr", "--stats-json", "./x.exr"],
     r"--stats-json './x.exr' is where -o writes its image"),
])
def test_cli_errors_are_one_line(argv, message, capsys):
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("partpm: error:") and \
        __import__("re").search(message, err[0]), err


@pytest.mark.parametrize("argv", [
    ["render", "cornell_box", "--k", "1", "--integrator", "pm", "-o", "x.exr"],
    ["render", "cornell_box", "--alpha", "1", "--passes", "2", "-o", "x.exr"],
    ["compare", "cornell_box", "--k", "20000", "--out", "x"],
    ["render", "cornell_box", "--resolution", "4x", "-o", "x.exr"],
    ["render", "cornell_box", "--maps", "0", "-o", "x.exr"],
    ["render", "cornell_box", "--radius", "0", "-o", "x.exr"],
])
def test_cli_rejects_malformed_arguments(argv, capsys):
    with pytest.raises(SystemExit) as e:
        main(argv)
    assert e.value.code == 2
    assert "must" in capsys.readouterr().err


def test_cli_scene_without_emitter(tmp_path, capsys):
    xml = tmp_path / "dark.xml"
    xml.write_text('<scene version="3.0.0"><shape type="sphere"/></scene>')
    assert main(["render", str(xml), "-o", str(tmp_path / "d.exr")]) == 2
    assert "no emitter" in capsys.readouterr().err


def test_a_bad_prop_in_a_scene_file_is_one_line(tmp_path, capsys):
    """Mitsuba reports a plugin that raised while the scene loaded with its Python
    traceback: the command line gives where in the file and the plugin's message alone."""
    xml = tmp_path / "bad.xml"
    xml.write_text('<scene version="3.0.0"><integrator type="partpm"><integer name="passes" '
                   'value="0"/></integrator><shape type="sphere"><emitter type="area"/>'
                   '</shape></scene>')
    assert main(["render", str(xml), "-o", str(tmp_path / "x.exr")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "Traceback" not in err[0], err
    assert err[0].endswith('failed to instantiate integrator plugin of type "partpm": passes '
                           'must be an integer >= 1, got 0'), err
    assert "(line 1, col" in err[0]


def test_cli_quality_options_reach_the_integrator(tmp_path, capsys):
    """--kernel, --caustic-photons, --caustic-radius-fraction, --glossy, --glossy-samples and
    --final-gather become the plugin's props, and a render with them traces the caustic maps
    (their photons and radius are in the figures written by --stats-json)."""
    import json
    from mi_partpm.cli.parser import build_parser
    from mi_partpm.cli.render import integrator_desc
    out, stats = tmp_path / "q.exr", tmp_path / "q.json"
    argv = ["render", "cornell_box", "--maps", "2", "--photons", "4000", "--resolution",
            "12x12", "--spp", "1", "--direct", "nee", "--kernel", "simpson",
            "--caustic-photons", "4000", "--caustic-radius-fraction", "0.01",
            "--glossy", "trace", "--glossy-samples", "2", "--final-gather", "2",
            "--stats-json", str(stats), "-o", str(out)]
    desc = integrator_desc(build_parser().parse_args(argv))
    assert {k: desc[k] for k in ("kernel", "caustic_photon_count", "caustic_radius_fraction",
                                 "glossy", "glossy_samples", "final_gather")} == {
        "kernel": "simpson", "caustic_photon_count": 4000, "caustic_radius_fraction": 0.01,
        "glossy": "trace", "glossy_samples": 2, "final_gather": 2}
    assert main(argv) == 0
    figures = json.loads(stats.read_text())
    assert figures["caustic_photons_stored"] > 0
    assert figures["caustic_radius"] == pytest.approx(0.01 * figures["radius"] / 0.05,
                                                      rel=1e-5)
    # The summary has a line of the caustic maps too (only the global ones were said).
    assert f"caustic  4000 emitted, {figures['caustic_photons_stored']} stored, radius " \
        f"{figures['caustic_radius']:.4g}" in capsys.readouterr().out


@pytest.mark.parametrize("argv, message", [
    (["--integrator", "pm", "--final-gather", "4"], "--final-gather applies to --integrator "
                                                    "partpm only"),
    (["--integrator", "path", "--kernel", "cone"], "--kernel, --glossy and --glossy-samples "
                                                   "apply to the photon mappers"),
    (["--integrator", "path", "--photons", "5", "--maps", "3", "--direct", "nee", "--radius",
      "0.1"], "--photons, --maps, --direct, --radius apply to the photon mappers "
              "(--integrator partpm or pm), not to path"),
    (["--integrator", "path", "--k", "5"], "--k applies to the photon mappers"),
    (["--k", "5"], "--k applies to --integrator pm only"),
    (["--k", "5", "--max-radius", "0.1"], "--k and --max-radius apply to --integrator pm only"),
])
def test_cli_quality_options_name_the_integrators_they_apply_to(argv, message, capsys):
    assert main(["render", "cornell_box", *argv, "-o", "x.exr"]) == 2
    assert message in capsys.readouterr().err


def test_an_output_that_cannot_be_replaced_is_a_one_line_error(tmp_path, capsys,
                                                               monkeypatch):
    """An output the render could not put in place (an immutable file, or another user's
    in a sticky folder) ends in one line and status 2, not a traceback."""
    from mi_partpm.cli import common
    out = tmp_path / "a.exr"

    def refuse(source, target):
        raise PermissionError(1, "Operation not permitted")
    monkeypatch.setattr(common.os, "replace", refuse)
    assert main(["render", "cornell_box", *SMALL[2:], "-q", "-o", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "a.exr' cannot be written: Operation not permitted" in err[0], err
    assert not list(tmp_path.glob(".*writing*"))


@pytest.mark.parametrize("argv, said", [
    (["render", "cornell_box", "-o", "x.exr", "--radius_fraction", "0.1"],
     "partpm render: error: unrecognized arguments: --radius_fraction 0.1 (did you mean "
     "--radius-fraction?) ('partpm render --help' lists the options)"),
    (["render", "cornell_box", "-o", "x.exr", "--pass", "2"],
     "unrecognized arguments: --pass 2 (did you mean --passes?)"),
    (["compare", "cornell_box", "--out", "x", "--photon", "5"],
     "partpm compare: error: unrecognized arguments: --photon 5 (did you mean --photons?)"),
])
def test_an_unknown_option_is_named_by_its_command_with_the_nearest(argv, said, capsys):
    """An unknown option is reported by the command it was given to, which lists its
    options, with the nearest one (the top-level parser reported it, pointing to 'partpm
    --help', which lists no render option); a prefix of an option is no longer taken for it
    (``--pass 2`` rendered 2 passes)."""
    with pytest.raises(SystemExit) as e:
        main(argv)
    assert e.value.code == 2
    assert said in capsys.readouterr().err


def test_a_plugins_error_of_several_lines_is_said_whole():
    """A bad prop whose value prints over several lines (a Transform given for a radius):
    the message kept only the traceback's last line, which read ']'."""
    from mi_partpm.scenes import _loader_message
    text = ('[xml.cpp:1] At f.xml (line 1, col 25): failed to instantiate integrator plugin '
            'of type "partpm": Traceback (most recent call last):\n  File "x.py", line 3, in '
            '__init__\nValueError: radius must be a finite number in [1e-15, 1e+18], got '
            'Transform[\n  matrix=[[2, 0, 0, 0]],\n]')
    assert _loader_message(text) == (
        'At f.xml (line 1, col 25): failed to instantiate integrator plugin of type "partpm": '
        'radius must be a finite number in [1e-15, 1e+18], got Transform[ matrix=[[2, 0, 0, '
        '0]], ]')


def test_one_pass_with_a_time_limit_is_not_progressive_on_the_command_line(capsys):
    """--passes 1 --time 5 renders one pass, as the integrator decides: --alpha and
    --checkpoint-every between passes are refused there (they were taken, since --time
    counted as progressive), and --radius-fraction's help says when 0.025 is the default."""
    for option in (["--alpha", "0.5"], ["--checkpoint-every", "1"]):
        assert main([*SMALL, "--passes", "1", "--time", "5", *option, "-o", "x.exr"]) == 2
        assert "it needs a progressive render (--passes P > 1, or --time SECONDS without " \
            "--passes)" in capsys.readouterr().err
    # --time alone with --passes 1 stopped nothing ("1 pass (at most 5 s)").
    assert main([*SMALL, "--passes", "1", "--time", "5", "-o", "x.exr"]) == 2
    assert "--time 5 stops a progressive render between passes: with --passes 1 the one " \
        "pass runs whole" in capsys.readouterr().err
    from mi_partpm.cli.parser import build_parser
    assert "--passes > 1, or --time without --passes" in " ".join(
        build_parser()._subparsers._group_actions[0].choices["render"].format_help().split())
