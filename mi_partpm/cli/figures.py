"""``partpm figures``: regenerate every table and figure of the README and the notebooks
(:mod:`mi_partpm.experiments.regenerate`)."""
from __future__ import annotations

from .common import UsageError, check_folder, progress

__all__ = ["run_figures"]


def run_figures(args) -> int:
    from ..experiments.regenerate import run_figures as run
    only = [t.strip() for t in args.only.split(",") if t.strip()] if args.only else None
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
