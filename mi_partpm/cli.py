"""The ``partpm`` command.

    partpm render SCENE [--integrator partpm|pm|path] [--maps N] [--photons N] [--k K]
                  [--radius R | --radius-fraction F] [--spp S] [--resolution WxH]
                  [--seed S] [--data DIR] [--variant V] -o OUT.exr
    partpm compare SCENE [--maps N] [--photons N] [--k K] [--resolution WxH] [--spp S]
                  [--reference-spp S] [--data DIR] --out DIR

SCENE is a built-in scene name (``partpm render --list``) or a Mitsuba XML file. ``render``
writes OUT.exr and a tone-mapped OUT.png and prints the time of each phase. ``compare`` renders
the conventional ``pm``, the partitioned ``partpm`` and a ``path`` reference and writes images,
difference heat maps, a side-by-side sheet and metrics.json (the paper's figures 7-12).
Errors end with one line on stderr and exit status 2.
"""
from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path

__all__ = ["main", "parse_resolution"]


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


def _positive_int(name):
    def parse(text):
        try:
            value = int(text)
        except ValueError:
            value = 0
        if value < 1 or str(value) != text.strip().lstrip("+"):
            raise argparse.ArgumentTypeError(f"{name} must be an integer >= 1, got {text!r}")
        return value
    return parse


def _positive_float(name, high=None):
    def parse(text):
        try:
            value = float(text)
        except ValueError:
            value = float("nan")
        if not (value > 0 and value != float("inf") and (high is None or value <= high)):
            allowed = f"in (0, {high}]" if high is not None else "> 0 and finite"
            raise argparse.ArgumentTypeError(f"{name} must be a number {allowed}, got {text!r}")
        return value
    return parse


def _scene_options(p, maps_default=8):
    """Options shared by the subcommands that render a scene."""
    p.add_argument("scene", nargs="?", help="built-in scene name or Mitsuba XML file")
    p.add_argument("--list", action="store_true", help="list the built-in scenes and exit")
    p.add_argument("--maps", type=_positive_int("--maps"),
                   help=f"number of partial photon maps n (default {maps_default})")
    p.add_argument("--photons", type=_positive_int("--photons"), default=100_000,
                   help="photons emitted in total N (default 100000)")
    p.add_argument("--k", type=_positive_int("--k"),
                   help="photons per kNN estimate of pm")
    p.add_argument("--direct", choices=("photons", "nee"), default="photons",
                   help="direct light from the maps (paper) or by emitter sampling")
    p.add_argument("--spp", type=_positive_int("--spp"), help="samples per pixel")
    p.add_argument("--resolution", type=parse_resolution, help="film size WxH, e.g. 480x480")
    p.add_argument("--seed", type=int, default=0, help="seed of photons and eye samples")
    p.add_argument("--data", metavar="DIR",
                   help="directory of scene data such as happy_buddha_20k.ply "
                        "(default: $PARTPM_DATA, else the package's copy)")
    p.add_argument("--variant", default="llvm_ad_rgb", help="Mitsuba variant (llvm_ad_rgb)")
    p.add_argument("-q", "--quiet", action="store_true", help="print only errors")


def _size_options(p, spp, repeats, repeats_help):
    """The workload-size options of the experiment commands (paper sizes by default)."""
    p.add_argument("--photons", type=_positive_int("--photons"), default=100_000,
                   help="photons emitted N (default 100000)")
    p.add_argument("--resolution", type=parse_resolution, default=(480, 480),
                   help="film size WxH (default 480x480)")
    if spp is not None:
        p.add_argument("--spp", type=_positive_int("--spp"), default=spp,
                       help=f"samples per pixel (default {spp})")
    p.add_argument("--repeats", type=_positive_int("--repeats"), default=repeats,
                   help=f"{repeats_help}; medians are reported (default {repeats})")


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="partpm", description=(
        "Partitioned photon maps for Mitsuba 3 (Tamura, Takizawa, Kobayashi)."))
    sub = parser.add_subparsers(dest="command", required=True)
    r = sub.add_parser("render", help="render a scene with partpm, pm or Mitsuba's path tracer")
    _scene_options(r)
    r.add_argument("--integrator", choices=("partpm", "pm", "path"), default="partpm")
    g = r.add_mutually_exclusive_group()
    g.add_argument("--radius", type=_positive_float("--radius"),
                   help="search radius in world units (partpm)")
    g.add_argument("--radius-fraction", type=_positive_float("--radius-fraction", 1.0),
                   help="radius as a fraction of the scene's longest side (default 0.05)")
    r.add_argument("--max-radius", type=_positive_float("--max-radius"),
                   help="cap of the kNN radius (pm; default: none)")
    r.add_argument("--max-depth", type=int, default=-1, help="longest path (-1: unlimited)")
    r.add_argument("--backend", choices=("local", "mpi"), default="local",
                   help="where the maps run: this process, or the ranks of an MPI job "
                        "(mpiexec -n P partpm render ... --backend mpi)")
    r.add_argument("--stats-json", metavar="FILE",
                   help="also write the run's figures (per rank with --backend mpi) as JSON")
    r.add_argument("-o", "--output", help="output EXR file (a PNG is written beside it)")

    c = sub.add_parser("compare", help="pm vs partpm vs a path-traced reference "
                                       "(the paper's figures 7-12)")
    _scene_options(c)
    c.add_argument("--radius-fraction", type=_positive_float("--radius-fraction", 1.0),
                   default=0.05, help="r as a fraction of the scene's longest side "
                                      "(default 0.05, the paper's 1/20)")
    c.add_argument("--reference-spp", type=_positive_int("--reference-spp"), default=512,
                   help="samples per pixel of the path-traced reference (default 512)")
    c.add_argument("--out", help="output directory")

    e = sub.add_parser("speedup", help="the paper's experiment: per-map density-estimation "
                                       "time vs the number of maps (figures 5-6)")
    e.add_argument("scene", help="built-in scene name or Mitsuba XML file")
    e.add_argument("--maps", default="1,2,4,8,16,32",
                   help="comma-separated map counts n (default 1,2,4,8,16,32)")
    _size_options(e, spp=1, repeats=3, repeats_help="timed passes over every map")
    e.add_argument("--radius-fraction", type=_positive_float("--radius-fraction", 1.0),
                   default=0.05, help="r as a fraction of the scene's longest side (0.05)")
    e.add_argument("--seed", type=int, default=0, help="photon seed (default 0)")
    e.add_argument("--data", metavar="DIR", help="scene data directory ($PARTPM_DATA)")
    e.add_argument("--variant", default="llvm_ad_rgb", help="Mitsuba variant (llvm_ad_rgb)")
    e.add_argument("--out", required=True, help="output directory (CSV, JSON, plot, workloads)")
    e.add_argument("-q", "--quiet", action="store_true", help="print only errors")

    b = sub.add_parser("bench", help="kd-tree and tracer benchmarks against scipy, pykdtree "
                                     "and Mitsuba's path tracer")
    b.add_argument("--scene", default="cornell_box", help="scene (default cornell_box)")
    _size_options(b, spp=None, repeats=5, repeats_help="timed runs of every benchmark")
    b.add_argument("--smoke", action="store_true",
                   help="tiny sizes: checks that every benchmark runs, measures nothing")
    b.add_argument("--variant", default="llvm_ad_rgb", help="Mitsuba variant (llvm_ad_rgb)")
    b.add_argument("--out", help="write the table as JSON to this file")
    b.add_argument("-q", "--quiet", action="store_true", help="print only the table")

    h = sub.add_parser("hwsim", help="simulate a PE array on the workloads of 'partpm speedup'")
    h.add_argument("workloads", help="a workloads/ directory written by 'partpm speedup'")
    h.add_argument("--config", help="hardware configuration (TOML; every key, unit and default "
                                     "in hwsim/default.toml)")
    h.add_argument("--check", metavar="WORKLOAD_DIR",
                   help="another scene's workloads: predict its measured per-map times with "
                        "the costs calibrated on 'workloads'")
    h.add_argument("--out", required=True, help="output directory (JSON, CSV, plots)")
    h.add_argument("-q", "--quiet", action="store_true", help="print only errors")

    m = sub.add_parser("scaling", help="strong scaling of the MPI backend over P ranks")
    m.add_argument("scene", help="built-in scene name or Mitsuba XML file")
    m.add_argument("--ranks", default="1,2", help="comma-separated rank counts P (default 1,2)")
    m.add_argument("--maps", type=_positive_int("--maps"), default=8,
                   help="number of partial photon maps n (default 8)")
    _size_options(m, spp=4, repeats=3, repeats_help="runs per P")
    m.add_argument("--data", metavar="DIR", help="scene data directory ($PARTPM_DATA)")
    m.add_argument("--hostfile", help="MPI hostfile, passed to mpiexec -f (clusters)")
    m.add_argument("--bench-repeats", type=_positive_int("--bench-repeats"), default=15,
                   help="timed reductions per message size in the micro-benchmark that fits "
                        "the alpha-beta model (default 15)")
    m.add_argument("--out", required=True, help="output directory (CSV, JSON, images)")
    m.add_argument("-q", "--quiet", action="store_true", help="print only errors")
    return parser


def _setup(args, needs_plugins=True):
    """Choose the variant, import the plugins, answer --list, check SCENE. True: go on."""
    import mitsuba as mi

    from . import plugins
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
    from .scenes import scene_names

    if getattr(args, "list", False):
        print("\n".join(scene_names()))
        return False
    if not args.scene:
        raise UsageError(f"{args.command} needs a SCENE (a built-in name or an XML file); "
                         f"built-in: {', '.join(scene_names())}")
    return True


def _render(args) -> int:
    import drjit as dr
    import mitsuba as mi

    if not _setup(args, needs_plugins=args.integrator != "path"):
        return 0
    import mi_partpm
    if not args.output:
        raise UsageError("render needs -o OUT.exr")
    out = Path(args.output)
    if out.suffix.lower() != ".exr":
        raise UsageError(f"-o must name an .exr file, got {args.output!r}")

    if args.integrator in ("partpm", "pm"):
        desc = {"type": args.integrator, "photon_count": args.photons, "seed": args.seed,
                "max_depth": args.max_depth, "direct": args.direct}
        if args.integrator == "pm":
            unused = [o for o, v in (("--maps", args.maps), ("--radius", args.radius),
                                     ("--radius-fraction", args.radius_fraction)) if v]
            if unused:
                raise UsageError(f"{', '.join(unused)} do(es) not apply to --integrator pm "
                                 f"(one map, k nearest photons: use --k, --max-radius)")
            if args.k is not None:
                desc["k"] = args.k
            if args.max_radius is not None:
                desc["max_radius"] = args.max_radius
        else:
            if args.k is not None or args.max_radius is not None:
                raise UsageError("--k and --max-radius apply to --integrator pm only")
            desc["map_count"] = args.maps or 8
            desc["backend"] = args.backend
            if args.radius is not None:
                desc["radius"] = args.radius
            elif args.radius_fraction is not None:
                desc["radius_fraction"] = args.radius_fraction
    else:
        desc = {"type": "path", "max_depth": args.max_depth}
    if args.backend == "mpi" and args.integrator != "partpm":
        raise UsageError("--backend mpi needs --integrator partpm (the maps are what the ranks "
                         "share out)")
    try:
        integrator = mi.load_dict(desc)
    except (ValueError, RuntimeError) as e:
        raise UsageError(_last_line(e)) from None
    t0 = time.perf_counter()
    try:
        scene = mi_partpm.load_scene(args.scene, resolution=args.resolution, spp=args.spp,
                                     data_dir=args.data)
    except (FileNotFoundError, ValueError) as e:
        raise UsageError(str(e)) from None
    if not scene.emitters():
        raise UsageError(f"scene {args.scene!r} has no emitter: nothing would be lit")
    if not scene.sensors():
        raise UsageError(f"scene {args.scene!r} has no sensor: add a camera to render it")
    film = scene.sensors()[0].film()
    log = logging.getLogger("mi_partpm")
    log.info("scene %s: %dx%d, %s", args.scene, film.size()[0], film.size()[1], integrator)
    t1 = time.perf_counter()
    try:
        image = mi.render(scene, integrator=integrator, seed=args.seed)
    except (ValueError, RuntimeError, MemoryError) as e:
        raise UsageError(_last_line(e)) from None
    dr.eval(image)
    dr.sync_thread()
    t2 = time.perf_counter()
    stats = getattr(integrator, "stats", {})
    if getattr(integrator, "comm", None) is not None and integrator.comm.rank != 0:
        return 0    # rank 0 holds the gathered image and writes it

    if args.stats_json:
        Path(args.stats_json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.stats_json).write_text(json.dumps(
            {"time_load": t1 - t0, "time_render": t2 - t1, "scene": args.scene,
             "integrator": args.integrator, "backend": args.backend,
             "resolution": list(film.size()), **stats}, indent=2, default=str) + "\n")
    out.parent.mkdir(parents=True, exist_ok=True)
    bitmap = mi.Bitmap(image)
    bitmap.write(str(out))
    png = out.with_suffix(".png")
    mi.util.write_bitmap(str(png), image, write_async=False)
    if not args.quiet:
        print(f"load     {t1 - t0:8.2f} s")
        for phase in ("trace", "build", "estimate"):
            if f"time_{phase}" in stats:
                print(f"{phase:8} {stats[f'time_{phase}']:8.2f} s")
        print(f"render   {t2 - t1:8.2f} s (all phases)")
        if "peak_memory_bytes" in stats:
            print(f"memory   {stats['peak_memory_bytes'] / 1e9:8.2f} GB peak (this process)")
        if stats:
            if "k" in stats:
                search = (f"k = {stats['k']}, mean kNN radius "
                          f"{stats['mean_knn_radius']:.4g}")
            else:
                search = f"radius {stats['radius']:.4g}"
            print(f"photons  {stats['photons_emitted']} emitted, {stats['photons_stored']} "
                  f"stored in {stats['map_count']} maps, {search}")
        if stats.get("ranks"):
            print(format_ranks(stats["ranks"]))
        print(f"wrote    {out} and {png}")
    return 0


def format_ranks(ranks) -> str:
    """Per-rank figures of an MPI render as a small table."""
    lines = [f"{'rank':>4} {'maps':>10} {'photons':>9} {'stored':>9} {'tree MB':>8} "
             f"{'trace s':>8} {'build s':>8} {'estim s':>8} {'wait s':>7} {'reduce s':>8} "
             f"{'reduce MB':>9}"]
    for j, r in enumerate(ranks):
        maps = ",".join(str(m) for m in r["maps_owned"])
        maps = maps if len(maps) <= 10 else maps[:8] + ".."
        lines.append(f"{j:4d} {maps:>10} {r['photons_traced']:9d} {r['photons_stored']:9d} "
                     f"{r['map_bytes'] / 1e6:8.2f} {r['time_trace']:8.2f} "
                     f"{r['time_build']:8.2f} {r['time_estimate']:8.2f} {r['time_wait']:7.3f} "
                     f"{r['time_reduce']:8.4f} {r['reduce_bytes'] / 1e6:9.2f}")
    return "\n".join(lines)


def _progress(args):
    """Where a long command's progress lines go: stdout, or nowhere with -q."""
    return None if args.quiet else (lambda line: print(line, flush=True))


def _last_line(e: Exception) -> str:
    """The message of an error raised inside a plugin (Mitsuba wraps it in a traceback, and
    mi.render in a RuntimeError whose cause is the original error)."""
    while e.__cause__ is not None:
        e = e.__cause__
    line = str(e).strip().splitlines()[-1] if str(e).strip() else type(e).__name__
    for prefix in ("ValueError: ", "RuntimeError: ", "FileNotFoundError: "):
        if line.startswith(prefix):
            line = line[len(prefix):]
    return line


def _compare(args) -> int:
    if not _setup(args):
        return 0
    from .compare import CompareSettings, format_table, run_compare
    if not args.out:
        raise UsageError("compare needs --out DIR")
    settings = CompareSettings(
        scene=args.scene, maps=args.maps or 8, photons=args.photons,
        resolution=args.resolution or (480, 480), spp=args.spp or 4,
        reference_spp=args.reference_spp, radius_fraction=args.radius_fraction, k=args.k,
        seed=args.seed, direct=args.direct, data_dir=args.data)
    try:
        settings.check()
    except ValueError as e:
        raise UsageError(str(e)) from None
    try:
        result = run_compare(settings, args.out,
                             progress=_progress(args))
    except (FileNotFoundError, ValueError) as e:
        raise UsageError(_last_line(e)) from None
    if not args.quiet:
        print(format_table(result))
        print(f"wrote    {args.out}/ (comparison.png, metrics.json, images and heat maps)")
    return 0


def _int_list(option, text):
    try:
        values = [int(v) for v in text.split(",")]
    except ValueError:
        values = []
    if not values or min(values) < 1:
        raise UsageError(f"{option} must be comma-separated integers >= 1, got {text!r}")
    return values


def _bench(args) -> int:
    _setup(args)
    from .bench import format_bench, run_bench
    sizes = dict(photons=args.photons, resolution=args.resolution, repeats=args.repeats)
    if args.smoke:
        sizes = dict(photons=5000, resolution=(32, 32), repeats=1, big=20_000, huge=100_000,
                     trace_photons_count=20_000, path_spp=2)
    result = run_bench(args.out, args.scene, progress=_progress(args), **sizes)
    print(format_bench(result))
    if args.out:
        print(f"wrote    {args.out}")
    return 0


def _hwsim(args) -> int:
    from hwsim.config import load_config
    from hwsim.report import format_report, run_report
    try:
        config = load_config(args.config)
        result = run_report(args.workloads, config, args.out, args.check,
                            progress=_progress(args))
    except (OSError, ValueError) as e:
        raise UsageError(str(e)) from None
    if not args.quiet:
        print(format_report(result))
        print(f"wrote    {args.out}/report.json, report.csv, sweep.csv, contention.csv, "
              f"sensitivity.csv, hwsim.png")
    return 0


def _speedup(args) -> int:
    _setup(args)
    from .speedup import format_speedup, run_speedup
    maps = _int_list("--maps", args.maps)
    try:
        result = run_speedup(args.scene, maps, args.out, args.photons, args.resolution,
                             args.spp, args.repeats, args.radius_fraction, args.seed,
                             args.data, progress=_progress(args))
    except (FileNotFoundError, ValueError) as e:
        raise UsageError(str(e)) from None
    if not args.quiet:
        print(format_speedup(result))
        print(f"wrote    {args.out}/speedup.csv, speedup.json, speedup.png and workloads/")
    return 0


def _scaling(args) -> int:
    from .scaling import format_scaling, run_scaling
    ranks = _int_list("--ranks", args.ranks)
    extra = ["-f", args.hostfile] if args.hostfile else []
    try:
        rows = run_scaling(args.scene, ranks, args.maps, args.out, args.photons,
                           args.resolution, args.spp, args.repeats, args.data, extra,
                           progress=_progress(args), bench_repeats=args.bench_repeats)
    except (FileNotFoundError, ValueError, RuntimeError) as e:
        raise UsageError(str(e)) from None
    if not args.quiet:
        print(format_scaling(rows))
        print(f"wrote    {args.out}/scaling.csv, scaling.json and collective.json")
    return 0


def main(argv=None) -> int:
    args = _parser().parse_args(argv)
    logging.basicConfig(level=logging.WARNING if getattr(args, "quiet", False) else logging.INFO,
                        format="%(message)s", stream=sys.stderr)
    try:
        if args.command == "render":
            return _render(args)
        if args.command == "compare":
            return _compare(args)
        if args.command == "scaling":
            return _scaling(args)
        if args.command == "speedup":
            return _speedup(args)
        if args.command == "bench":
            return _bench(args)
        if args.command == "hwsim":
            return _hwsim(args)
    except UsageError as e:
        print(f"partpm: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("partpm: interrupted", file=sys.stderr)
        return 130
    return 1


if __name__ == "__main__":
    sys.exit(main())
