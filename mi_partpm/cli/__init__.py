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

import contextlib
import io
import logging
import os
import sys

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


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    # Started by mpiexec on several ranks: the ranks run the command as one job, from the
    # parsing of their arguments on (a rank that fails alone would leave the others waiting).
    from ..backends import MPIUnavailable, comm_world, launcher_ranks, run_as_one_job
    if launcher_ranks() > 1:
        try:
            comm = comm_world()
        except MPIUnavailable:
            comm = None                 # no MPI here: a render refuses to run locally
        if comm is not None and comm.size > 1:
            return run_as_one_job(comm, argv, lambda: _main(argv, comm))
    return _main(argv)


def _main(argv, comm=None) -> int:
    """The command of ``argv``; ``comm``: the MPI job it is a rank of (its errors say which
    rank; ranks other than 0 log only errors: every rank renders the same scene with the
    same options, so their warnings are rank 0's, which speaks for the job)."""
    rank = comm.rank if comm is not None else 0
    # Every rank parses the same words: rank 0 alone says what is wrong with them.
    with contextlib.redirect_stderr(io.StringIO()) if rank else contextlib.nullcontext():
        args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.ERROR if rank else logging.WARNING
                        if getattr(args, "quiet", False) else logging.INFO,
                        format="%(message)s", stream=sys.stderr)
    from ..backends import launcher_ranks
    from .common import MADE_FOLDERS, remove_made_folders
    MADE_FOLDERS.clear()
    code = 1
    try:
        if args.command != "render" and launcher_ranks() > 1:
            # Only a render splits its work over the ranks: any other command would run
            # whole on every rank, each writing the same files.
            raise UsageError(f"'partpm {args.command}' runs in one process: under mpiexec "
                             f"every one of the {launcher_ranks()} ranks would run it whole "
                             f"and write the same files; run it without mpiexec (partpm "
                             f"scaling starts its own MPI jobs)")
        code = COMMANDS[args.command](args)
        return code
    except BrokenPipeError:
        # The reader of the output left (partpm ... | head): nothing more to say, and
        # Python's own flush of stdout at exit must not fail again.
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141
    except UsageError as e:
        from ..backends import report_error
        report_error(comm, str(e))
        return 2
    except BaseException as e:      # Ctrl-C, also where Mitsuba wrapped it in its own error
        if not interrupted(e):
            raise
        print("partpm: interrupted", file=sys.stderr)
        return 130
    finally:
        if code:                        # failed (an exception leaves code at 1)
            remove_made_folders()
