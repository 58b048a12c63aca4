"""hwsim's command: the report on a scene's workloads, as ``partpm hwsim`` and, without
Mitsuba or Dr.Jit (an architect's machine may have neither), as ``python -m hwsim``.

Both take the same arguments (:func:`add_arguments`) and run :func:`run`; bad input is a
``ValueError`` whose message names the option, which each command prints as one line with
exit status 2.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

__all__ = ["add_arguments", "run", "main"]


def add_arguments(parser: argparse.ArgumentParser):
    """The command's arguments, on ``parser``."""
    parser.add_argument("workloads", help="a workloads/ directory written by 'partpm speedup'")
    parser.add_argument("--config", help="hardware configuration (TOML; every key, unit and "
                                         "default in hwsim/default.toml)")
    parser.add_argument("--check", metavar="WORKLOAD_DIR",
                        help="another scene's workloads (or calibration sets, 'partpm "
                             "calibrate' DIR/sets): predict its measured per-map times with "
                             "the costs calibrated on 'workloads'")
    parser.add_argument("--out", required=True, help="output directory (JSON, CSV, plots)")
    parser.add_argument("-q", "--quiet", action="store_true",
                        help="print only warnings and errors")


def run(args, code=None) -> int:
    """Simulate, write the report into ``args.out`` and print it (unless ``args.quiet``).
    ``code``: the version of the code, recorded in ``report.json``."""
    import tomllib

    from .config import load_config
    from .report import format_report, run_report
    if args.config and not Path(args.config).is_file():
        raise ValueError(f"--config {args.config!r} is not a file")
    config = load_config(args.config)           # a file that is not TOML is named there
    keys = {}
    if args.config:
        with open(args.config, "rb") as f:
            keys = tomllib.load(f)
    if "pe_count" in keys:
        raise ValueError(f"pe_count in {args.config}: the report sets the PE count itself (one "
                         f"PE per map at every recorded n, and P = 1, 2, 4, ... n at the "
                         f"largest n); remove the key (it is simulate()'s, in Python)")
    say = None if args.quiet else (lambda line: print(line, flush=True))
    result = run_report(args.workloads, config, args.out, args.check, progress=say, code=code,
                        out_name="--out")
    if not args.quiet:
        print(format_report(result))
        print(f"wrote    {args.out}/report.json, report.csv, sweep.csv, contention.csv, "
              f"sensitivity.csv, hwsim.png")
    return 0


def main(argv=None) -> int:
    """``python -m hwsim WORKLOADS --out DIR [--config F] [--check DIR] [-q]``."""
    parser = argparse.ArgumentParser(
        prog="python -m hwsim", description="Simulate a PE array on the workloads of "
        "'partpm speedup' (the same report as 'partpm hwsim', without Mitsuba).")
    add_arguments(parser)
    args = parser.parse_args(argv)
    try:
        return run(args)
    except (OSError, ValueError) as e:
        print(f"hwsim: error: {e}", file=sys.stderr)
        return 2
