"""``partpm figures``: regenerate every table and figure of the README and the notebooks
(:mod:`mi_partpm.experiments.regenerate`)."""
from __future__ import annotations

from .common import UsageError, check_folder, progress

__all__ = ["run_figures"]


def run_figures(args) -> int:
    from ..experiments.regenerate import run_figures as run
    only = None
    if args.only is not None:
        only = [t.strip() for t in args.only.split(",") if t.strip()]
        if not only:                     # "" or "," would otherwise mean every step
            raise UsageError(f"--only must name one or more steps (comma-separated; --list "
                             f"shows them), got {args.only!r}")
    argv = "partpm figures" + "".join(
        f" {flag}" for flag, on in (("--smoke", args.smoke), ("--list", args.list)) if on)
    if args.out:
        argv += f" --out {args.out}"
        if not args.list:
            check_folder(args.out, "--out")
    if only:
        argv += f" --only {','.join(only)}"
    try:
        return run(out=args.out, only=only, smoke=args.smoke, list_only=args.list,
                   progress=progress(args), argv=argv)
    except ValueError as e:
        raise UsageError(str(e)) from None
