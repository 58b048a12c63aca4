"""What the notebooks in ``notebooks/`` share: the size they run at, where results go, and the
reuse of a finished run.

Each notebook runs an experiment of the paper at one of two sizes, from the environment
variable ``PARTPM_NOTEBOOK_SIZE``:

- ``paper`` (default): the paper's settings, the same as the CLI's defaults;
- ``smoke``: tiny images and photon counts, so that the test suite can execute every notebook.

Results go to ``$PARTPM_NOTEBOOK_OUT`` (default ``../out``, beside the notebooks, which is where
the CLI examples of the README write). A finished run is read back instead of being run again
only when its recorded settings equal the ones asked for AND it was made by the current code
(:func:`~mi_partpm.experiments.provenance.code_version`, a hash of the sources); otherwise it
is run again, and the progress line says why. Delete a run's directory to recompute it anyway.

Every result file a notebook reuses (``speedup.json``, the comparison's ``metrics.json``, the
hwsim report) records the code version that wrote it, in its ``code`` field; a file without
one is run again.
"""
from __future__ import annotations

import json
import os
from dataclasses import asdict
from pathlib import Path

from .calibrate import scene_dir_name
from .provenance import code_version, scene_digest

__all__ = ["SIZES", "size", "out_dir", "compare", "speedup", "hwsim_report", "show"]

SIZES = {
    "paper": {"compare": {"resolution": (480, 480), "spp": 4, "photons": 100_000, "maps": 8,
                          "reference_spp": 2048},
              "speedup": {"maps": (1, 2, 4, 8, 16, 32), "resolution": (480, 480), "spp": 1,
                          "photons": 100_000, "repeats": 3}},
    "smoke": {"compare": {"resolution": (24, 24), "spp": 1, "photons": 10_000, "maps": 4,
                          "reference_spp": 16},
              "speedup": {"maps": (1, 2, 4), "resolution": (24, 24), "spp": 1,
                          "photons": 10_000, "repeats": 1}},
}


def size() -> str:
    """The size the notebooks run at (``PARTPM_NOTEBOOK_SIZE``: paper or smoke)."""
    value = os.environ.get("PARTPM_NOTEBOOK_SIZE", "paper")
    if value not in SIZES:
        raise ValueError(f"PARTPM_NOTEBOOK_SIZE must be one of {', '.join(SIZES)}, got "
                         f"{value!r}")
    return value


def out_dir(name: str) -> Path:
    """Where the run ``name`` lives: ``$PARTPM_NOTEBOOK_OUT/name`` (``smoke/name`` at the smoke
    size, so that a smoke run never replaces a paper-size one)."""
    base = Path(os.environ.get("PARTPM_NOTEBOOK_OUT", "../out"))
    if base.exists() and not base.is_dir():
        raise ValueError(f"PARTPM_NOTEBOOK_OUT must name a folder (relative paths from the "
                         f"notebook's folder), but {base} is a file")
    return base / name if size() == "paper" else base / "smoke" / name


def _same(recorded: dict, wanted: dict) -> bool:
    return all(json.loads(json.dumps(recorded.get(k))) == json.loads(json.dumps(v))
               for k, v in wanted.items())


def _reusable(done: Path, what: str, matches, progress) -> dict | None:
    """The result in ``done`` when ``matches(result)`` (its settings), its scene's files are
    those of the scene now (:func:`~mi_partpm.experiments.provenance.scene_digest`: a user's
    scene file, its includes and meshes) and its code version is the current one; otherwise
    None, after a progress line saying why it is run again."""
    progress = progress or (lambda *a: None)
    if not done.is_file():
        return None
    result = json.loads(done.read_text())
    if not matches(result):
        progress(f"{what}: {done} has other settings: running again")
        return None
    if result.get("scene_sha256") != scene_digest(what):
        progress(f"{what}: {done} was made from other scene files (or records none): "
                 f"running again")
        return None
    current, recorded = code_version(), result.get("code")
    if recorded != current:
        made_by = f"code {recorded}" if recorded else "code of unknown version"
        progress(f"{what}: {done} was made by {made_by}, this is code {current}: "
                 f"running again")
        return None
    progress(f"{what}: reusing {done} (code {current})")
    return result


def compare(scene: str, progress=print) -> dict:
    """pm vs partpm vs path on ``scene`` (``metrics.json`` of :func:`run_compare`)."""
    from .compare import CompareSettings, run_compare
    settings = CompareSettings(scene=scene, **SIZES[size()]["compare"])
    out = out_dir(f"compare_{scene_dir_name(scene)}")
    done = out / "metrics.json"
    wanted = {k: v for k, v in asdict(settings).items() if k not in ("k", "data_dir")}

    def matches(result):
        # k calibrated (None asked), as the paper comparison has it: not a k given by hand
        return _same(result["settings"], wanted) and \
            result.get("calibrated_knn_radius") is not None
    result = _reusable(done, scene, matches, progress)
    if result is None:
        result = run_compare(settings, out, progress=progress)
    result["out"] = str(out)
    return result


#: The speedup experiment's radius (the paper's, 1/20 of the scene).
SPEEDUP_RADIUS_FRACTION = 0.05


def speedup(scene: str, progress=print) -> dict:
    """The speedup experiment on ``scene`` (``speedup.json`` of :func:`run_speedup`)."""
    from .speedup import run_speedup
    s = SIZES[size()]["speedup"]
    out = out_dir(f"speedup_{scene_dir_name(scene)}")
    done = out / "speedup.json"

    def matches(result):
        # the radius and seed of run_speedup's defaults (a run that records neither is older)
        return (out / "workloads" / "meta.json").is_file() and _same(
            result, {"photons_emitted": s["photons"], "resolution": s["resolution"],
                     "spp": s["spp"], "repeats": s["repeats"],
                     "radius_fraction": SPEEDUP_RADIUS_FRACTION, "seed": 0}) and \
            [r["n"] for r in result["rows"]] == list(s["maps"])
    result = _reusable(done, scene, matches, progress)
    if result is None:
        result = run_speedup(scene, s["maps"], out, photons=s["photons"],
                             resolution=s["resolution"], spp=s["spp"], repeats=s["repeats"],
                             radius_fraction=SPEEDUP_RADIUS_FRACTION, seed=0,
                             progress=progress)
    result["out"] = str(out)
    return result


def hwsim_report(scene: str, config=None, check_scene: str | None = None) -> dict:
    """hwsim's report on the workloads of :func:`speedup` for ``scene`` (rerun every time: it
    takes seconds), optionally checking its calibration on ``check_scene``'s workloads."""
    from hwsim.config import HardwareConfig
    from hwsim.report import run_report
    workloads = out_dir(f"speedup_{scene_dir_name(scene)}") / "workloads"
    check = out_dir(f"speedup_{scene_dir_name(check_scene)}") / "workloads" \
        if check_scene else None
    for name, folder in ((scene, workloads), (check_scene, check)):
        if folder is not None and not (folder / "meta.json").is_file():
            raise FileNotFoundError(f"no workloads of {name} in {folder.parent}: run "
                                    f"speedup({name!r}) first")
    out = out_dir(f"hwsim_{scene_dir_name(scene)}")
    result = run_report(workloads, config or HardwareConfig(), out, check, code=code_version())
    result["out"] = str(out)
    return result


def show(path, width: int | None = None, max_png_bytes: int = 300_000):
    """Display an image file in the notebook. A PNG larger than ``max_png_bytes`` (a rendered
    image, not a plot) is shown as a JPEG of quality 90, to keep the saved notebook small."""
    import io

    from IPython.display import Image, display
    path = Path(path)
    if path.suffix.lower() == ".png" and path.stat().st_size > max_png_bytes:
        from PIL import Image as PILImage
        buffer = io.BytesIO()
        PILImage.open(path).convert("RGB").save(buffer, format="JPEG", quality=90)
        display(Image(data=buffer.getvalue(), format="jpeg", width=width))
        return
    display(Image(filename=str(path), width=width))
