"""Strong scaling of the MPI backend: the same render on P = 1, 2, ... ranks.

:func:`run_scaling` starts ``mpiexec -n P python -m mi_partpm.cli render ... --backend mpi`` for
each P (with the ``mpiexec`` beside the running Python, i.e. the venv's, else the one on PATH),
reads the figures each run writes with ``--stats-json`` and tabulates time, speedup and
efficiency per P, and the gather's share. Every image is compared with the P = 1 image.

It then runs the reduction micro-benchmark (:mod:`.reducebench`) on each P, fits its
two-regime alpha-beta lines (:mod:`hwsim.collective`), and predicts each P's render time
from the first P's (P = 1's) CPU seconds per phase and the fitted reduction alone
(:mod:`.mpimodel`); the prediction is then compared with the measured time, out of sample for
every P > 1. ``collective.json`` holds the measurements, the fits and the reduction
extrapolated to larger P under the stated assumptions of :func:`_extrapolate`.
"""
from __future__ import annotations

import csv
import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from hwsim.collective import fit_collective, fit_regimes
from ..backends import find_mpiexec
from .provenance import code_version
from .mpimodel import PhaseWork, predict
from .reducebench import CONDITIONS, run_reduce_bench

__all__ = ["run_scaling", "format_scaling"]


def _median(values):
    return float(np.median(np.asarray(values, dtype=np.float64)))


def _failure(stderr: str) -> str:
    """Why a render under mpiexec failed: the first line a rank wrote as its error (MPI's and
    Dr.Jit's own lines about the abort may follow it); where no rank said one (mpiexec could
    not start them: a host it cannot reach), mpiexec's first line, which says why, and its
    last."""
    lines = [x for x in stderr.strip().splitlines() if x.strip()]
    said = [x.removeprefix("partpm: ") for x in lines if x.startswith("partpm: error")]
    if said:
        return said[0]
    if not lines:
        return "(no message)"
    if len(lines) == 1 or lines[0].startswith("Traceback"):   # a Python error: its last line
        return lines[-1]
    return f"{lines[0]} ... {lines[-1]}"


def run_scaling(scene: str, ranks: Sequence[int], maps: int, out_dir, photons: int = 100_000,
                resolution=(480, 480), spp: int = 4, repeats: int = 3,
                data_dir: Optional[str] = None, mpiexec_args: Sequence[str] = (),
                progress=print, timeout: float = 3600, bench_repeats: int = 15,
                variant: str = "llvm_ad_rgb") -> list:
    """Render ``scene`` on each P in ``ranks`` ``repeats`` times; return one row per P.

    Each row holds the medians over the repeats of: the render time (trace, build, estimate
    and gather, as rank 0 measures it; process start-up and scene loading are not counted),
    the slowest rank's trace / build / estimate time, the reduction time and bytes, the
    speedup and efficiency against P = 1 (``ranks`` must hold 1, and each P once; the
    rows come in increasing P), the largest relative pixel difference from P = 1's image,
    and the version of the code that made it (``code``).
    """
    for p in ranks:
        if p < 1 or p > maps:
            raise ValueError(f"every P in --ranks must be in [1, maps = {maps}], got {p}")
    twice = sorted({p for p in ranks if list(ranks).count(p) > 1})
    if twice:
        raise ValueError(f"--ranks lists {', '.join(map(str, twice))} more than once: give "
                         f"each P once")
    if 1 not in ranks:
        raise ValueError(f"--ranks must include 1: speedups, efficiencies and the model's "
                         f"predictions are against one rank (got {','.join(map(str, ranks))})")
    ranks = sorted(ranks)                        # P = 1 first: the rows' base
    if maps > photons:
        raise ValueError(f"--maps {maps} is more than --photons {photons}: every map needs at "
                         f"least one photon")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    mpiexec = find_mpiexec()
    say = progress or (lambda *a: None)
    rows, first_image, p1_stats = [], None, []
    for p in ranks:
        runs = []
        for rep in range(repeats):
            stem = out / f"P{p}_run{rep}"
            cmd = [mpiexec, *mpiexec_args, "-n", str(p), sys.executable, "-m", "mi_partpm.cli",
                   "render", scene, "--backend", "mpi", "--maps", str(maps), "--photons",
                   str(photons), "--resolution", f"{resolution[0]}x{resolution[1]}", "--spp",
                   str(spp), "--variant", variant, "-q", "-o", f"{stem}.exr", "--stats-json",
                   f"{stem}.json"]
            if data_dir:
                cmd += ["--data", str(data_dir)]
            say(f"P = {p}, run {rep + 1}/{repeats}: mpiexec -n {p} partpm render {scene} ...")
            done = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout,
                                  env=os.environ.copy())
            if done.returncode != 0:
                raise RuntimeError(f"mpiexec -n {p} failed (exit {done.returncode}): "
                                   f"{_failure(done.stderr)}")
            runs.append(json.loads(Path(f"{stem}.json").read_text()))
        image = _read_exr(out / f"P{p}_run0.exr")
        if first_image is None:
            first_image = image
        diff = float(np.max(np.abs(image - first_image) / np.maximum(np.abs(first_image), 1e-3)))
        slowest = {ph: _median([max(r[f"time_{ph}"] for r in run["ranks"]) for run in runs])
                   for ph in ("trace", "build", "eye", "estimate")}
        compute = _median([max(r["time_trace"] + r["time_build"] + r["time_eye"]
                               + r["time_estimate"] for r in run["ranks"]) for run in runs])
        if not rows:
            p1_stats = [_rank0_stats(run) for run in runs]
        rows.append({
            "ranks": p, "maps": maps, "time_render": _median([r["time_render"] for r in runs]),
            **{f"time_{k}_max": v for k, v in slowest.items()},
            "time_reduce": _median([run["ranks"][0]["time_reduce"] for run in runs]),
            "reduce_bytes_per_rank": runs[0]["ranks"][0]["reduce_bytes"],
            "tree_bytes_max": max(r["map_bytes"] for r in runs[0]["ranks"]),
            "max_rel_diff_vs_first": diff, "repeats": repeats, "time_compute_max": compute,
            "code": code_version(),
        })
    base = rows[0]
    for row in rows:
        row["speedup"] = base["time_render"] / row["time_render"]
        row["efficiency"] = row["speedup"] * base["ranks"] / row["ranks"]
        row["reduce_share"] = row["time_reduce"] / row["time_render"]
    if bench_repeats > 0:
        _predict(rows, out, mpiexec_args, bench_repeats, say, timeout, p1_stats, variant)
    with open(out / "scaling.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    (out / "scaling.json").write_text(json.dumps(rows, indent=2) + "\n")
    return rows


#: P of the extrapolated reduction times in collective.json.
EXTRAPOLATE_RANKS = (2, 4, 8, 16, 32, 64, 128, 256, 512, 1024)


def _rank0_stats(run: dict) -> dict:
    """Rank 0's figures of one render's ``--stats-json``, with the render's wall time."""
    stats = dict(run["ranks"][0])
    stats["time_render"] = run["time_render"]
    return stats


def _phase_work(p1_stats) -> PhaseWork:
    """The first P's work per phase: medians over its repeats."""
    works = [PhaseWork.from_stats(s, os.cpu_count() or 1) for s in p1_stats]
    first = works[0]
    return PhaseWork(cpu={ph: _median([w.cpu[ph] for w in works]) for ph in first.cpu},
                     wall=_median([w.wall for w in works]), maps=first.maps,
                     passes=first.passes, cores=first.cores,
                     overhead=_median([w.overhead for w in works]))


def _predict(rows, out, mpiexec_args, repeats, say, timeout, p1_stats, variant):
    """Micro-benchmark the reduction on every P in both conditions and fit it; predict each
    row's reduction (transport alone and in situ) and, from the first P's work per phase and
    the transport fit alone, its render time (:mod:`.mpimodel`)."""
    info = {}
    transport = {}
    for condition in CONDITIONS:
        benches, fits = {}, {}
        for row in rows:
            p = row["ranks"]
            say(f"P = {p}: reduction micro-benchmark ({condition}) ...")
            benches[p] = run_reduce_bench(p, out / f"reducebench_{condition}_P{p}.json",
                                          repeats, mpiexec_args, timeout, condition, variant)
            fits[p] = fit_regimes(benches[p]["sizes"], benches[p]["reduce"])
            row[f"time_reduce_pred_{condition}"] = fits[p](row["reduce_bytes_per_rank"])
        if condition == "transport":
            transport = fits
        entry = {"benchmarks": benches, "reduce_fits": {p: f.as_dict() for p, f in fits.items()}}
        multi = [p for p in benches if p >= 2]
        if multi:
            entry.update(_extrapolate(benches[max(multi)], rows[0]["reduce_bytes_per_rank"]))
        info[condition] = entry
    work = _phase_work(p1_stats) if p1_stats and rows[0]["ranks"] == 1 else None
    for row in rows:
        if work is None:
            continue
        pred = predict(work, row["ranks"], transport[row["ranks"]], row["reduce_bytes_per_rank"])
        row["time_render_pred"] = pred["render"]
        row["time_compute_pred"] = pred["compute"]
        row["render_pred_rel_error"] = row["time_render_pred"] / row["time_render"] - 1.0
        row["render_pred_out_of_sample"] = row["ranks"] != 1
    info["model"] = {"p1_work": work.__dict__ if work else None,
                     "efficiency_p1": work.efficiency if work else None}
    (out / "collective.json").write_text(json.dumps(info, indent=2) + "\n")


def _extrapolate(bench: dict, nbytes: int) -> dict:
    """The alpha-beta(-gamma) model fitted to the largest P benchmarked, and the image's
    reduction extrapolated to :data:`EXTRAPOLATE_RANKS`. It assumes that every link of a
    larger job has this node's latency and bandwidth (one node's shared-memory transport,
    not a cluster network), that MPICH reduces along a binomial tree of log2(P) steps, and
    that nothing else competes for the links: a lower bound for a cluster, whose own alpha
    and beta the same command measures there."""
    model = fit_collective(bench)
    alpha, beta, gamma = model.alpha_beta_gamma(nbytes)
    return {"collective": model.as_dict(),
            "image": {"bytes": nbytes, "alpha": alpha, "beta": beta, "gamma": gamma,
                      "assumes": "this node's alpha and beta on every link, a binomial "
                                 "tree, no contention",
                      "reduce_seconds": {q: model.reduce_seconds(q, nbytes)
                                         for q in EXTRAPOLATE_RANKS}}}


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
    if "time_render_pred" in rows[0]:
        lines.append("predicted: the reduction from the micro-benchmark's alpha-beta fits "
                     "(transport alone; in situ, beside Dr.Jit's thread pool); the render "
                     "from the first P's CPU seconds per phase and the transport fit alone "
                     "(out of sample for every other P):")
        lines.append(f"{'P':>3} {'reduce ms':>9} {'transport':>9} {'in situ':>9} "
                     f"{'render s':>9} {'predicted':>9} {'error':>7}")
        for r in rows:
            lines.append(f"{r['ranks']:3d} {r['time_reduce'] * 1e3:9.2f} "
                         f"{r['time_reduce_pred_transport'] * 1e3:9.2f} "
                         f"{r['time_reduce_pred_in_situ'] * 1e3:9.2f} {r['time_render']:9.2f} "
                         f"{r['time_render_pred']:9.2f} "
                         f"{r['render_pred_rel_error'] * 100:+6.2f}%")
    return "\n".join(lines)
