"""``partpm render``: one image with partpm, pm or Mitsuba's path tracer, and its figures.

Phases: the integrator from the options (:func:`integrator_desc`), the scene, the render, then
the outputs (EXR, PNG, optional JSON of the figures) and a summary of the phases' times.
"""
from __future__ import annotations

import json
import logging
import signal
import threading
from pathlib import Path
from typing import Optional

from .common import (UsageError, check_writable, interrupted, last_line, scene_parameters,
                     setup, write_atomic)

__all__ = ["run_render", "integrator_desc", "format_ranks", "quality_props", "apply_text"]

log = logging.getLogger("mi_partpm")


def apply_text(names, negated: bool = False) -> str:
    """'--a applies' or '--a, --b apply' ('does not apply', 'do not apply' if ``negated``)."""
    one = len(names) == 1
    verb = ("does not apply" if one else "do not apply") if negated else \
        ("applies" if one else "apply")
    return f"{', '.join(names)} {verb}"


#: The integrator props the render options set, by option.
PROP_OPTIONS = {"photon_count": "--photons", "map_count": "--maps", "max_depth": "--max-depth",
                "radius_fraction": "--radius-fraction", "max_radius": "--max-radius",
                "time_limit": "--time", "caustic_photon_count": "--caustic-photons",
                "caustic_radius_fraction": "--caustic-radius-fraction",
                "caustic_radius": "--caustic-radius", "glossy_samples": "--glossy-samples",
                "final_gather": "--final-gather", "radius": "--radius", "passes": "--passes",
                "alpha": "--alpha", "direct": "--direct", "kernel": "--kernel",
                "glossy": "--glossy", "k": "--k"}


def in_options(message: str) -> str:
    """A message of the integrator's, about its props, in the options that set them:
    ``photon_count = 100`` becomes ``--photons 100``, ``max_depth must`` ``--max-depth
    must``. Props of one word (radius, passes, ...) are replaced only before ``=`` or
    ``must`` and after raise, lower or give, where they cannot be a word of the sentence."""
    import re
    for prop, option in PROP_OPTIONS.items():
        if "_" in prop:
            message = re.sub(rf"(?<![\w-]){prop} = ", f"{option} ", message)
            message = re.sub(rf"(?<![\w-]){prop}(?!\w)", option, message)
        else:
            message = re.sub(rf"(?<![\w'-]){prop} = ", f"{option} ", message)
            message = re.sub(rf"(?<![\w'-]){prop} must", f"{option} must", message)
            message = re.sub(rf"\b(raise|lower|give) {prop}(?![\w'-])", rf"\1 {option}",
                             message)
    return message


#: The option that sets a prop, where it is not the prop's own name with dashes.
_OPTION_NAMES = {"caustic_photon_count": "caustic_photons"}


def quality_props(args) -> tuple:
    """The props the quality options give (``--direct``, ``--kernel``, ``--glossy``,
    ``--glossy-samples``; ``--caustic-photons``, ``--caustic-radius``,
    ``--caustic-radius-fraction``, ``--final-gather``), as two dicts: those of both photon
    mappers and those of partpm alone, each with the options given only (a zero given is
    given)."""
    from ..props import PARTPM_QUALITY_PROPS, QUALITY_PROPS
    return tuple({prop: getattr(args, _OPTION_NAMES.get(prop, prop))
                  for prop in props if getattr(args, _OPTION_NAMES.get(prop, prop)) is not None}
                 for props in (QUALITY_PROPS, PARTPM_QUALITY_PROPS))


def check_caustic_options(args):
    """A caustic radius needs caustic maps."""
    if (args.caustic_radius or args.caustic_radius_fraction) and not args.caustic_photons:
        raise UsageError("--caustic-radius and --caustic-radius-fraction are the caustic "
                         "maps' radius: they need caustic maps (--caustic-photons N)")


def given_options(props: dict) -> list:
    """The options that set ``props`` (those with a value other than 0: a zero asks for
    none of the thing), as a user types them."""
    return [PROP_OPTIONS[p] for p, v in props.items() if v]


def integrator_desc(args) -> dict:
    """The ``mi.load_dict`` description of the integrator the options ask for (partpm
    unless ``--integrator`` names another)."""
    args.integrator = args.integrator or "partpm"
    max_depth = -1 if args.max_depth is None else args.max_depth
    if args.integrator == "path":
        desc = {"type": "path", "max_depth": max_depth}
        photon_options = [o for o, v in (
            ("--photons", args.photons), ("--maps", args.maps), ("--direct", args.direct),
            ("--radius", args.radius), ("--radius-fraction", args.radius_fraction),
            ("--k", args.k), ("--max-radius", args.max_radius)) if v is not None]
        if photon_options:
            raise UsageError(f"{apply_text(photon_options)} to the photon mappers "
                             f"(--integrator partpm or pm), not to path")
    else:
        desc = {"type": args.integrator, "photon_count": args.photons or 100_000,
                "seed": args.seed, "max_depth": max_depth,
                "direct": args.direct or "photons"}
    progressive_options = [o for o, v in (
        ("--passes", args.passes), ("--alpha", args.alpha), ("--time", args.time),
        ("--checkpoint-every", args.checkpoint_every)) if v]
    if progressive_options and args.integrator != "partpm":
        raise UsageError(f"{apply_text(progressive_options)} to --integrator partpm only (the "
                         f"progressive photon mapper)")
    # As the integrator decides: a time limit alone runs passes until it; --passes 1 is one.
    progressive = (args.passes or 1) > 1 or (bool(args.time) and args.passes is None)
    for option, value, what in (("--alpha", args.alpha, "sets how fast the radius shrinks"),
                                ("--checkpoint-every", args.checkpoint_every,
                                 "writes the image")):
        if value is not None and not progressive:
            raise UsageError(f"{option} {what} between passes: it needs a progressive render "
                             f"(--passes P > 1, or --time SECONDS without --passes)")
    if args.time and args.passes == 1:
        raise UsageError(f"--time {args.time:g} stops a progressive render between passes: "
                         f"with --passes 1 the one pass runs whole (give --passes P > 1, or "
                         f"--time without --passes for passes until it)")
    if args.checkpoint_every and not args.time and args.checkpoint_every > args.passes:
        raise UsageError(f"--checkpoint-every {args.checkpoint_every} would write no "
                         f"checkpoint in {args.passes} passes: give K <= --passes")
    shared, partpm_props = quality_props(args)
    if args.integrator != "path":
        desc.update({k: v for k, v in shared.items() if k != "direct"})
    elif any(v is not None for v in (args.kernel, args.glossy, args.glossy_samples)):
        raise UsageError("--kernel, --glossy and --glossy-samples apply to the photon mappers "
                         "(--integrator partpm or pm)")
    partpm_only = given_options(partpm_props)
    if partpm_only and args.integrator != "partpm":
        raise UsageError(f"{apply_text(partpm_only)} to --integrator partpm only")
    check_caustic_options(args)
    if args.integrator == "pm":
        unused = [o for o, v in (("--maps", args.maps), ("--radius", args.radius),
                                 ("--radius-fraction", args.radius_fraction)) if v]
        if unused:
            raise UsageError(f"{apply_text(unused, negated=True)} to --integrator pm "
                             f"(one map, k nearest photons: use --k, --max-radius)")
        if args.k is not None:
            desc["k"] = args.k
        if args.max_radius is not None:
            desc["max_radius"] = args.max_radius
    elif args.integrator == "partpm":
        given = [o for o, v in (("--k", args.k), ("--max-radius", args.max_radius))
                 if v is not None]
        if given:
            raise UsageError(f"{' and '.join(given)} appl{'ies' if len(given) == 1 else 'y'} "
                             f"to --integrator pm only")
        desc["map_count"] = args.maps or 8
        desc["backend"] = args.backend or "local"
        for key, value in (("passes", args.passes), ("alpha", args.alpha),
                           ("time_limit", args.time)):
            if value is not None:
                desc[key] = value
        desc.update(partpm_props)
        if args.radius is not None:
            desc["radius"] = args.radius
        elif args.radius_fraction is not None:
            desc["radius_fraction"] = args.radius_fraction
    if args.backend == "mpi" and args.integrator != "partpm":
        raise UsageError("--backend mpi needs --integrator partpm (the maps are what the ranks "
                         "share out)")
    return desc


#: The render options that describe the integrator (``--checkpoint-every`` and ``--seed``
#: apply to a scene file's own integrator too). Given none, a scene file's ``<integrator>``
#: renders; given any, the command line's integrator replaces it.
INTEGRATOR_OPTIONS = ("integrator", "photons", "maps", "direct", "radius", "radius_fraction",
                      "max_radius", "k", "max_depth", "passes", "alpha", "time", "kernel",
                      "caustic_photons", "caustic_radius", "caustic_radius_fraction", "glossy",
                      "glossy_samples", "final_gather")


def _given_options(args) -> list:
    """The integrator options given on the command line, as the user typed them."""
    given = [f"--{o.replace('_', '-')}" for o in INTEGRATOR_OPTIONS
             if getattr(args, o, None) is not None]
    return given


def scene_file_integrator(scene: str) -> Optional[str]:
    """The type of ``scene``'s own ``<integrator>`` when it is a scene file with one (at the
    top level of the file or of a file it includes: Mitsuba's default when it has none is
    ``path``, which cannot be told apart), else None."""
    from ..scenes import scene_files, scene_names, scene_path
    if scene in scene_names():                # the built-in scenes leave the integrator to us
        return None
    try:
        files = scene_files(scene_path(scene))
    except (OSError, ValueError):
        return None
    return next((child.get("type", "?") for _, _, root in files for child in root
                 if child.tag == "integrator"), None)


def _output_path(args) -> Path:
    from ..backends import launcher_rank
    out = Path(args.output)
    if out.suffix.lower() != ".exr":
        raise UsageError(f"-o must name an .exr file, got {args.output!r}")
    if launcher_rank() > 0:
        return out      # rank 0 alone writes (and checks, and makes the folders)
    # Before any work: an output that cannot be written would lose the whole render.
    check_writable(out, "-o")
    check_writable(out.with_suffix(".png"), "-o (its PNG)")
    if args.stats_json is not None:
        check_writable(args.stats_json, "--stats-json")
        images = {out.resolve(), out.with_suffix(".png").resolve()}
        if Path(args.stats_json).resolve() in images:
            raise UsageError(f"--stats-json {args.stats_json!r} is where -o writes its image "
                             f"({out.name} and {out.with_suffix('.png').name}): give the "
                             f"stats another name")
    return out


def run_render(args) -> int:
    import mitsuba as mi

    import mi_partpm
    from ..scenes import check_scene
    from ..timing import Stopwatch
    if not setup(args, needs_plugins=args.integrator != "path"):
        return 0
    if not args.output:
        raise UsageError("render needs -o OUT.exr")
    # --backend says where the integrator runs, not what it is: alone, it moves a scene
    # file's own partpm onto the ranks (mpi) or into this process (local).
    given = _given_options(args)
    from_file = args.scene is not None and scene_file_integrator(args.scene)
    if from_file and given:
        # Only pm takes the photon mappers' options besides partpm: for another integrator
        # (path, aov, moment) no --integrator renders it with them.
        log.warning("the command line's %s (%s) replaces the <integrator type=\"%s\"> of %s "
                    "with its own props (without these options the file's renders)%s",
                    args.integrator or "partpm", ", ".join(given), from_file, args.scene,
                    "; add --integrator pm to render pm with these options"
                    if args.integrator is None and from_file == "pm" else "")
    integrator = None
    if not from_file or given:
        named = args.integrator is not None
        from ..plugins import load_integrator
        try:
            integrator = load_integrator(integrator_desc(args))
        except (ValueError, RuntimeError) as e:    # (path's own props: Mitsuba's errors)
            raise UsageError(in_options(last_line(e))) from None
        except UsageError as e:
            if from_file and not named and from_file != args.integrator:
                # An option of the file's own integrator (--k for its pm) given without
                # --integrator: the command line's partpm refuses it.
                raise UsageError(f"{e} (the command line's integrator, {args.integrator} "
                                 f"unless --integrator says otherwise, replaces the "
                                 f"<integrator type=\"{from_file}\"> of {args.scene}: add "
                                 f"--integrator {from_file})") from None
            raise
    defines = scene_parameters(args.define)
    out = _output_path(args)           # after the options' checks: it makes the folders
    clock = Stopwatch()
    try:
        scene = mi_partpm.load_scene(args.scene, resolution=args.resolution, spp=args.spp,
                                     data_dir=args.data, **defines)
        check_scene(scene, args.scene)
    except (FileNotFoundError, ValueError) as e:
        raise UsageError(str(e)) from None
    own = integrator is None
    if own:                             # the scene file's own, as Mitsuba would render it
        integrator = scene.integrator()
        # A Python plugin's class_name() is its base class's ("SamplingIntegrator"): ours
        # are named by their plugin names.
        from ..plugins import PLUGINS
        ours = {class_name: name for name, (_, class_name) in PLUGINS.items()}
        args.integrator = ours.get(type(integrator).__name__, type(integrator).__name__) \
            if not type(integrator).__module__.startswith("mitsuba") \
            else integrator.class_name()
        if args.backend is not None and hasattr(integrator, "run_on"):
            try:                                # also --backend local over backend="mpi"
                integrator.run_on(args.backend)
            except ValueError as e:             # more ranks than the file's maps
                raise UsageError(f"{e} (map_count of {args.scene})") from None
        elif args.backend == "mpi":
            raise UsageError(f"--backend mpi runs partpm's maps on the ranks; the scene "
                             f"file's integrator is {args.integrator}: render the command "
                             f"line's partpm (--integrator partpm and its options) or give "
                             f"the scene file a partpm")
        if args.checkpoint_every and not (getattr(integrator, "passes", 1) > 1 and
                                          hasattr(integrator, "on_pass")):
            raise UsageError(f"--checkpoint-every writes the image between passes: the scene "
                             f"file's integrator ({args.integrator}) is not a progressive "
                             f"partpm (passes > 1 or time_limit)")
    _check_ranks(integrator, args.integrator)
    film = scene.sensors()[0].film()
    log.info("scene %s: %dx%d, %s%s", args.scene, film.size()[0], film.size()[1], integrator,
             " (the scene file's integrator)" if own else "")
    if len(scene.sensors()) > 1:
        first = scene.sensors()[0]
        log.warning("scene %s has %d sensors: render draws the first (%s), as mi.render does "
                    "by default; render another from Python with mi.render(scene, "
                    "sensor=INDEX)", args.scene, len(scene.sensors()),
                    repr(first.id()) if first.id() else first.class_name())
    seconds = {"load": clock.lap()}
    if args.checkpoint_every:
        integrator.on_pass = _checkpoints(args.checkpoint_every, out, integrator, film)
    def described(e):
        return last_line(e) if own else in_options(last_line(e))
    backend = getattr(integrator, "backend", None)
    if backend is not None and backend.name == "mpi":
        backend.describe = described   # an MPI rank ends the job itself, with this message
    try:
        with _stop_on_interrupt(integrator):
            image = mi.render(scene, integrator=integrator, seed=args.seed)
    except (ValueError, RuntimeError, MemoryError) as e:
        if interrupted(e):
            raise KeyboardInterrupt from None
        raise UsageError(described(e)) from None
    seconds["render"] = clock.lap(image)
    stats = getattr(integrator, "stats", {})
    if backend is not None and not backend.is_root:
        return 0    # rank 0 holds the gathered image and writes it
    _write(args, out, image, film, stats, seconds, integrator)
    if not args.quiet:
        print(_summary(stats, seconds, out))
    return 0


def _check_ranks(integrator, name: str):
    """Under mpiexec with several ranks, a render whose integrator runs locally is refused
    (every rank would render the whole image and write it); with the MPI backend in a job
    of one rank, a warning says how to start P."""
    from ..backends import launcher_ranks
    backend = getattr(integrator, "backend", None)
    ranks = launcher_ranks()
    if getattr(backend, "name", "local") != "mpi":
        if ranks > 1:
            raise UsageError(f"this process is one of the {ranks} ranks of an MPI job "
                             f"(mpiexec), but the integrator ({name}) renders locally: every "
                             f"rank would render the whole image and write it; pass --backend "
                             f"mpi (partpm: the scene file's own, or the command line's)")
    elif backend.comm.size == 1:
        log.warning("--backend mpi in an MPI job of one rank: start it with mpiexec -n P to "
                    "render on P ranks")


class _stop_on_interrupt:
    """During a progressive render, the first Ctrl-C asks the integrator to stop after the
    pass it is in (the image of the passes so far is then written as usual); a second one,
    or the first in any other render, ends the process at once (``partpm: interrupted``,
    exit status 130).

    Python runs a signal handler only between bytecodes, and a pass spends seconds inside
    one Dr.Jit kernel: the signals are read instead from a wakeup pipe (written by the
    C-level handler as they come) by a thread, which says so and stops at once."""

    def __init__(self, integrator):
        self.integrator = integrator
        self.asked = False
        self.progressive = getattr(integrator, "passes", 1) > 1 and \
            hasattr(integrator, "stop_requested")
        # Not where Ctrl-C was ignored on entry (a background job) or off the main thread
        # (where Python cannot install a handler): there Python's Ctrl-C stays.
        self.active = threading.current_thread() is threading.main_thread() and \
            signal.getsignal(signal.SIGINT) is not signal.SIG_IGN

    def _watch(self, fd: int):
        import os
        import sys
        while True:
            try:
                data = os.read(fd, 64)
            except OSError:
                return
            if not data:                       # the pipe was closed: the render is over
                return
            for signum in data:
                if signum != signal.SIGINT:
                    continue
                if self.asked or not self.progressive:
                    sys.stdout.flush()
                    sys.stderr.write("partpm: interrupted\n")
                    sys.stderr.flush()
                    os._exit(130)     # (a temporary output being written may be left)
                self.asked = True
                log.warning("Ctrl-C: stopping after this pass and writing the image of the "
                            "passes so far (Ctrl-C again to stop at once, with no image)")

    def __enter__(self):
        if self.active:
            import os
            self.read_fd, self.write_fd = os.pipe()
            self.previous, self.previous_fd = None, None
            try:
                os.set_blocking(self.write_fd, False)
                # The Python-level handler does nothing: the watcher thread acts on it.
                self.previous = signal.signal(signal.SIGINT, lambda signum, frame: None)
                self.previous_fd = signal.set_wakeup_fd(self.write_fd,
                                                        warn_on_full_buffer=False)
                self.watcher = threading.Thread(target=self._watch, args=(self.read_fd,),
                                                name="partpm-ctrl-c", daemon=True)
                self.watcher.start()
            except BaseException:
                self._restore(joined=False)
                raise
            if self.progressive:
                self.integrator.stop_requested = lambda: self.asked
        return self

    def _restore(self, joined: bool = True):
        """Python's handler first (a Ctrl-C from here on is Python's again), then the
        wakeup fd; the pipe is closed once the watcher has seen its end."""
        import os
        if self.previous is not None:
            signal.signal(signal.SIGINT, self.previous)
        if self.previous_fd is not None:
            signal.set_wakeup_fd(self.previous_fd)
        os.close(self.write_fd)               # the watcher reads the end and returns
        if joined:
            self.watcher.join(timeout=5)
        if not joined or not self.watcher.is_alive():
            os.close(self.read_fd)

    def __exit__(self, *exc):
        if self.active:
            self._restore()
            if self.progressive:
                self.integrator.stop_requested = None
        return False


def _checkpoints(every: int, out: Path, integrator, film):
    """An ``on_pass`` that writes the image so far to ``out`` every ``every`` passes."""
    def on_pass(info):
        backend = getattr(integrator, "backend", None)
        if info["pass"] % every or (backend is not None and not backend.is_root):
            return
        info["image"]()                 # develops the passes so far into the film
        _write_image(out, film)
        log.info("checkpoint: pass %d written to %s", info["pass"], out)
    return on_pass


def _write(args, out: Path, image, film, stats: dict, seconds: dict, integrator):
    from ..experiments.provenance import code_version
    if args.stats_json:
        ran_on = getattr(getattr(integrator, "backend", None), "name", "local")
        write_atomic(args.stats_json, lambda name: Path(name).write_text(json.dumps(
            {"time_load": seconds["load"], "time_render": seconds["render"],
             "scene": args.scene, "integrator": args.integrator, "backend": ran_on,
             "resolution": list(film.size()), "code": code_version(),
             "options": {k: v for k, v in vars(args).items() if k != "command"}, **stats},
            indent=2,
            default=str) + "\n"))
    _write_image(out, film)


def _write_image(out: Path, film):
    """The EXR with the film's channels (R, G, B, alpha where the film has it, then the
    AOVs by name, as Mitsuba's own film writes them) and the PNG beside it (the film's colour
    and alpha only: its first ``base_channels_count()``, Y, or three colour channels (R, G,
    B; an xyz film's X, Y, Z as they are), with A where the film has it), both from the film, so they show one render (inside
    Mitsuba's ``aov`` the image ``mi.render`` returns is another render of the nested
    integrator), each written whole or not at all (see :func:`~.common.write_atomic`): a
    checkpoint may be read while the render goes on."""
    import mitsuba as mi
    import numpy as np
    bitmap = film.bitmap()
    write_atomic(out, lambda name: bitmap.write(name))
    pixels = np.array(bitmap, dtype=np.float32)
    if pixels.ndim == 2:
        pixels = pixels[..., None]
    colour = film.base_channels_count() if hasattr(film, "base_channels_count") else \
        (1 if mi.is_monochromatic else 3) + int(mi.has_flag(film.flags(), mi.FilmFlags.Alpha))
    pixels = pixels[..., :colour]
    # Mitsuba's write_bitmap keeps only RGB in a PNG: the format is given here, with alpha.
    formats = {1: mi.Bitmap.PixelFormat.Y, 2: mi.Bitmap.PixelFormat.YA,
               3: mi.Bitmap.PixelFormat.RGB, 4: mi.Bitmap.PixelFormat.RGBA}
    fmt = formats[pixels.shape[2]]
    png = mi.Bitmap(np.ascontiguousarray(pixels), fmt).convert(fmt, mi.Struct.Type.UInt8, True)
    write_atomic(out.with_suffix(".png"),
                 lambda name: png.write(name, mi.Bitmap.FileFormat.PNG))


def _summary(stats: dict, seconds: dict, out: Path) -> str:
    lines = [f"load     {seconds['load']:8.2f} s"]
    for phase in ("trace", "build", "eye", "estimate"):
        if f"time_{phase}" in stats:
            lines.append(f"{phase:8} {stats[f'time_{phase}']:8.2f} s")
    lines.append(f"render   {seconds['render']:8.2f} s (all phases)")
    if "peak_memory_bytes" in stats:
        whose = "the largest rank's" if stats.get("ranks") else "this process"
        lines.append(f"memory   {stats['peak_memory_bytes'] / 1e9:8.2f} GB peak ({whose})")
    if stats:
        if "k" in stats:
            search = f"k = {stats['k']}, mean kNN radius {stats['mean_knn_radius']:.4g}"
        else:
            search = f"radius {stats['radius']:.4g}"
            if stats.get("passes", 1) > 1 and "mean_final_radius" in stats:
                search += f" at the start, {stats['mean_final_radius']:.4g} (mean) at the end"
        passes = stats.get("passes", 1)
        per_pass = f" per pass, {passes} passes" if passes > 1 else ""
        lines.append(f"photons  {stats['photons_emitted']} emitted{per_pass}, "
                     f"{stats['photons_stored']} stored in {stats['map_count']} "
                     f"map{'' if stats['map_count'] == 1 else 's'}, {search}")
        if "caustic_photons_stored" in stats:
            lines.append(f"caustic  {stats['caustic_photons_traced'] // max(passes, 1)} "
                         f"emitted{per_pass}, "
                         f"{stats['caustic_photons_stored']} stored, radius "
                         f"{stats['caustic_radius']:.4g}")
    if stats.get("ranks"):
        lines.append(format_ranks(stats["ranks"]))
    lines.append(f"wrote    {out} and {out.with_suffix('.png')}")
    return "\n".join(lines)


def format_ranks(ranks) -> str:
    """Per-rank figures of an MPI render as a small table (times summed over the passes)."""
    lines = [f"{'rank':>4} {'maps':>10} {'photons':>9} {'stored':>9} {'tree MB':>8} "
             f"{'trace s':>8} {'build s':>8} {'eye s':>7} {'estim s':>8} {'reduce s':>8} "
             f"{'reduce MB':>9}"]
    for j, r in enumerate(ranks):
        maps = ",".join(str(m) for m in r["maps_owned"])
        maps = maps if len(maps) <= 10 else maps[:8] + ".."
        lines.append(f"{j:4d} {maps:>10} {r['photons_traced']:9d} {r['photons_stored']:9d} "
                     f"{r['map_bytes'] / 1e6:8.2f} {r['time_trace']:8.2f} "
                     f"{r['time_build']:8.2f} {r['time_eye']:7.2f} {r['time_estimate']:8.2f} "
                     f"{r['time_reduce']:8.4f} {r['reduce_bytes'] / 1e6:9.2f}")
    return "\n".join(lines)
