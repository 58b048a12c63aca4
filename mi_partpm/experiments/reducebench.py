"""Micro-benchmark of the one collective the MPI backend does: MPI_Allreduce (sum, float32).

Run under MPI (``mpiexec -n P python -m mi_partpm.experiments.reducebench --out F.json``) or
through :func:`run_reduce_bench`. For every message size it times, on rank 0, the backend's own
:func:`mi_partpm.backends.allreduce_arrays` (``MPI_Allreduce`` after an ``MPI_Barrier``), and with P >= 2 a
ping-pong between ranks 0 and 1 (half the round trip). Medians over the repeats go to a JSON
file that :func:`hwsim.collective.fit_collective` fits.

Two conditions: ``transport`` measures MPI alone; ``in_situ`` first gives every rank Dr.Jit's
thread pool as the backend does (:func:`mi_partpm.backends.share_cores`) and runs a Dr.Jit kernel
before each timed reduction, as the backend's reduction follows its estimate kernels. When the
ranks and their pools oversubscribe the cores, the scheduler then delays the reduction by whole
time slices, which the transport alone never shows. No Mitsuba kernel runs.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from functools import partial
from pathlib import Path
from typing import Sequence

import numpy as np

from ..backends import find_mpiexec

__all__ = ["SIZES", "CONDITIONS", "measure", "run_reduce_bench"]

#: Message sizes in bytes: 4 B to 16 MiB in steps of 4x (a 480x480 RGB image is 2.76 MB).
SIZES = tuple(4 ** i for i in range(1, 13))


CONDITIONS = ("transport", "in_situ")


def _drjit_work(Float):
    """A Dr.Jit kernel on the variant's backend, like the estimate before the backend's
    reduction."""
    import drjit as dr
    x = dr.arange(Float, 1 << 23)
    dr.eval(dr.sum(dr.sin(x) * x))


def measure(comm, sizes: Sequence[int] = SIZES, repeats: int = 15, warmup: int = 2,
            condition: str = "transport", variant: str = "llvm_ad_rgb") -> dict:
    """Median seconds of Reduce and of a one-way ping-pong for each size (on rank 0), of
    arrays of ``variant``'s backend, as the renders of that variant reduce them."""
    import mitsuba as mi
    from ..backends import allreduce_arrays
    if condition not in CONDITIONS:
        raise ValueError(f"condition must be one of {', '.join(CONDITIONS)}, got {condition!r}")
    mi.set_variant(variant)
    Float = mi.Float
    work = None
    if condition == "in_situ":
        from ..backends import share_cores
        share_cores(comm)
        work = partial(_drjit_work, Float)
    out = {"ranks": comm.size, "condition": condition, "variant": variant, "sizes": [],
           "reduce": [], "pingpong": [], "repeats": repeats}
    for size in sizes:
        count = max(1, size // 4)
        send = np.ones(count, dtype=np.float32)
        recv = np.empty_like(send)
        reduce_times, pingpong_times = [], []
        for rep in range(warmup + repeats):
            if work is not None:
                work()
            # The backend's own gather: a barrier, then its MPI_Allreduce timed on its own.
            values = [Float(send)]
            comm.Barrier()
            t0 = time.perf_counter()
            allreduce_arrays(comm, values)
            seconds = time.perf_counter() - t0
            if comm.size > 1:
                comm.Barrier()
                t2 = time.perf_counter()
                if comm.rank == 0:
                    comm.Send(send, dest=1, tag=7)
                    comm.Recv(recv, source=1, tag=8)
                elif comm.rank == 1:
                    comm.Recv(recv, source=0, tag=7)
                    comm.Send(send, dest=0, tag=8)
                t3 = time.perf_counter()
            if rep >= warmup:
                reduce_times.append(seconds)
                if comm.size > 1:
                    pingpong_times.append((t3 - t2) / 2)
        out["sizes"].append(count * 4)
        out["reduce"].append(float(np.median(reduce_times)))
        out["pingpong"].append(float(np.median(pingpong_times)) if pingpong_times else None)
    return out


def run_reduce_bench(ranks: int, out_json, repeats: int = 15, mpiexec_args=(),
                     timeout: float = 600, condition: str = "transport",
                     variant: str = "llvm_ad_rgb") -> dict:
    """Run :func:`measure` on ``ranks`` ranks with the venv's ``mpiexec``; return its JSON."""
    cmd = [find_mpiexec(), *mpiexec_args, "-n", str(ranks), sys.executable, "-m",
           "mi_partpm.experiments.reducebench", "--repeats", str(repeats), "--condition", condition,
           "--variant", variant, "--out", str(out_json)]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout,
                          env=os.environ.copy())
    if done.returncode != 0:
        raise RuntimeError(f"the reduction micro-benchmark on {ranks} ranks failed (exit "
                           f"{done.returncode}): {done.stderr.strip().splitlines()[-1:]}")
    return json.loads(Path(out_json).read_text())


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m mi_partpm.experiments.reducebench",
                                     description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=15)
    parser.add_argument("--condition", choices=CONDITIONS, default="transport")
    parser.add_argument("--variant", default="llvm_ad_rgb",
                        help="Mitsuba variant whose arrays are reduced (default llvm_ad_rgb)")
    parser.add_argument("--out", required=True, help="JSON file written by rank 0")
    args = parser.parse_args(argv)
    if args.repeats < 1:
        parser.error(f"--repeats must be >= 1, got {args.repeats}")
    from ..backends import comm_world
    comm = comm_world()
    result = measure(comm, repeats=args.repeats, condition=args.condition,
                     variant=args.variant)
    if comm.rank == 0:
        Path(args.out).write_text(json.dumps(result, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
