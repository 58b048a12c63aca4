"""The ``partpm`` command.

    partpm render SCENE [--integrator partpm|path] [--maps N] [--photons N]
                  [--radius R | --radius-fraction F] [--spp S] [--resolution WxH]
                  [--seed S] [--variant V] -o OUT.exr

SCENE is a built-in scene name (``partpm render --list``) or a Mitsuba XML file. Writes OUT.exr
and a tone-mapped OUT.png and prints the time of each phase. Errors end with one line on
stderr and exit status 2.
"""
from __future__ import annotations

import argparse
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


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="partpm", description=(
        "Partitioned photon maps for Mitsuba 3 (Tamura, Takizawa, Kobayashi)."))
    sub = parser.add_subparsers(dest="command", required=True)
    r = sub.add_parser("render", help="render a scene with partpm (or Mitsuba's path tracer)")
    r.add_argument("scene", nargs="?", help="built-in scene name or Mitsuba XML file")
    r.add_argument("--list", action="store_true", help="list the built-in scenes and exit")
    r.add_argument("--integrator", choices=("partpm", "path"), default="partpm")
    r.add_argument("--maps", type=_positive_int("--maps"), default=8,
                   help="number of partial photon maps n (default 8)")
    r.add_argument("--photons", type=_positive_int("--photons"), default=100_000,
                   help="photons emitted in total N (default 100000)")
    g = r.add_mutually_exclusive_group()
    g.add_argument("--radius", type=_positive_float("--radius"),
                   help="search radius in world units")
    g.add_argument("--radius-fraction", type=_positive_float("--radius-fraction", 1.0),
                   help="radius as a fraction of the scene's longest side (default 0.05)")
    r.add_argument("--direct", choices=("photons", "nee"), default="photons",
                   help="direct light from the maps (paper) or by emitter sampling")
    r.add_argument("--max-depth", type=int, default=-1, help="longest path (-1: unlimited)")
    r.add_argument("--spp", type=_positive_int("--spp"), help="samples per pixel")
    r.add_argument("--resolution", type=parse_resolution, help="film size WxH, e.g. 480x480")
    r.add_argument("--seed", type=int, default=0, help="seed of photons and eye samples")
    r.add_argument("--variant", default="llvm_ad_rgb", help="Mitsuba variant (llvm_ad_rgb)")
    r.add_argument("-o", "--output", help="output EXR file (a PNG is written beside it)")
    r.add_argument("-q", "--quiet", action="store_true", help="print only errors")
    return parser


def _render(args) -> int:
    import drjit as dr
    import mitsuba as mi

    from . import plugins
    if args.variant not in mi.variants():
        raise UsageError(f"--variant {args.variant!r} is not a Mitsuba variant; available: "
                         f"{', '.join(mi.variants())}")
    if args.integrator == "partpm":
        try:
            plugins.check_variant(args.variant)
        except ValueError as e:
            raise UsageError(str(e)) from None
    mi.set_variant(args.variant)
    import mi_partpm
    from .scenes import scene_names

    if args.list:
        print("\n".join(scene_names()))
        return 0
    if not args.scene:
        raise UsageError("render needs a SCENE (a built-in name or an XML file); "
                         f"built-in: {', '.join(scene_names())}")
    if not args.output:
        raise UsageError("render needs -o OUT.exr")
    out = Path(args.output)
    if out.suffix.lower() != ".exr":
        raise UsageError(f"-o must name an .exr file, got {args.output!r}")

    t0 = time.perf_counter()
    try:
        scene = mi_partpm.load_scene(args.scene, resolution=args.resolution, spp=args.spp)
    except (FileNotFoundError, ValueError) as e:
        raise UsageError(str(e)) from None
    if not scene.emitters():
        raise UsageError(f"scene {args.scene!r} has no emitter: nothing would be lit")
    if args.integrator == "partpm":
        desc = {"type": "partpm", "photon_count": args.photons, "map_count": args.maps,
                "seed": args.seed, "max_depth": args.max_depth, "direct": args.direct}
        if args.radius is not None:
            desc["radius"] = args.radius
        elif args.radius_fraction is not None:
            desc["radius_fraction"] = args.radius_fraction
    else:
        desc = {"type": "path", "max_depth": args.max_depth}
    try:
        integrator = mi.load_dict(desc)
    except (ValueError, RuntimeError) as e:
        raise UsageError(str(e).strip().splitlines()[-1]) from None
    film = scene.sensors()[0].film()
    log = logging.getLogger("mi_partpm")
    log.info("scene %s: %dx%d, %s", args.scene, film.size()[0], film.size()[1], integrator)
    t1 = time.perf_counter()
    image = mi.render(scene, integrator=integrator, seed=args.seed)
    dr.eval(image)
    dr.sync_thread()
    t2 = time.perf_counter()

    out.parent.mkdir(parents=True, exist_ok=True)
    bitmap = mi.Bitmap(image)
    bitmap.write(str(out))
    png = out.with_suffix(".png")
    mi.util.write_bitmap(str(png), image, write_async=False)
    stats = getattr(integrator, "stats", {})
    if not args.quiet:
        print(f"load     {t1 - t0:8.2f} s")
        for phase in ("trace", "build", "estimate"):
            if f"time_{phase}" in stats:
                print(f"{phase:8} {stats[f'time_{phase}']:8.2f} s")
        print(f"render   {t2 - t1:8.2f} s (all phases)")
        if stats:
            print(f"photons  {stats['photons_emitted']} emitted, {stats['photons_stored']} "
                  f"stored in {stats['map_count']} maps, radius {stats['radius']:.4g}")
        print(f"wrote    {out} and {png}")
    return 0


def main(argv=None) -> int:
    args = _parser().parse_args(argv)
    logging.basicConfig(level=logging.WARNING if getattr(args, "quiet", False) else logging.INFO,
                        format="%(message)s", stream=sys.stderr)
    try:
        if args.command == "render":
            return _render(args)
    except UsageError as e:
        print(f"partpm: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("partpm: interrupted", file=sys.stderr)
        return 130
    return 1


if __name__ == "__main__":
    sys.exit(main())
