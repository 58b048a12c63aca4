"""The notebooks run from top to bottom (at the smoke size) and draw their figures."""
import importlib
import importlib.util
import json
import os
import sys
from pathlib import Path

import pytest

NOTEBOOKS = Path(__file__).resolve().parents[1] / "notebooks"

#: What executing a notebook needs; all are in the test extras, so a missing one is a broken
#: environment and fails the test (a skip would pass a run that never executed a notebook).
TOOLS = ("nbformat", "nbclient", "ipykernel")


def _tools():
    """The nbformat and nbclient modules; fails, naming what to install, when any of
    :data:`TOOLS` is missing."""
    missing = [name for name in TOOLS if importlib.util.find_spec(name) is None]
    if missing:
        pytest.fail(f"the notebook tests need {', '.join(missing)}, which the test extras "
                    f"install: pip install -e '.[test]'", pytrace=False)
    return importlib.import_module("nbformat"), importlib.import_module("nbclient")


def test_a_missing_notebook_tool_fails_and_says_what_to_install(monkeypatch):
    monkeypatch.setattr(sys.modules[__name__], "TOOLS", TOOLS + ("no_such_module_here",))
    with pytest.raises(pytest.fail.Exception, match=r"need no_such_module_here, .*"
                                                    r"pip install -e '\.\[test\]'"):
        _tools()


@pytest.fixture(scope="module")
def smoke_out(tmp_path_factory):
    """One output directory for all notebooks: 03 reuses the workloads 02 recorded."""
    return tmp_path_factory.mktemp("notebooks")


@pytest.mark.parametrize("name", ["01_image_comparison.ipynb", "02_speedup.ipynb",
                                  "03_hwsim.ipynb"])
def test_notebook_runs_and_draws(name, smoke_out, monkeypatch):
    monkeypatch.setenv("PARTPM_NOTEBOOK_SIZE", "smoke")
    monkeypatch.setenv("PARTPM_NOTEBOOK_OUT", str(smoke_out))
    if os.environ.get("PARTPM_DATA"):    # the kernel runs in notebooks/: make it absolute
        monkeypatch.setenv("PARTPM_DATA", str(Path(os.environ["PARTPM_DATA"]).resolve()))
    nbformat, nbclient = _tools()
    notebook = nbformat.read(NOTEBOOKS / name, as_version=4)
    for cell in notebook.cells:          # run what is committed, not its stored outputs
        if cell.cell_type == "code":
            cell.outputs = []
    client = nbclient.NotebookClient(notebook, timeout=600, kernel_name="python3",
                            resources={"metadata": {"path": str(NOTEBOOKS)}})
    client.execute()                     # raises CellExecutionError with the cell's traceback
    outputs = [o for c in notebook.cells if c.cell_type == "code" for o in c.outputs]
    assert not [o for o in outputs if o.output_type == "error"]
    images = [o for o in outputs if {"image/png", "image/jpeg"} & set(o.get("data", {}))]
    assert images, f"{name} drew no figure"
    text = "".join(o.get("text", "") for o in outputs)
    assert "size: smoke" in text


def test_a_finished_run_is_reused_only_by_the_code_that_made_it(tmp_path, monkeypatch):
    """The notebooks read a finished run back only when its settings and its code version
    are the current ones; with another code version (or none recorded) they run it again
    and say so. The experiments are replaced by stand-ins that count their runs and write
    what the real ones write (metrics.json and speedup.json record their code version)."""
    from dataclasses import asdict

    from mi_partpm.experiments import compare, notebook, speedup
    from mi_partpm.experiments.provenance import scene_digest
    monkeypatch.setenv("PARTPM_NOTEBOOK_SIZE", "smoke")
    monkeypatch.setenv("PARTPM_NOTEBOOK_OUT", str(tmp_path))
    runs = []

    def fake_compare(settings, out, progress=print):
        runs.append("compare")
        result = {"settings": {**asdict(settings), "resolution": list(settings.resolution),
                               "k": 10}, "calibrated_knn_radius": 0.1, "metrics": {},
                  "code": notebook.code_version(),
                  "scene_sha256": scene_digest(settings.scene)}
        out.mkdir(parents=True, exist_ok=True)
        (out / "metrics.json").write_text(json.dumps(result))
        return result

    def fake_speedup(scene, maps, out, photons, resolution, spp, repeats, radius_fraction,
                     seed, progress=print):
        runs.append("speedup")
        result = {"photons_emitted": photons, "resolution": list(resolution), "spp": spp,
                  "repeats": repeats, "radius_fraction": radius_fraction, "seed": seed,
                  "rows": [{"n": n} for n in maps],
                  "code": notebook.code_version(), "scene_sha256": scene_digest(scene)}
        (out / "workloads").mkdir(parents=True, exist_ok=True)
        (out / "workloads" / "meta.json").write_text("{}")
        (out / "speedup.json").write_text(json.dumps(result))
        return result
    monkeypatch.setattr(compare, "run_compare", fake_compare)
    monkeypatch.setattr(speedup, "run_speedup", fake_speedup)
    code = {"now": notebook.code_version()}
    monkeypatch.setattr(notebook, "code_version", lambda: code["now"])
    said = []
    for helper, kind in ((notebook.compare, "compare"), (notebook.speedup, "speedup")):
        code["now"] = "0123456789abcdef"
        helper("cornell_box", progress=said.append)
        helper("cornell_box", progress=said.append)          # same code: reused
        assert runs.count(kind) == 1 and "reusing" in said[-1], said
        code["now"] = "fedcba9876543210"
        helper("cornell_box", progress=said.append)          # other code: run again
        assert runs.count(kind) == 2, said
        assert said[-1].endswith("was made by code 0123456789abcdef, this is code "
                                 "fedcba9876543210: running again"), said[-1]
        helper("cornell_box", progress=said.append)          # the new run is reused
        assert runs.count(kind) == 2 and "reusing" in said[-1], said
    # Other settings: run again.
    monkeypatch.setitem(notebook.SIZES["smoke"], "compare",
                        {**notebook.SIZES["smoke"]["compare"], "photons": 20_000})
    notebook.compare("cornell_box", progress=said.append)
    assert runs.count("compare") == 3 and said[-1].endswith("has other settings: running "
                                                            "again"), said[-1]
    # A run of the same sizes but another radius or seed (the README's commands take both),
    # or a compare whose k was given by hand rather than calibrated: run again (they were
    # reused).
    done = tmp_path / "smoke" / "speedup_cornell_box" / "speedup.json"
    for key, value in (("radius_fraction", 0.2), ("seed", 7)):
        result = json.loads(done.read_text())
        done.write_text(json.dumps({**result, key: value}))
        before = runs.count("speedup")
        notebook.speedup("cornell_box", progress=said.append)
        assert runs.count("speedup") == before + 1 and "other settings" in said[-1], said[-1]
    metrics = tmp_path / "smoke" / "compare_cornell_box" / "metrics.json"
    result = json.loads(metrics.read_text())
    metrics.write_text(json.dumps({**result, "calibrated_knn_radius": None}))
    notebook.compare("cornell_box", progress=said.append)
    assert runs.count("compare") == 4 and "other settings" in said[-1], said[-1]
    # A result file without a code version: run again.
    result = json.loads(done.read_text())
    del result["code"]
    done.write_text(json.dumps(result))
    notebook.speedup("cornell_box", progress=said.append)
    assert runs.count("speedup") == 5 and "code of unknown version" in said[-1], said
    metrics = tmp_path / "smoke" / "compare_cornell_box" / "metrics.json"
    result = json.loads(metrics.read_text())
    del result["code"]
    metrics.write_text(json.dumps(result))
    notebook.compare("cornell_box", progress=said.append)
    assert runs.count("compare") == 5 and "code of unknown version" in said[-1], said
    # A user's scene file: its run's folder is named after the file's stem (its path made
    # folders within folders), and a change to a file it includes runs it again (the
    # results were reused: the key held the settings and the code, not the user's scene).
    scenes = tmp_path / "scenes"
    scenes.mkdir()
    (scenes / "light.xml").write_text('<scene version="3.0.0"><emitter type="constant"/>'
                                      '</scene>')
    xml = scenes / "mine.xml"
    xml.write_text('<scene version="3.0.0"><include filename="light.xml"/></scene>')
    for helper, kind in ((notebook.compare, "compare"), (notebook.speedup, "speedup")):
        (scenes / "light.xml").write_text('<scene version="3.0.0"><emitter type="constant"/>'
                                          '</scene>')
        before = runs.count(kind)
        result = helper(str(xml), progress=said.append)
        assert result["out"] == str(tmp_path / "smoke" / f"{kind}_mine")
        helper(str(xml), progress=said.append)
        assert runs.count(kind) == before + 1 and "reusing" in said[-1], said
        (scenes / "light.xml").write_text('<scene version="3.0.0"><emitter type="constant">'
                                          '<rgb name="radiance" value="10"/></emitter></scene>')
        helper(str(xml), progress=said.append)
        assert runs.count(kind) == before + 2, said
        assert said[-1].endswith("was made from other scene files (or records none): running "
                                 "again"), said[-1]


def test_a_bad_notebook_setting_is_named_before_any_work(tmp_path, monkeypatch):
    """A file as PARTPM_NOTEBOOK_OUT is refused by name (it gave mkdir's NotADirectoryError),
    and photons < 1 in the speedup settings by name (it gave a message about the lcm of the
    map counts)."""
    from mi_partpm.experiments import notebook
    from mi_partpm.experiments.speedup import check_speedup
    (tmp_path / "f").write_text("")
    monkeypatch.setenv("PARTPM_NOTEBOOK_OUT", str(tmp_path / "f"))
    with pytest.raises(ValueError, match="PARTPM_NOTEBOOK_OUT must name a folder"):
        notebook.out_dir("speedup_cornell_box")
    with pytest.raises(ValueError, match="photons must be an integer >= 1, got -5"):
        check_speedup([1, 2, 4], -5)
    # hwsim's report on workloads never recorded says which call records them.
    monkeypatch.setenv("PARTPM_NOTEBOOK_OUT", str(tmp_path))
    with pytest.raises(FileNotFoundError, match=r"run speedup\('glossy_spheres'\) first"):
        notebook.hwsim_report("glossy_spheres")
