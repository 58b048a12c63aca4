"""``partpm figures``: every table and figure of the README and the notebooks, from the
current code, with a record of the commit and the machine that made them.

The pipeline is a list of named steps (:func:`steps`), each one ``partpm`` command with its
own folder under the output directory (``out/figures`` by default):

- ``demo``: the Cornell box of ``make demo``;
- ``compare_*``: pm vs partpm vs path on the Cornell box, the Happy Buddha and the glossy
  spheres, at the paper's settings with a 2048-spp reference;
- ``speedup_*``: the speedup experiment on both paper scenes at the paper's size, and the
  wide runs (n up to 1024 maps at 128 x 128, one repeat);
- ``hwsim_*``: the PE-array simulator on those workloads (calibration checked across scenes);
- ``bench``, ``scaling_cornell_box`` (MPI, 1 and 2 ranks);
- ``converge_*``: error against time on the Cornell box, the caustic glass and the diffuse
  Cornell box (25 s each; on both Cornell boxes the photon mappers again with direct light
  by emitter sampling, ``--direct nee``, against the same reference), and a 150-s
  progressive run of partpm alone (its error after 4 and 64 passes);
- ``notebooks``: the three notebooks executed at the paper's size and saved with their
  outputs; they read the runs above back instead of running them again.

A step is **reused** when its folder holds the result it would make: a result file that
records the current :func:`~.provenance.code_version`, beside a ``step.json`` saying that
this step's command (the same settings) wrote exactly that file (its SHA-256), from inputs
(the results of the steps it reads) that have not changed since. Otherwise it runs again,
and the progress line says why. Each step's output is also logged to ``step.log``.

Then the step's plots are copied to ``docs/images/`` under the names the README uses, the
README's generated blocks (:mod:`.readme`) are rewritten from the results, and
``docs/figures.json`` records per step the command, code version, commit, machine, date and
seconds taken. ``smoke=True`` runs the same pipeline at tiny sizes and writes nothing into
``docs/``, ``notebooks/`` or ``README.md``: the README copy, the images, the executed
notebooks and the provenance go into the output directory.
"""
from __future__ import annotations

import contextlib
import datetime
import hashlib
import json
import os
import shlex
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Sequence, Tuple

from . import provenance, readme

__all__ = ["Step", "steps", "run_figures", "NOTEBOOKS", "SIDECAR"]

ROOT = Path(__file__).resolve().parents[2]

#: The record beside each step's result: the command that wrote it and where it ran.
SIDECAR = "step.json"

#: The notebooks the ``notebooks`` step executes (in ``notebooks/``).
NOTEBOOKS = ("01_image_comparison.ipynb", "02_speedup.ipynb", "03_hwsim.ipynb")

PAPER_SCENES = ("cornell_box", "happy_buddha")
COMPARE_SCENES = PAPER_SCENES + ("glossy_spheres",)
CONVERGE_SCENES = ("cornell_box", "caustic_glass", "cornell_box_diffuse")
#: The converge scenes run a second time with direct light by emitter sampling (step
#: ``converge_<scene>_nee``: the photon mappers only, against the first run's reference).
CONVERGE_NEE_SCENES = ("cornell_box", "cornell_box_diffuse")


@dataclass(frozen=True)
class Step:
    """One command of the pipeline.

    ``args`` are ``partpm``'s arguments, ``{out}`` standing for the output directory;
    ``result`` the JSON file (in the step's folder ``{out}/name``) that records the code
    version; ``needs`` the steps whose results this one reads; ``images`` (file in the
    step's folder, name in ``docs/images``); ``reference_from`` a step whose cached path
    reference (``reference.exr``, reused only when its settings match) may be copied first.
    """

    name: str
    args: Tuple[str, ...]
    result: str
    needs: Tuple[str, ...] = ()
    images: Tuple[Tuple[str, str], ...] = ()
    reference_from: Optional[str] = None
    kind: str = "partpm"          # or "notebooks"

    @property
    def group(self) -> str:
        return self.name.split("_")[0]

    def command(self, out: str) -> list:
        return [a.replace("{out}", out) for a in self.args]

    def display(self, out: str) -> str:
        if self.kind == "notebooks":
            return "nbclient: notebooks/" + ", ".join(NOTEBOOKS)
        return "partpm " + shlex.join(self.command(out))


#: The settings of each experiment: the README's (paper) and tiny ones (smoke).
SIZES = {
    "paper": {
        "demo": ("--maps", "8", "--photons", "100000", "--resolution", "480x480"),
        "compare": ("--reference-spp", "2048"),
        "speedup": ("--maps", "1,2,4,8,16,32"),
        "speedup_wide": ("--maps", "1,2,4,8,16,32,64,128,256,512,1024", "--resolution",
                         "128x128", "--repeats", "1"),
        "bench": (),
        "scaling": ("--ranks", "1,2,4", "--maps", "8"),
        "converge": ("--time", "25"),
        "converge_long": ("--time", "150", "--methods", "partpm"),
        "large": {"1e7": ("--photons", "10000000", "--maps", "8"),
                  "1e8": ("--photons", "100000000", "--maps", "64")},
        # Most of the Buddha's photons leave its open scene: 6x the Cornell box's 10^5
        # store about as many (3 x 10^5), so both fits span the same map sizes, on which
        # the costs depend through the caches.
        "calibrate": ("--repeats", "7", "--photons", "100000,600000"),
    },
    "smoke": {
        "demo": ("--maps", "2", "--photons", "2000", "--resolution", "32x32", "--spp", "1"),
        "compare": ("--resolution", "24x24", "--spp", "1", "--photons", "10000", "--maps",
                    "4", "--reference-spp", "16"),
        "speedup": ("--maps", "1,2,4", "--photons", "2000", "--resolution", "24x24",
                    "--repeats", "1"),
        "speedup_wide": ("--maps", "1,2,4,8", "--photons", "4000", "--resolution", "16x16",
                         "--repeats", "1"),
        "bench": ("--smoke",),
        "scaling": ("--ranks", "1,2", "--maps", "2", "--photons", "4000", "--resolution",
                    "16x16", "--spp", "1", "--repeats", "1", "--bench-repeats", "3"),
        "converge": ("--time", "0.5", "--resolution", "24x24", "--photons", "2000",
                     "--reference-spp", "16"),
        "converge_long": ("--time", "1", "--methods", "partpm", "--resolution", "24x24",
                          "--photons", "2000", "--reference-spp", "16"),
        "large": {"1e7": ("--photons", "20000", "--maps", "2"),
                  "1e8": ("--photons", "40000", "--maps", "4")},
        "calibrate": ("--leaf-sizes", "4,16", "--radius-fractions", "0.05,0.1", "--maps",
                      "1,2", "--photons", "4000", "--resolution", "16x16", "--repeats", "2"),
    },
}


def steps(smoke: bool = False) -> list:
    """Every step, in the order they run (a step after the steps it reads)."""
    z = SIZES["smoke" if smoke else "paper"]
    out = [Step("demo", ("render", "cornell_box", *z["demo"], "-o", "{out}/demo/cornell_box.exr",
                         "--stats-json", "{out}/demo/stats.json"), "stats.json",
                images=(("cornell_box.png", "cornell_box_partpm_8maps.png"),))]
    for scene in PAPER_SCENES:
        out.append(Step(f"speedup_{scene}", ("speedup", scene, *z["speedup"], "--out",
                                             f"{{out}}/speedup_{scene}"), "speedup.json",
                        images=(("speedup.png", f"speedup_{scene}.png"),)))
    for scene in PAPER_SCENES:
        out.append(Step(f"speedup_wide_{scene}", ("speedup", scene, *z["speedup_wide"], "--out",
                                                  f"{{out}}/speedup_wide_{scene}"),
                        "speedup.json"))
    for scene, other in (PAPER_SCENES, PAPER_SCENES[::-1]):
        out.append(Step(f"hwsim_{scene}", ("hwsim", f"{{out}}/speedup_{scene}/workloads",
                                           "--check", f"{{out}}/speedup_{other}/workloads",
                                           "--out", f"{{out}}/hwsim_{scene}"), "report.json",
                        needs=(f"speedup_{scene}", f"speedup_{other}"),
                        images=(("hwsim.png", f"hwsim_{scene}.png"),) if scene == "cornell_box"
                        else ()))
    out.append(Step("hwsim_wide_cornell_box", (
        "hwsim", "{out}/speedup_wide_cornell_box/workloads", "--check",
        "{out}/speedup_wide_happy_buddha/workloads", "--out", "{out}/hwsim_wide_cornell_box"),
        "report.json", needs=("speedup_wide_cornell_box", "speedup_wide_happy_buddha"),
        images=(("hwsim.png", "hwsim_cornell_box_1024.png"),)))
    out.append(Step("hwsim_wide_happy_buddha", (
        "hwsim", "{out}/speedup_wide_happy_buddha/workloads", "--out",
        "{out}/hwsim_wide_happy_buddha"), "report.json", needs=("speedup_wide_happy_buddha",),
        images=(("hwsim.png", "hwsim_happy_buddha_1024.png"),)))
    for scene in COMPARE_SCENES:
        out.append(Step(f"compare_{scene}", ("compare", scene, *z["compare"], "--out",
                                             f"{{out}}/compare_{scene}"), "metrics.json",
                        images=(("comparison.png", f"compare_{scene}.png"),)))
    for scene in CONVERGE_SCENES:
        out.append(Step(f"converge_{scene}", ("converge", scene, *z["converge"], "--out",
                                              f"{{out}}/converge_{scene}"), "converge.json",
                        images=(("converge.png", f"converge_{scene}.png"),)))
    for scene in CONVERGE_NEE_SCENES:
        out.append(Step(f"converge_{scene}_nee", (
            "converge", scene, *z["converge"], "--direct", "nee", "--methods", "partpm,pm",
            "--out", f"{{out}}/converge_{scene}_nee"), "converge.json",
            reference_from=f"converge_{scene}"))
    out.append(Step("converge_cornell_box_long", (
        "converge", "cornell_box", *z["converge_long"], "--out",
        "{out}/converge_cornell_box_long"), "converge.json",
        images=(("converge.png", "converge_cornell_box_long.png"),),
        reference_from="converge_cornell_box"))
    out.append(Step("scaling_cornell_box", ("scaling", "cornell_box", *z["scaling"], "--out",
                                            "{out}/scaling_cornell_box"), "scaling.json"))
    out.append(Step("bench", ("bench", *z["bench"], "--out", "{out}/bench/bench.json"),
                    "bench.json"))
    # Costs fitted to workloads of several leaf sizes and radii, both scenes timed in one
    # run, each predicting the other.
    out.append(Step("calibrate", ("calibrate", *PAPER_SCENES, *z["calibrate"],
                                  "--out", "{out}/calibrate"), "calibration.json"))
    for size, names in readme.large_steps().items():
        # Large photon counts in waves of maps: time and peak memory per stored photon. A
        # single render's phase times vary by 15% from run to run on a shared machine, so
        # the size that holds the build-against-trace goal is rendered 3 times
        # (readme.LARGE_RUNS).
        for name in names:
            out.append(Step(name, ("render", "cornell_box", *z["large"][size], "--spp", "1",
                                   "--resolution", "480x480", "--radius-fraction", "0.01",
                                   "-o", f"{{out}}/{name}/cornell_box.exr",
                                   "--stats-json", f"{{out}}/{name}/stats.json"),
                            "stats.json"))
    out.append(Step("notebooks", (), "notebooks.json", kind="notebooks",
                    needs=tuple(f"{e}_{s}" for e in ("compare", "speedup", "hwsim")
                                for s in PAPER_SCENES)))
    return out


def _sha256(path: Path) -> Optional[str]:
    try:
        return hashlib.sha256(path.read_bytes()).hexdigest()
    except OSError:
        return None


def _now() -> str:
    return datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")


def recorded_code(result) -> Optional[str]:
    """The code version a result file records: its ``code``, or the one ``code`` of all its
    rows when it is a list of rows (``scaling.json``)."""
    if isinstance(result, dict):
        return result.get("code")
    if isinstance(result, list) and result and all(isinstance(r, dict) for r in result):
        codes = {r.get("code") for r in result}
        return codes.pop() if len(codes) == 1 else None
    return None


@contextlib.contextmanager
def _environ(**values):
    """``os.environ`` with ``values`` set, as it was afterwards."""
    old = {k: os.environ.get(k) for k in values}
    os.environ.update(values)
    try:
        yield
    finally:
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


class _Pipeline:
    """One run of ``partpm figures``: where things go, what is current, what ran."""

    def __init__(self, out: Path, smoke: bool, say, verbose: bool, root: Path):
        self.root, self.smoke, self.say, self.verbose = root, smoke, say, verbose
        self.out = out
        try:
            self.out_text = str(out.resolve().relative_to(root.resolve()))
        except ValueError:
            self.out_text = str(out.resolve())
        self.steps = {s.name: s for s in steps(smoke)}
        self.code = provenance.code_version()
        self.commit = provenance.git_commit()
        self.machine = provenance.machine()
        self.state = {}         # step name -> {"status", "reason", "info"}
        self.block_errors = {}  # block name -> why it could not be formatted
        if smoke:
            self.readme_in, self.readme_out = root / "README.md", out / "README.md"
            self.images, self.prefix = out / "images", "images/"
            self.record, self.notebooks_out = out / "figures.json", out / "notebooks"
        else:
            self.readme_in = self.readme_out = root / "README.md"
            self.images, self.prefix = root / "docs" / "images", "docs/images/"
            self.record, self.notebooks_out = root / "docs" / "figures.json", root / "notebooks"

    # -- what is current ----------------------------------------------------------------

    def folder(self, step: Step) -> Path:
        return self.out / step.name

    def result_path(self, step: Step) -> Path:
        return self.folder(step) / step.result

    def inputs(self, step: Step) -> dict:
        return {dep: _sha256(self.result_path(self.steps[dep])) for dep in step.needs}

    def current(self, step: Step):
        """(True, info) when the step's folder holds what it would make, else (False, why)."""
        path = self.result_path(step)
        if not path.is_file():
            return False, "no result yet"
        try:
            result = json.loads(path.read_text())
        except ValueError:
            return False, f"{path.name} does not parse"
        recorded = recorded_code(result)
        if recorded is None:
            return False, f"{path.name} records no code version"
        if recorded != self.code:
            return False, f"made by code {recorded}, this is code {self.code}"
        try:
            info = json.loads((self.folder(step) / SIDECAR).read_text())
        except (OSError, ValueError):
            return False, f"no record ({SIDECAR}) of the command that made it"
        if info.get("settings") != list(step.args):
            return False, f"made with other settings ({info.get('command', '?')})"
        if info.get("result_sha256") != _sha256(path):
            return False, f"{path.name} was rewritten since this step made it"
        for dep, sha in self.inputs(step).items():
            if info.get("inputs", {}).get(dep) != sha:
                return False, f"its input {dep} changed since"
        if step.kind == "notebooks":
            for name, sha in result.get("notebooks", {}).items():
                if _sha256(self.notebooks_out / name) != sha:
                    return False, f"{name} changed since it was executed"
        return True, info

    # -- running ------------------------------------------------------------------------

    def run(self, step: Step, label: str):
        for dep in step.needs:
            if self.state.get(dep, {}).get("status") in ("failed", "skipped"):
                self.state[step.name] = {"status": "skipped", "reason": f"needs {dep}, which "
                                         f"{self.state[dep]['status']}"}
                self.say(f"{label} {step.name}: skipped (needs {dep})")
                return
        ok, info = self.current(step)
        if ok:
            self.state[step.name] = {"status": "reused", "info": info}
            self.say(f"{label} {step.name}: reusing {self.out_text}/{step.name}/{step.result} "
                     f"(code {self.code}, made {info.get('date', '?')[:10]})")
            return
        self.say(f"{label} {step.name}: running ({info}): {step.display(self.out_text)}")
        folder = self.folder(step)
        folder.mkdir(parents=True, exist_ok=True)
        (folder / SIDECAR).unlink(missing_ok=True)
        start = time.perf_counter()
        try:
            error = (self._notebooks() if step.kind == "notebooks"
                     else self._partpm(step, folder))
        except Exception as e:          # a step's failure must not stop the others
            error = f"{type(e).__name__}: {e}"
        seconds = time.perf_counter() - start
        result = self.result_path(step)
        if error is None and not result.is_file():
            error = f"it wrote no {step.result}"
        if error is not None:
            self.state[step.name] = {"status": "failed", "reason": error, "seconds": seconds}
            self.say(f"{label} {step.name}: FAILED after {seconds:.1f} s: {error}")
            return
        code = recorded_code(json.loads(result.read_text()))
        if code != self.code:
            self.say(f"{label} {step.name}: warning: its result records code {code}, but this "
                     f"run started at code {self.code}: the sources changed while it ran")
        info = {"step": step.name, "settings": list(step.args),
                "command": step.display(self.out_text), "code": code, "commit": self.commit,
                "machine": self.machine, "date": _now(), "seconds": round(seconds, 2),
                "result": step.result, "result_sha256": _sha256(result),
                "inputs": self.inputs(step)}
        (folder / SIDECAR).write_text(json.dumps(info, indent=2) + "\n")
        self.state[step.name] = {"status": "ran", "info": info}
        self.say(f"{label} {step.name}: done in {seconds:.1f} s")

    def _partpm(self, step: Step, folder: Path) -> Optional[str]:
        """Run the step's command; None, or why it failed."""
        if step.reference_from:
            source = self.folder(self.steps[step.reference_from])
            for name in ("reference.exr", "reference.json"):
                if (source / name).is_file() and not (folder / name).is_file():
                    shutil.copy2(source / name, folder / name)
        cmd = [sys.executable, "-m", "mi_partpm.cli", *step.command(self.out_text)]
        tail = []
        with open(folder / "step.log", "w") as log, subprocess.Popen(
                cmd, cwd=self.root, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                text=True, bufsize=1) as proc:
            for line in proc.stdout:
                log.write(line)
                log.flush()
                tail = (tail + [line.rstrip()])[-5:]
                if self.verbose:
                    self.say(f"    {line.rstrip()}")
        if proc.returncode != 0:
            last = next((t for t in reversed(tail) if t.strip()), "")
            return (f"exit status {proc.returncode}: {last} (all of its output: "
                    f"{self.out_text}/{step.name}/step.log)")
        return None

    def _notebooks(self) -> Optional[str]:
        """Execute the notebooks (saved in place, or into the output directory with smoke);
        they share this run's results through ``PARTPM_NOTEBOOK_OUT``."""
        try:
            import nbclient
            import nbformat
        except ImportError as e:
            return f"{e.name} is missing: pip install -e '.[test]'"
        source = self.root / "notebooks"
        self.notebooks_out.mkdir(parents=True, exist_ok=True)
        # Relative to notebooks/, where the kernel runs, so their outputs name no machine path.
        base = os.path.relpath(self.out.resolve(), source.resolve())
        hashes = {}
        with _environ(PARTPM_NOTEBOOK_SIZE="smoke" if self.smoke else "paper",
                      PARTPM_NOTEBOOK_OUT=base):
            for name in NOTEBOOKS:
                self.say(f"    executing {name} ...")
                notebook = nbformat.read(source / name, as_version=4)
                for cell in notebook.cells:
                    if cell.cell_type == "code":
                        cell.outputs = []
                        cell.execution_count = None
                nbclient.NotebookClient(notebook, timeout=None, kernel_name="python3",
                                        resources={"metadata": {"path": str(source)}}).execute()
                nbformat.write(notebook, self.notebooks_out / name)
                hashes[name] = _sha256(self.notebooks_out / name)
        (self.out / "notebooks").mkdir(parents=True, exist_ok=True)
        (self.out / "notebooks" / "notebooks.json").write_text(json.dumps(
            {"code": self.code, "size": "smoke" if self.smoke else "paper",
             "notebooks": hashes}, indent=2) + "\n")
        return None

    # -- after the steps ----------------------------------------------------------------

    def done(self, name: str) -> Optional[dict]:
        """The sidecar of a step whose result is current (run or reused now, or current
        without being selected), else None."""
        state = self.state.get(name)
        if state is None:
            ok, info = self.current(self.steps[name])
            state = self.state[name] = ({"status": "current", "info": info} if ok else
                                        {"status": "not run", "reason": info})
        return state.get("info") if state["status"] in ("ran", "reused", "current") else None

    def copy_images(self, selected) -> list:
        copied = []
        for name in selected:
            if self.done(name) is None:
                continue
            for src, dst in self.steps[name].images:
                if (self.folder(self.steps[name]) / src).is_file():
                    self.images.mkdir(parents=True, exist_ok=True)
                    shutil.copyfile(self.folder(self.steps[name]) / src, self.images / dst)
                    copied.append(dst)
        return copied

    def blocks(self, selected) -> dict:
        """Markdown of every block made from a selected step whose inputs are all current."""
        contents = {}
        for block in readme.BLOCKS.values():
            if not set(block.steps) & set(selected):
                continue
            infos = {s: self.done(s) for s in block.steps}
            missing = [s for s, info in infos.items() if info is None]
            if missing:
                self.say(f"README block {block.name}: left as it was ({', '.join(missing)} "
                         f"not current)")
                continue
            results = {s: json.loads(self.result_path(self.steps[s]).read_text())
                       for s in block.steps}
            try:
                kwargs = {"images": self.prefix} if block.images else {}
                body = block.format(results, **kwargs)
            except (KeyError, IndexError, TypeError, ValueError) as e:
                self.block_errors[block.name] = repr(e)
                self.say(f"README block {block.name}: FAILED to format: {e!r}")
                continue
            cited = [infos[s] for s in block.note_steps]
            note = readme.note([i["command"] for i in cited],
                               [i.get("commit", "") for i in cited],
                               [i.get("date", "") for i in cited],
                               [readme.machine_summary(i.get("machine", {})) for i in cited],
                               made_by="partpm figures --smoke" if self.smoke
                               else "make figures")
            contents[block.name] = body + "\n\n" + note
        return contents

    def write_record(self, selected, blocks, started: str, argv: str):
        try:
            record = json.loads(self.record.read_text())
        except (OSError, ValueError):
            record = {}
        entries = record.get("steps", {})
        for name in selected:
            state = self.state[name]
            step = self.steps[name]
            info = state.get("info") or {}
            entry = {"command": step.display(self.out_text), "status": state["status"]}
            if info:
                entry.update({k: info.get(k) for k in ("code", "commit", "date", "seconds")})
                entry["machine"] = info.get("machine")
            else:
                entry.update({"reason": state.get("reason"), "code": None,
                              "commit": self.commit, "date": started,
                              "seconds": round(state.get("seconds", 0.0), 2),
                              "machine": self.machine})
            entries[name] = entry
        done_blocks = record.get("blocks", {})
        for name in blocks:
            done_blocks[name] = {"steps": list(readme.BLOCKS[name].steps), "date": started}
        record.update({"command": argv, "date": started, "code": self.code,
                       "commit": self.commit, "machine": self.machine,
                       "out": self.out_text, "smoke": self.smoke,
                       "steps": {k: entries[k] for k in self.steps if k in entries},
                       "blocks": done_blocks})
        self.record.parent.mkdir(parents=True, exist_ok=True)
        self.record.write_text(json.dumps(record, indent=2) + "\n")


def _select(all_steps: dict, only: Optional[Sequence[str]]) -> list:
    """The steps ``only`` names (step names or groups: the steps' names up to the first
    underscore, demo, speedup, hwsim, ... large, notebooks) and the steps they read, in
    pipeline order."""
    if not only:
        return list(all_steps)
    groups = {}
    for s in all_steps.values():
        groups.setdefault(s.group, []).append(s.name)
    wanted = set()
    for token in only:
        if token in all_steps:
            wanted.add(token)
        elif token in groups:
            wanted.update(groups[token])
        else:
            raise ValueError(f"--only: no step or group {token!r}; steps: "
                             f"{', '.join(all_steps)}; groups: {', '.join(groups)}")
    todo = list(wanted)
    while todo:
        for dep in all_steps[todo.pop()].needs:
            if dep not in wanted:
                wanted.add(dep)
                todo.append(dep)
    return [name for name in all_steps if name in wanted]


def run_figures(out=None, only: Optional[Sequence[str]] = None, smoke: bool = False,
                list_only: bool = False, progress=print, verbose: bool = True,
                root: Path = ROOT, argv: str = "partpm figures") -> int:
    """Run the pipeline (or with ``list_only`` say what it would do); 0 when every selected
    step and block succeeded, 1 otherwise."""
    say = progress or (lambda *a: None)
    if out is None:
        out = (Path(tempfile.mkdtemp(prefix="partpm-figures-")) if smoke
               else root / "out" / "figures")
    out = Path(out)
    p = _Pipeline(out, smoke, say, verbose, root)
    selected = _select(p.steps, only)
    if list_only:
        for name in selected:
            step = p.steps[name]
            ok, info = p.current(step)
            needs = f" (reads {', '.join(step.needs)})" if step.needs else ""
            say(f"{name}: {'reuse' if ok else 'run: ' + info}{needs}\n    "
                f"{step.display(p.out_text)}")
        for block in readme.BLOCKS.values():
            say(f"README block {block.name}: from {', '.join(block.steps)}")
        return 0
    started = _now()
    _claim(out, smoke)
    say(f"figures: code {p.code}, commit {p.commit or 'unknown'}, "
        f"{readme.machine_summary(p.machine)}; results in {p.out_text}/"
        f"{' (smoke sizes)' if smoke else ''}")
    if only:
        extra = [n for n in selected if n not in only and p.steps[n].group not in only]
        if extra:
            say(f"figures: also the steps they read: {', '.join(extra)} (reused when current)")
    for i, name in enumerate(selected):
        p.run(p.steps[name], f"[{i + 1}/{len(selected)}]")
    copied = p.copy_images(selected)
    if copied:
        say(f"images: {len(copied)} copied into {_show(p.images, root)}/ "
            f"({', '.join(copied)})")
    contents = p.blocks(selected)
    text = p.readme_in.read_text()
    for name in list(contents):
        try:
            readme.replace_blocks(text, {name: contents[name]})
        except readme.BlockError as e:      # the others are still written
            p.block_errors[name] = str(e)
            say(f"README block {name}: not written: {e}")
            del contents[name]
    if contents:
        text = readme.replace_blocks(text, contents)
        p.readme_out.parent.mkdir(parents=True, exist_ok=True)
        p.readme_out.write_text(text)
        say(f"{_show(p.readme_out, root)}: regenerated blocks {', '.join(contents)}")
    elif smoke and not p.readme_out.exists():
        shutil.copyfile(p.readme_in, p.readme_out)
    p.write_record(selected, contents, started, argv)
    say(f"provenance: {_show(p.record, root)}")
    failed = [n for n in selected if p.state[n]["status"] in ("failed", "skipped")]
    failed += [f"README block {b}" for b in p.block_errors]
    if failed:
        say(f"figures: {len(failed)} failed or skipped: {', '.join(failed)}")
        return 1
    return 0


#: In the output directory: which sizes its runs are (a smoke run never replaces a full one).
SIZE_FILE = ".partpm-figures.json"


def _claim(out: Path, smoke: bool):
    """Make ``out`` this run's, refusing one that holds the runs of the other size."""
    size = "smoke" if smoke else "paper"
    try:
        held = json.loads((out / SIZE_FILE).read_text()).get("size")
    except (OSError, ValueError):
        held = None
    if held not in (None, size):
        raise ValueError(f"{out} holds the {held}-size runs of 'partpm figures'; a {size} "
                         f"run would replace them: give it another --out")
    out.mkdir(parents=True, exist_ok=True)
    (out / SIZE_FILE).write_text(json.dumps({"size": size}) + "\n")


def _show(path: Path, root: Path) -> str:
    try:
        return str(path.resolve().relative_to(root.resolve()))
    except ValueError:
        return str(path)
