"""What every ``partpm`` subcommand shares: argument types, errors, set-up, progress."""
from __future__ import annotations

import argparse
import os
import re
from contextlib import contextmanager
from pathlib import Path

from ..backends import interrupted  # noqa: F401  (the command line's name for it)
from ..props import check_float, check_int

__all__ = ["UsageError", "parse_resolution", "positive_int", "seed_int", "positive_float",
           "radius_float", "int_list", "scene_parameter", "scene_parameters", "setup",
           "progress", "last_line", "interrupted", "write_atomic", "check_writable",
           "check_folder", "check_scene_name", "check_variant_name", "check_plugin_variant",
           "check_eye_pass", "user_errors", "MAX_PIXELS", "MADE_FOLDERS", "remove_made_folders"]

#: The most pixels a film may have: Mitsuba indexes a film's values (4 or 5 a pixel) with
#: 32-bit integers (60000 x 60000 failed inside Mitsuba's tensor).
MAX_PIXELS = 1 << 28


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
    width, height = int(parts[0]), int(parts[1])
    if width * height > MAX_PIXELS:
        raise argparse.ArgumentTypeError(
            f"--resolution {width}x{height} has {width * height:,} pixels, more than 2^28 "
            f"(16384 x 16384): Mitsuba indexes a film's values with 32-bit integers")
    return width, height


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


#: Names that -D cannot set: the options that set them, or load_scene's own arguments.
_NOT_DEFINES = {"resx": "--resolution WxH", "resy": "--resolution WxH", "spp": "--spp N",
                "scene": None, "resolution": None, "data_dir": None}


def scene_parameter(text: str):
    """An argparse type for ``-D NAME=VALUE`` (as Mitsuba's own command line has it): the
    scene file's parameter ``$NAME`` set to VALUE, a string as Mitsuba reads it."""
    name, equals, value = text.partition("=")
    if not equals or not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", name):
        raise argparse.ArgumentTypeError(
            f"-D must look like NAME=VALUE, NAME a scene parameter ($NAME in the scene file: "
            f"letters, digits, _), got {text!r}")
    if not value:
        raise argparse.ArgumentTypeError(
            f"-D {name}= gives ${name} no value: give one (NAME=VALUE)")
    if name in _NOT_DEFINES:
        option = _NOT_DEFINES[name]
        raise argparse.ArgumentTypeError(
            f"-D {name}: " + (f"set the scene's ${name} with {option}" if option else
                              f"{name!r} cannot be set with -D (a name of load_scene's own "
                              f"arguments)"))
    return name, value


def scene_parameters(pairs) -> dict:
    """The ``-D`` pairs as a dict; a name given twice is refused (which one was meant?)."""
    params = {}
    for name, value in pairs or ():
        if name in params and params[name] != value:
            raise UsageError(f"-D {name} is given twice, as {params[name]!r} and {value!r}")
        params[name] = value
    return params


def positive_int(name, low=1, high=None):
    """An argparse type for an integer >= 1 (in [low, high]), checked as the props are."""
    return _argument_type(_integer, lambda v: check_int(name, v, low=low, high=high))


def seed_int(name="--seed"):
    """An argparse type for a seed: an integer that ``mi.render``'s ``seed`` takes too (32-bit
    unsigned), since the commands pass it to the eye samples as well as to the photons."""
    return _argument_type(_integer, lambda v: check_int(name, v, low=0, high=2**32 - 1))


def positive_float(name, high=None, high_open=False):
    """An argparse type for a finite number > 0 (and <= ``high``, or < with ``high_open``),
    checked as the props are."""
    return _argument_type(float, lambda v: check_float(name, v, low=0.0, high=high,
                                                       high_open=high_open))


def radius_float(name):
    """An argparse type for a radius in world units: the range the props take."""
    from ..kdtree.radius import MIN_RADIUS
    from ..props import MAX_RADIUS
    return _argument_type(float, lambda v: check_float(name, v, low=MIN_RADIUS,
                                                       high=MAX_RADIUS, low_open=False))


def int_list(option, text):
    """'1,2,4' -> [1, 2, 4], every value >= 1."""
    try:
        values = [int(v) for v in text.split(",")]
    except ValueError:
        values = []
    if not values or min(values) < 1:
        raise UsageError(f"{option} must be comma-separated integers >= 1, got {text!r}")
    return values


def check_variant_name(variant: str):
    """Refuse a ``--variant`` that this Mitsuba does not have, naming those it has."""
    import mitsuba as mi
    if variant not in mi.variants():
        raise UsageError(f"--variant {variant!r} is not a Mitsuba variant; available: "
                         f"{', '.join(mi.variants())}")


def check_plugin_variant(variant: str):
    """Refuse a ``--variant`` this Mitsuba lacks or the plugins do not run on."""
    from .. import plugins
    check_variant_name(variant)
    try:
        plugins.check_variant(variant, hint="--variant llvm_ad_rgb")
    except ValueError as e:
        raise UsageError(str(e)) from None


def setup(args, needs_plugins=True) -> bool:
    """Choose the variant, import the plugins, answer --list, check SCENE. True: go on."""
    import mitsuba as mi

    if needs_plugins:
        check_plugin_variant(args.variant)
    else:
        check_variant_name(args.variant)
    try:
        mi.set_variant(args.variant)
    except (ImportError, RuntimeError) as e:   # e.g. a CUDA variant without a CUDA device
        raise UsageError(f"--variant {args.variant!r} cannot run on this machine: "
                         f"{last_line(e)}") from None
    from ..backends import launcher_rank
    if launcher_rank() > 0:
        # Mitsuba's own warnings (a mono film's) are rank 0's too, as the package's are.
        mi.set_log_level(mi.LogLevel.Error)
    import mi_partpm  # noqa: F401  (registers the plugins)
    from ..scenes import scene_names

    if getattr(args, "list", False):
        if getattr(args, "scene", None):
            raise UsageError(f"--list lists the built-in scenes and takes no SCENE (got "
                             f"{args.scene!r}): give --list alone, or leave it out to "
                             f"{args.command} the scene")
        print("\n".join(scene_names()))
        return False
    if not getattr(args, "scene", None):
        raise UsageError(f"{args.command} needs a SCENE (a built-in name or an XML file); "
                         f"built-in: {', '.join(scene_names())}")
    return True


def progress(args):
    """Where a long command's progress lines go: stdout, or nowhere with -q."""
    return None if args.quiet else (lambda line: print(line, flush=True))


def check_eye_pass(resolution, spp: int, here: bool = True, kept: bool = False):
    """Refuse, before any work, camera samples (``resolution`` x ``spp``) that one wavefront
    of 2^32 lanes cannot hold or (``here``: they run on this machine) that alone would not
    fit the free memory (``kept``: of a progressive render, see
    :func:`~mi_partpm.memory.eye_bytes`)."""
    from .. import memory
    from ..camera import MAX_WAVEFRONT
    width, height = resolution
    samples = width * height * spp
    if samples > MAX_WAVEFRONT:
        raise UsageError(f"--resolution {width}x{height} at --spp {spp} has {samples:,} "
                         f"samples, more than one wavefront of 2^32 holds: lower --spp or "
                         f"--resolution")
    if not here:
        return
    try:
        memory.check_fits(memory.estimate_render(0, 1, width, height, spp, kept=kept))
    except memory.MemoryGuardError as e:
        raise UsageError(f"--resolution {width}x{height} at --spp {spp}: {e}") from None


@contextmanager
def user_errors(describe=None):
    """Errors of the input met during an experiment, as one line (``describe``: how to word
    a message; default as it is): a missing file, a value out of range, not enough memory,
    also where Mitsuba's render wrapped them in its RuntimeError. A Ctrl-C stays one. Any
    other error keeps its traceback, and so does a ValueError that a library raised (NumPy,
    Matplotlib, Python's own unpacking): only the project's own checks speak for the input."""
    from ..memory import MemoryGuardError
    try:
        yield
    except BaseException as e:
        if interrupted(e):
            raise KeyboardInterrupt from None
        cause = _root_cause(e)
        if isinstance(cause, MemoryGuardError) or (
                isinstance(cause, (FileNotFoundError, ValueError)) and _raised_here(cause)):
            message = last_line(e)
            raise UsageError(describe(message) if describe else message) from None
        raise


def _raised_here(e: BaseException) -> bool:
    """Whether ``e`` was raised by the project's own code (its innermost frame is in
    mi_partpm, its integrators or hwsim), not inside a library it called."""
    import hwsim
    import mi_partpm
    from mi_partpm import integrators
    roots = [str(Path(m.__file__).resolve().parent) for m in (mi_partpm, integrators, hwsim)]
    tb = e.__traceback__
    if tb is None:
        return False
    while tb.tb_next is not None:
        tb = tb.tb_next
    where = str(Path(tb.tb_frame.f_code.co_filename).resolve())
    return any(where.startswith(root + os.sep) for root in roots)


def _root_cause(e: BaseException) -> BaseException:
    """The error at the end of ``e``'s chain of causes (mi.render wraps a plugin's error in a
    RuntimeError caused by it)."""
    while e.__cause__ is not None:
        e = e.__cause__
    return e


def last_line(e: Exception) -> str:
    """The message of an error raised inside a plugin (Mitsuba wraps it in a traceback, and
    mi.render in a RuntimeError whose cause is the original error)."""
    e = _root_cause(e)
    line = str(e).strip().splitlines()[-1] if str(e).strip() else type(e).__name__
    # The exception's class name, which the traceback's last line starts with.
    return re.sub(r"^(?:\w+\.)*[A-Z]\w*(?:Error|Exception|Unavailable): ", "", line)


def _file_on_the_way(path: Path):
    """The first of ``path``'s folders (or ``path`` itself) that exists as a file, or None."""
    for part in reversed([path, *path.parents]):
        if os.path.exists(part) and not os.path.isdir(part):    # (these never raise)
            return part
    return None


#: The outermost folder each :func:`check_folder` of this command made (it was missing).
MADE_FOLDERS: list = []


def remove_made_folders():
    """Remove the folders :func:`check_folder` made for a command that failed, where they
    are still empty (folders only): a failed command leaves no empty output folder behind,
    and nothing it wrote is lost."""
    for top in reversed(MADE_FOLDERS):
        for folder in sorted((p for p in [top, *top.rglob("*")] if p.is_dir()),
                             key=lambda p: len(p.parts), reverse=True):
            try:
                folder.rmdir()                   # only an empty folder goes
            except OSError:
                pass
    MADE_FOLDERS.clear()


def _make_folder(path: Path):
    """Make the folder ``path`` where it is missing, and remember the outermost folder made
    (:data:`MADE_FOLDERS`)."""
    missing = [part for part in [path, *path.parents] if not os.path.exists(part)]
    path.mkdir(parents=True, exist_ok=True)
    if missing:
        MADE_FOLDERS.append(missing[-1])


def check_folder(path, option: str):
    """Refuse an output folder that cannot be made or written (a file on its way, no
    permission) before any work, naming ``option``; the folder is made when missing."""
    if not str(path).strip():
        raise UsageError(f"{option} needs a folder, got {str(path)!r}")
    path = Path(path)
    blocked = _file_on_the_way(path)
    if blocked is not None:
        raise UsageError(f"{option} {str(path)!r} cannot be made: {str(blocked)!r} is a "
                         f"file, not a folder")
    try:
        _make_folder(path)
        probe = path / f".probe{os.getpid()}"
        probe.write_bytes(b"")
        probe.unlink(missing_ok=True)
    except OSError as e:
        raise UsageError(f"{option} {str(path)!r} cannot be written: "
                         f"{e.strerror or e}") from None


def check_scene_name(scene: str):
    """Refuse a SCENE that is neither a built-in scene nor a file, before any work."""
    from ..scenes import scene_path
    if scene is None:                 # (a command given --list: nothing to check)
        return
    try:
        scene_path(scene)
    except FileNotFoundError as e:
        raise UsageError(str(e)) from None


def check_writable(path, option: str):
    """Refuse an output file that cannot be written (its folder is a file, or is not
    writable) before any work; its folder is made when missing."""
    if not str(path).strip():
        raise UsageError(f"{option} needs a file name, got {str(path)!r}")
    path = Path(path)
    blocked = _file_on_the_way(path.parent)
    if blocked is not None:
        raise UsageError(f"{option} {str(path)!r} cannot be written: {str(blocked)!r} is a "
                         f"file, not a folder")
    try:
        _make_folder(path.parent)
        if path.is_dir():
            raise UsageError(f"{option} {str(path)!r} is a folder: give a file name")
        # One probe per process: the ranks of an MPI job all check the same output.
        probe = path.with_name(f".{path.name}.probe{os.getpid()}")
        probe.write_bytes(b"")
        probe.unlink(missing_ok=True)
    except OSError as e:
        raise UsageError(f"{option} {str(path)!r} cannot be written: "
                         f"{e.strerror or e}") from None


def write_atomic(path, write):
    """``write(temporary path)`` then rename it to ``path``: a reader of ``path`` (a
    checkpoint read during the render) never sees a file half written. The temporary file
    keeps the suffix, which tells Mitsuba the format."""
    path = Path(path)
    temporary = path.with_name(f".{path.stem}.writing{path.suffix}")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        write(str(temporary))
        os.replace(temporary, path)
    except OSError as e:             # replaced or removed since it was checked
        raise UsageError(f"{str(path)!r} cannot be written: {e.strerror or e}") from None
    finally:
        if temporary.exists():
            temporary.unlink()
