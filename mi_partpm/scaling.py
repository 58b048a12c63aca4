"""Strong scaling of the MPI backend: the same render on P = 1, 2, ... ranks.

:func:`run_scaling` starts ``mpiexec -n P python -m mi_partpm.cli render ... --backend mpi`` for
each P (with the ``mpiexec`` beside the running Python, i.e. the venv's, else the one on PATH),
reads the figures each run writes with ``--stats-json`` and tabulates time, speedup and
efficiency per P, and the gather's share. Every image is compared with the P = 1 image.
"""
from __future__ import annotations

import csv
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

__all__ = ["find_mpiexec", "run_scaling", "format_scaling"]


def find_mpiexec() -> str:
    """The venv's ``mpiexec`` (from the ``mpich`` wheel), else the first on PATH."""
    beside = Path(sys.executable).parent / "mpiexec"
    if beside.is_file():
        return str(beside)
    found = shutil.which("mpiexec")
    if not found:
        raise FileNotFoundError("no mpiexec found beside Python or on PATH: install MPI with "
                                "'pip install mpi4py mpich' (or load your cluster's MPI)")
    return found


def _median(values):
    return float(np.median(np.asarray(values, dtype=np.float64)))


def run_scaling(scene: str, ranks: Sequence[int], maps: int, out_dir, photons: int = 100_000,
                resolution=(480, 480), spp: int = 4, repeats: int = 3,
                data_dir: Optional[str] = None, mpiexec_args: Sequence[str] = (),
                progress=print, timeout: float = 3600) -> list:
    """Render ``scene`` on each P in ``ranks`` ``repeats`` times; return one row per P.

    Each row holds the medians over the repeats of: the render time (trace, build, estimate
    and gather, as rank 0 measures it; process start-up and scene loading are not counted),
    the slowest rank's trace / build / estimate time, the reduction time and bytes, the
    speedup and efficiency against the first P, and the largest relative pixel difference
    from the first P's image.
    """
    for p in ranks:
        if p < 1 or p > maps:
            raise ValueError(f"every P in --ranks must be in [1, maps = {maps}], got {p}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    mpiexec = find_mpiexec()
    say = progress or (lambda *a: None)
    rows, first_image = [], None
    for p in ranks:
        runs = []
        for rep in range(repeats):
            stem = out / f"P{p}_run{rep}"
            cmd = [mpiexec, *mpiexec_args, "-n", str(p), sys.executable, "-m", "mi_partpm.cli",
                   "render", scene, "--backend", "mpi", "--maps", str(maps), "--photons",
                   str(photons), "--resolution", f"{resolution[0]}x{resolution[1]}", "--spp",
                   str(spp), "-q", "-o", f"{stem}.exr", "--stats-json", f"{stem}.json"]
            if data_dir:
                cmd += ["--data", str(data_dir)]
            say(f"P = {p}, run {rep + 1}/{repeats}: {' '.join(cmd[:4])} ...")
            done = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout,
                                  env=os.environ.copy())
            if done.returncode != 0:
                raise RuntimeError(f"mpiexec -n {p} failed (exit {done.returncode}): "
                                   f"{done.stderr.strip().splitlines()[-1:]}")
            runs.append(json.loads(Path(f"{stem}.json").read_text()))
        image = _read_exr(out / f"P{p}_run0.exr")
        if first_image is None:
            first_image = image
        diff = float(np.max(np.abs(image - first_image) / np.maximum(np.abs(first_image), 1e-3)))
        slowest = {ph: _median([max(r[f"time_{ph}"] for r in run["ranks"]) for run in runs])
                   for ph in ("trace", "build", "estimate")}
        rows.append({
            "ranks": p, "maps": maps, "time_render": _median([r["time_render"] for r in runs]),
            **{f"time_{k}_max": v for k, v in slowest.items()},
            "time_reduce": _median([run["ranks"][0]["time_reduce"] for run in runs]),
            "reduce_bytes_per_rank": runs[0]["ranks"][0]["reduce_bytes"],
            "tree_bytes_max": max(r["map_bytes"] for r in runs[0]["ranks"]),
            "max_rel_diff_vs_first": diff, "repeats": repeats,
        })
    base = rows[0]
    for row in rows:
        row["speedup"] = base["time_render"] / row["time_render"]
        row["efficiency"] = row["speedup"] * base["ranks"] / row["ranks"]
        row["reduce_share"] = row["time_reduce"] / row["time_render"]
    with open(out / "scaling.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    (out / "scaling.json").write_text(json.dumps(rows, indent=2) + "\n")
    return rows


def _read_exr(path) -> np.ndarray:
    import mitsuba as mi
    return np.array(mi.Bitmap(str(path)), dtype=np.float64)


def format_scaling(rows) -> str:
    lines = [f"{'P':>3} {'maps':>5} {'render s':>9} {'speedup':>8} {'effic.':>7} "
             f"{'trace s':>8} {'build s':>8} {'estim s':>8} {'reduce ms':>9} {'reduce KB':>9} "
             f"{'max rel diff':>12}"]
    for r in rows:
        lines.append(f"{r['ranks']:3d} {r['maps']:5d} {r['time_render']:9.2f} "
                     f"{r['speedup']:8.2f} {r['efficiency']:7.2f} {r['time_trace_max']:8.2f} "
                     f"{r['time_build_max']:8.2f} {r['time_estimate_max']:8.2f} "
                     f"{r['time_reduce'] * 1e3:9.2f} {r['reduce_bytes_per_rank'] / 1e3:9.1f} "
                     f"{r['max_rel_diff_vs_first']:12.2e}")
    lines.append("times: medians over repeats; trace/build/estimate: the slowest rank; "
                 "speedup and efficiency against the first P")
    return "\n".join(lines)
