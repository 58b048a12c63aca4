"""The ``partpm`` command.

    partpm render SCENE [options] -o OUT.exr     render with partpm, pm or Mitsuba's path
    partpm compare SCENE [options] --out DIR     pm vs partpm vs a path-traced reference
    partpm converge SCENE [options] --out DIR    error against time: progressive partpm, pm,
                                                 Mitsuba's path
    partpm speedup SCENE [options] --out DIR     the paper's speedup experiment (figures 5-6)
    partpm bench [options]                       kd-tree and tracer against scipy, pykdtree
                                                 and Mitsuba's path tracer
    partpm hwsim WORKLOAD_DIR [options] --out DIR   the PE-array simulator
    partpm calibrate SCENE [options] --out DIR   hwsim's costs fitted to per-map times at
                                                 several leaf sizes and radii
    partpm scaling SCENE [options] --out DIR     strong scaling of the MPI backend
    partpm figures [--out DIR] [--only NAME,...] [--smoke] [--list]
                                                 every table and figure of the README and
                                                 the notebooks, from the current code

SCENE is a built-in scene name (``partpm render --list``) or a Mitsuba XML file; ``partpm
COMMAND --help`` lists a command's options (:mod:`.parser`). ``render`` is :mod:`.render`,
``figures`` :mod:`.figures`, the others :mod:`.experiments`. Errors end with one line on stderr
and exit status 2.
"""
from __future__ import annotations

import logging
import sys
from contextlib import nullcontext

from .common import UsageError, interrupted, parse_resolution
from .experiments import (run_bench, run_calibrate, run_compare, run_converge, run_hwsim,
                          run_scaling, run_speedup)
from .figures import run_figures
from .parser import build_parser
from .render import format_ranks, run_render

__all__ = ["main", "parse_resolution", "format_ranks"]

#: Subcommand -> the function that runs it.
COMMANDS = {"render": run_render, "compare": run_compare, "speedup": run_speedup,
            "bench": run_bench, "hwsim": run_hwsim, "scaling": run_scaling,
            "converge": run_converge, "figures": run_figures, "calibrate": run_calibrate}


def _as_one_job(args, argv):
    """Where ``render`` runs as an MPI job (``--backend mpi``), its ranks run it as one job
    (:func:`~mi_partpm.backends.one_job`); a render started by mpiexec on several ranks with
    the local backend is refused (every rank would render and write the whole image)."""
    from ..backends import MPIUnavailable, comm_world, launcher_ranks, one_job
    if args.command != "render":
        return nullcontext()
    ranks = launcher_ranks()
    if getattr(args, "backend", "local") != "mpi":
        if ranks > 1:
            raise UsageError(f"this process is one of the {ranks} ranks of an MPI job "
                             f"(mpiexec), but --backend is local: every rank would render the "
                             f"whole image and write it; pass --backend mpi")
        return nullcontext()
    if ranks == 1:
        logging.getLogger(__name__).warning(
            "--backend mpi in an MPI job of one rank: start it with mpiexec -n P to render on "
            "P ranks")
    try:
        comm = comm_world()
    except MPIUnavailable as e:
        raise UsageError(str(e)) from None
    return one_job(comm, argv)


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.WARNING if getattr(args, "quiet", False) else logging.INFO,
                        format="%(message)s", stream=sys.stderr)
    try:
        with _as_one_job(args, sys.argv[1:] if argv is None else argv):
            return COMMANDS[args.command](args)
    except UsageError as e:
        print(f"partpm: error: {e}", file=sys.stderr)
        return 2
    except BaseException as e:      # Ctrl-C, also where Mitsuba wrapped it in its own error
        if not interrupted(e):
            raise
        print("partpm: interrupted", file=sys.stderr)
        return 130
