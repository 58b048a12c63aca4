"""The experiment subcommands: ``compare``, ``speedup``, ``bench``, ``hwsim``, ``calibrate``,
``scaling``.

Each reads its options, calls the experiment in :mod:`mi_partpm.experiments` (or
:mod:`hwsim.report`), prints its table and says what it wrote.
"""
from __future__ import annotations

import logging
import re
from pathlib import Path

from ..trace import MAX_RUN
from .common import (UsageError, check_eye_pass, check_folder, check_plugin_variant,
                     check_scene_name, check_writable, int_list, last_line, progress, setup,
                     user_errors)

__all__ = ["run_compare", "run_speedup", "run_bench", "run_hwsim", "run_scaling",
           "run_converge", "run_calibrate"]

log = logging.getLogger("mi_partpm")

#: The options of the settings' fields that :func:`in_settings` names.
SETTING_OPTIONS = {"photons": "--photons", "maps": "--maps", "spp": "--spp",
                   "reference_spp": "--reference-spp", "radius_fraction": "--radius-fraction",
                   "k": "--k", "alpha": "--alpha", "seconds": "--time", "methods": "--methods",
                   "direct": "--direct", "resolution": "--resolution"}


def in_settings(message: str) -> str:
    """A message about a setting of :class:`~mi_partpm.experiments.compare.CompareSettings`
    or its siblings, or about an integrator's prop, in the options that set them. The
    experiments take their depth from the scene (no ``--max-depth``): the memory guard's
    advice to lower it is left out."""
    from ..memory import LOWER_DEPTH
    from .render import in_options
    message = message.replace(LOWER_DEPTH, "")
    found = re.match(r"(\w+) must (.*)", message)
    if found and found.group(1) in SETTING_OPTIONS:
        message = f"{SETTING_OPTIONS[found.group(1)]} must {found.group(2)}"
        if found.group(1) == "maps":
            message += " (at most --photons)"
    return in_options(message)


def check_experiment_scene(scene: str, command: str):
    """:func:`check_scene_name`, and a word where a scene file has an ``<integrator>`` of its
    own: the experiments render with their own options, not with it (they ignored it in
    silence, while ``render`` says when its options replace it)."""
    check_scene_name(scene)
    from .render import scene_file_integrator
    own = scene_file_integrator(scene)
    if own:
        log.warning(
            "scene %s has an <integrator type=\"%s\"> of its own, which %s does not use: it "
            "renders with its own options (partpm %s --help lists them and their defaults)",
            scene, own, command, command)


def run_compare(args) -> int:
    if not setup(args):
        return 0
    from ..experiments.compare import CompareSettings, format_table, run_compare
    if not args.out:
        raise UsageError("compare needs --out DIR")
    settings = CompareSettings(
        scene=args.scene, maps=args.maps or 8, photons=args.photons,
        resolution=args.resolution or (480, 480), spp=args.spp or 4,
        reference_spp=args.reference_spp, radius_fraction=args.radius_fraction, k=args.k,
        seed=args.seed, direct=args.direct, data_dir=args.data, best=not args.no_best)
    with user_errors(in_settings):
        settings.check()
    check_eye_pass(settings.resolution, settings.spp)     # (path's reference splits its own)
    check_experiment_scene(args.scene, "compare")
    check_folder(args.out, "--out")
    with user_errors(in_settings):
        result = run_compare(settings, args.out, progress=progress(args))
    if not args.quiet:
        print(format_table(result))
        print(f"wrote    {args.out}/ (comparison.png, metrics.json, images and heat maps)")
    return 0


def run_bench(args) -> int:
    setup(args)
    from ..experiments.bench import format_bench, run_bench as run
    check_scene_name(args.scene)
    if args.out is not None:                   # "" is refused, not taken as no file
        check_writable(args.out, "--out")
    try:
        result = run(args.out, args.scene, size="smoke" if args.smoke else "full",
                     repeats=args.repeats, progress=progress(args))
    except (FileNotFoundError, ValueError) as e:
        raise UsageError(last_line(e)) from None
    print(format_bench(result))
    if args.out:
        print(f"wrote    {args.out}")
    return 0


def run_hwsim(args) -> int:
    from hwsim.cli import run
    from ..experiments.provenance import code_version
    try:
        return run(args, code=code_version())
    except (OSError, ValueError) as e:
        raise UsageError(str(e)) from None


def run_speedup(args) -> int:
    if not setup(args):
        return 0
    from ..experiments.speedup import check_speedup, format_speedup, run_speedup
    maps = int_list("--maps", args.maps)
    with user_errors(in_settings):              # the list's own errors, before any work
        check_speedup(maps, args.photons, args.repeats)
    check_eye_pass(args.resolution, args.spp)
    check_experiment_scene(args.scene, "speedup")
    check_folder(args.out, "--out")
    with user_errors(in_settings):
        result = run_speedup(args.scene, maps, args.out, args.photons, args.resolution,
                             args.spp, args.repeats, args.radius_fraction, args.seed,
                             args.data, progress=progress(args))
    if not args.quiet:
        print(format_speedup(result))
        print(f"wrote    {args.out}/speedup.csv, speedup.json, speedup.png and workloads/")
    return 0


def run_calibrate(args) -> int:
    from ..experiments import calibrate as cal
    if args.refit:
        if args.scene:
            raise UsageError(f"--refit fits the sets already in --out again: SCENE "
                             f"({' '.join(args.scene)}) does not apply")
        try:
            result = cal.refit(args.out, args.check, progress=progress(args))
        except (OSError, ValueError) as e:
            raise UsageError(str(e)) from None
    else:
        if not args.scene:
            raise UsageError("calibrate needs SCENE (or --refit to fit the sets in --out)")
        setup(args)
        # Each option's own error first; the size of the fit last (it is about them all).
        for scene in args.scene:
            check_experiment_scene(scene, "calibrate")
        try:
            fracs = [float(v) for v in args.radius_fractions.split(",")]
        except ValueError:
            raise UsageError(f"--radius-fractions must be comma-separated numbers in (0, 1], "
                             f"got {args.radius_fractions!r}") from None
        if not all(0 < f <= 1 for f in fracs) or len(set(fracs)) < len(fracs):
            raise UsageError(f"--radius-fractions must be distinct numbers in (0, 1], got "
                             f"{args.radius_fractions!r}")
        leaves = int_list("--leaf-sizes", args.leaf_sizes)
        maps = int_list("--maps", args.maps)
        photons = int_list("--photons", args.photons)
        if max(photons) > MAX_RUN:
            raise UsageError(f"--photons must be counts in [1, 2^32), got {max(photons)}")
        from ..experiments.speedup import check_maps
        with user_errors(in_settings):          # a count twice, before the fit's size
            check_maps(maps, MAX_RUN)           # the list alone: the photons come later
        check_eye_pass(args.resolution, args.spp)
        if args.check and not Path(args.check).is_dir():
            raise UsageError(f"--check {args.check!r} is not a folder (an earlier "
                             f"calibrate's --out)")
        check_folder(args.out, "--out")
        from hwsim.calibrate import COST_NAMES
        measured = len(leaves) * len(fracs) * sum(maps)
        if measured < len(COST_NAMES) + 1:   # checked before any map is timed
            raise UsageError(f"the fit of hwsim's {len(COST_NAMES)} costs needs at least "
                             f"{len(COST_NAMES) + 1} measured maps per scene; --leaf-sizes x "
                             f"--radius-fractions x the sum of --maps gives {len(leaves)} x "
                             f"{len(fracs)} x {sum(maps)} = {measured}: give more of any")
        with user_errors(in_settings):
            result = cal.run_calibrations(
                args.scene, args.out, leaves, fracs, maps, photons, args.resolution,
                args.spp, args.repeats, args.threads, args.seed, args.data, args.check,
                progress=progress(args))
    if not args.quiet:
        print(cal.format_calibration(result))
        where = (f"{args.out}/{{{','.join(result['dirs'].values())}}}" if "dirs" in result
                 else args.out)
        print(f"wrote    {where}/calibration.json, fitted_costs.toml, hwsim_fitted.toml"
              + ("" if args.refit else " and sets/")
              + (f"; {args.out}/calibration.json" if "dirs" in result else ""))
    return 0


def run_scaling(args) -> int:
    from ..experiments.scaling import format_scaling, run_scaling
    check_plugin_variant(args.variant)               # before any rank starts
    ranks = int_list("--ranks", args.ranks)
    if args.hostfile and not Path(args.hostfile).is_file():
        raise UsageError(f"--hostfile {args.hostfile!r} is not a file")
    if args.maps > args.photons:
        raise UsageError(f"--maps {args.maps} is more than --photons {args.photons}: every "
                         f"map needs at least one photon")
    # (Its first launch found out, and said spp.) The ranks' memory is theirs to check
    # where a hostfile runs them on other machines.
    check_eye_pass(args.resolution, args.spp, here=not args.hostfile)
    check_experiment_scene(args.scene, "scaling")
    check_folder(args.out, "--out")
    extra = ["-f", args.hostfile] if args.hostfile else []
    try:
        rows = run_scaling(args.scene, ranks, args.maps, args.out, args.photons,
                           args.resolution, args.spp, args.repeats, args.data, extra,
                           progress=progress(args), bench_repeats=args.bench_repeats,
                           variant=args.variant)
    except (FileNotFoundError, ValueError, RuntimeError) as e:
        raise UsageError(str(e)) from None
    if not args.quiet:
        print(format_scaling(rows))
        print(f"wrote    {args.out}/scaling.csv, scaling.json and collective.json")
    return 0


def run_converge(args) -> int:
    if not setup(args):
        return 0
    from ..experiments.converge import (METHODS, ConvergeSettings, format_converge,
                                        run_converge as run)
    from .render import PROP_OPTIONS, apply_text, check_caustic_options, quality_props
    props, partpm_props = quality_props(args)
    methods = tuple(m.strip() for m in args.methods.split(",") if m.strip())
    # Options left out take the settings' defaults; given (any value, a zero too), the
    # methods they are for must be run: unused, they would be named in the table.
    options = {"spp": "--spp", "photons": "--photons", "maps": "--maps",
               "radius_fraction": "--radius-fraction", "alpha": "--alpha", "k": "--k"}
    values = {key: getattr(args, key) for key in options if getattr(args, key) is not None}
    if set(methods) <= set(METHODS):            # (else the settings' check names them)
        for needs, given in (
                (("partpm", "pm"), [PROP_OPTIONS[p] for p in props] +
                 ([options["spp"]] if "spp" in values else [])),
                (("partpm",), [PROP_OPTIONS[p] for p in partpm_props] +
                 [options[k] for k in ("photons", "maps", "radius_fraction", "alpha")
                  if k in values]),
                (("pm",), [options["k"]] if "k" in values else [])):
            if given and not set(needs) & set(methods):
                raise UsageError(f"{apply_text(given)} to {' or '.join(needs)}, which "
                                 f"--methods {','.join(methods)} does not run")
    check_caustic_options(args)
    settings = ConvergeSettings(
        scene=args.scene, seconds=args.time, resolution=args.resolution,
        reference_spp=args.reference_spp, methods=methods, seed=args.seed,
        data_dir=args.data, props=props, partpm_props=partpm_props, **values)
    with user_errors(in_settings):
        settings.check()
    # (path's reference splits its own; partpm's eye paths keep their state between passes)
    check_eye_pass(settings.resolution, settings.spp, kept="partpm" in settings.methods)
    check_experiment_scene(args.scene, "converge")
    check_folder(args.out, "--out")
    with user_errors(in_settings):
        result = run(settings, args.out, progress=progress(args))
    if not args.quiet:
        print(format_converge(result))
        images = ", ".join(result["images"])
        print(f"wrote    {args.out}/converge.csv, converge.json, converge.png, {images} (each "
              f"method's last image)"
              + ("" if result["reference_reused"] else " and reference.exr"))
    return 0
