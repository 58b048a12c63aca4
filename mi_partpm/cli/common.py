"""What every ``partpm`` subcommand shares: argument types, errors, set-up, progress."""
from __future__ import annotations

import argparse
import re

from ..props import check_float, check_int

__all__ = ["UsageError", "parse_resolution", "positive_int", "seed_int", "positive_float",
           "int_list", "setup", "progress", "last_line"]


class UsageError(Exception):
    """A bad argument or input: reported in one line, exit status 2."""


def parse_resolution(text: str):
    """'WxH' -> (W, H), both integers >= 1."""
    parts = text.lower().split("x")
    if len(parts) != 2 or not all(p.strip().isdigit() for p in parts) \
            or min(int(p) for p in parts) < 1:
        raise argparse.ArgumentTypeError(
            f"--resolution must look like WIDTHxHEIGHT with integers >= 1 (e.g. 480x480), "
            f"got {text!r}")
    return int(parts[0]), int(parts[1])


def _argument_type(convert, check):
    """An argparse type: ``convert(text)`` then ``check(value)`` (the checks of
    :mod:`mi_partpm.props`); text that does not convert is reported by checking the text
    itself, so the message is the same one."""
    def parse(text):
        try:
            try:
                value = convert(text.strip())
            except ValueError:
                value = text
            return check(value)
        except ValueError as e:
            raise argparse.ArgumentTypeError(str(e)) from None
    return parse


def _integer(text: str) -> int:
    value = int(text)
    if str(value) != text.lstrip("+"):
        raise ValueError(text)
    return value


def positive_int(name):
    """An argparse type for an integer >= 1, checked as the props are."""
    return _argument_type(_integer, lambda v: check_int(name, v, low=1))


def seed_int(name="--seed"):
    """An argparse type for a seed: an integer that ``mi.render``'s ``seed`` takes too (32-bit
    unsigned), since the commands pass it to the eye samples as well as to the photons."""
    return _argument_type(_integer, lambda v: check_int(name, v, low=0, high=2**32 - 1))


def positive_float(name, high=None):
    """An argparse type for a finite number > 0 (and <= ``high``), checked as the props are."""
    return _argument_type(float, lambda v: check_float(name, v, low=0.0, high=high))


def int_list(option, text):
    """'1,2,4' -> [1, 2, 4], every value >= 1."""
    try:
        values = [int(v) for v in text.split(",")]
    except ValueError:
        values = []
    if not values or min(values) < 1:
        raise UsageError(f"{option} must be comma-separated integers >= 1, got {text!r}")
    return values


def setup(args, needs_plugins=True) -> bool:
    """Choose the variant, import the plugins, answer --list, check SCENE. True: go on."""
    import mitsuba as mi

    from .. import plugins
    if args.variant not in mi.variants():
        raise UsageError(f"--variant {args.variant!r} is not a Mitsuba variant; available: "
                         f"{', '.join(mi.variants())}")
    if needs_plugins:
        try:
            plugins.check_variant(args.variant)
        except ValueError as e:
            raise UsageError(str(e)) from None
    mi.set_variant(args.variant)
    import mi_partpm  # noqa: F401  (registers the plugins)
    from ..scenes import scene_names

    if getattr(args, "list", False):
        print("\n".join(scene_names()))
        return False
    if not getattr(args, "scene", None):
        raise UsageError(f"{args.command} needs a SCENE (a built-in name or an XML file); "
                         f"built-in: {', '.join(scene_names())}")
    return True


def progress(args):
    """Where a long command's progress lines go: stdout, or nowhere with -q."""
    return None if args.quiet else (lambda line: print(line, flush=True))


def last_line(e: Exception) -> str:
    """The message of an error raised inside a plugin (Mitsuba wraps it in a traceback, and
    mi.render in a RuntimeError whose cause is the original error)."""
    while e.__cause__ is not None:
        e = e.__cause__
    line = str(e).strip().splitlines()[-1] if str(e).strip() else type(e).__name__
    # The exception's class name, which the traceback's last line starts with.
    return re.sub(r"^(?:\w+\.)*[A-Z]\w*(?:Error|Exception|Unavailable): ", "", line)
