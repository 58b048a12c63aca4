"""``partpm render``: one image with partpm, pm or Mitsuba's path tracer, and its figures.

Phases: the integrator from the options (:func:`integrator_desc`), the scene, the render, then
the outputs (EXR, PNG, optional JSON of the figures) and a summary of the phases' times.
"""
from __future__ import annotations

import json
import logging
from pathlib import Path

from .common import UsageError, last_line, setup

__all__ = ["run_render", "integrator_desc", "format_ranks"]

log = logging.getLogger("mi_partpm")


def integrator_desc(args) -> dict:
    """The ``mi.load_dict`` description of the integrator the options ask for."""
    if args.integrator == "path":
        desc = {"type": "path", "max_depth": args.max_depth}
        photon_options = [o for o, v in (
            ("--photons", args.photons), ("--maps", args.maps), ("--direct", args.direct),
            ("--radius", args.radius), ("--radius-fraction", args.radius_fraction),
            ("--k", args.k), ("--max-radius", args.max_radius)) if v is not None]
        if photon_options:
            raise UsageError(f"{', '.join(photon_options)} apply to the photon mappers "
                             f"(--integrator partpm or pm), not to path")
    else:
        desc = {"type": args.integrator, "photon_count": args.photons or 100_000,
                "seed": args.seed, "max_depth": args.max_depth,
                "direct": args.direct or "photons"}
    progressive = [o for o, v in (("--passes", args.passes), ("--alpha", args.alpha),
                                  ("--time", args.time),
                                  ("--checkpoint-every", args.checkpoint_every)) if v]
    if progressive and args.integrator != "partpm":
        raise UsageError(f"{', '.join(progressive)} apply to --integrator partpm only (the "
                         f"progressive photon mapper)")
    if args.checkpoint_every and not args.time and (args.passes or 1) == 1:
        raise UsageError("--checkpoint-every writes the image between passes: it needs a "
                         "progressive render (--passes P > 1, or --time SECONDS)")
    if args.integrator != "path":
        for key, value in (("kernel", args.kernel), ("glossy", args.glossy),
                           ("glossy_samples", args.glossy_samples)):
            if value is not None:
                desc[key] = value
    elif any(v is not None for v in (args.kernel, args.glossy, args.glossy_samples)):
        raise UsageError("--kernel, --glossy and --glossy-samples apply to the photon mappers "
                         "(--integrator partpm or pm)")
    partpm_only = [o for o, v in (("--caustic-photons", args.caustic_photons),
                                  ("--caustic-radius", args.caustic_radius),
                                  ("--caustic-radius-fraction", args.caustic_radius_fraction),
                                  ("--final-gather", args.final_gather)) if v]
    if partpm_only and args.integrator != "partpm":
        raise UsageError(f"{', '.join(partpm_only)} apply to --integrator partpm only")
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
    elif args.integrator == "partpm":
        if args.k is not None or args.max_radius is not None:
            raise UsageError("--k and --max-radius apply to --integrator pm only")
        desc["map_count"] = args.maps or 8
        desc["backend"] = args.backend
        for key, value in (("passes", args.passes), ("alpha", args.alpha),
                           ("time_limit", args.time)):
            if value is not None:
                desc[key] = value
        for key, value in (("caustic_photon_count", args.caustic_photons),
                           ("caustic_radius", args.caustic_radius),
                           ("caustic_radius_fraction", args.caustic_radius_fraction),
                           ("final_gather", args.final_gather)):
            if value is not None:
                desc[key] = value
        if args.radius is not None:
            desc["radius"] = args.radius
        elif args.radius_fraction is not None:
            desc["radius_fraction"] = args.radius_fraction
    if args.backend == "mpi" and args.integrator != "partpm":
        raise UsageError("--backend mpi needs --integrator partpm (the maps are what the ranks "
                         "share out)")
    return desc


def _output_path(args) -> Path:
    if not args.output:
        raise UsageError("render needs -o OUT.exr")
    out = Path(args.output)
    if out.suffix.lower() != ".exr":
        raise UsageError(f"-o must name an .exr file, got {args.output!r}")
    return out


def run_render(args) -> int:
    import mitsuba as mi

    import mi_partpm
    from ..scenes import check_scene
    from ..timing import Stopwatch
    if not setup(args, needs_plugins=args.integrator != "path"):
        return 0
    out = _output_path(args)
    try:
        integrator = mi.load_dict(integrator_desc(args))
    except (ValueError, RuntimeError) as e:
        raise UsageError(last_line(e)) from None
    clock = Stopwatch()
    try:
        scene = mi_partpm.load_scene(args.scene, resolution=args.resolution, spp=args.spp,
                                     data_dir=args.data)
        check_scene(scene, args.scene)
    except (FileNotFoundError, ValueError) as e:
        raise UsageError(str(e)) from None
    film = scene.sensors()[0].film()
    log.info("scene %s: %dx%d, %s", args.scene, film.size()[0], film.size()[1], integrator)
    seconds = {"load": clock.lap()}
    if args.checkpoint_every:
        integrator.on_pass = _checkpoints(args.checkpoint_every, out, integrator)
    try:
        image = mi.render(scene, integrator=integrator, seed=args.seed)
    except (ValueError, RuntimeError, MemoryError) as e:
        raise UsageError(last_line(e)) from None
    seconds["render"] = clock.lap(image)
    stats = getattr(integrator, "stats", {})
    backend = getattr(integrator, "backend", None)
    if backend is not None and not backend.is_root:
        return 0    # rank 0 holds the gathered image and writes it
    _write(args, out, image, stats, seconds, list(film.size()))
    if not args.quiet:
        print(_summary(stats, seconds, out))
    return 0


def _checkpoints(every: int, out: Path, integrator):
    """An ``on_pass`` that writes the image so far to ``out`` every ``every`` passes."""
    import mitsuba as mi

    def on_pass(info):
        backend = getattr(integrator, "backend", None)
        if info["pass"] % every or (backend is not None and not backend.is_root):
            return
        out.parent.mkdir(parents=True, exist_ok=True)
        image = info["image"]()
        mi.Bitmap(image).write(str(out))
        mi.util.write_bitmap(str(out.with_suffix(".png")), image, write_async=False)
        log.info("checkpoint: pass %d written to %s", info["pass"], out)
    return on_pass


def _write(args, out: Path, image, stats: dict, seconds: dict, resolution):
    import mitsuba as mi

    from ..experiments.provenance import code_version
    if args.stats_json:
        Path(args.stats_json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.stats_json).write_text(json.dumps(
            {"time_load": seconds["load"], "time_render": seconds["render"],
             "scene": args.scene, "integrator": args.integrator, "backend": args.backend,
             "resolution": resolution, "code": code_version(), **stats}, indent=2,
            default=str) + "\n")
    out.parent.mkdir(parents=True, exist_ok=True)
    mi.Bitmap(image).write(str(out))
    mi.util.write_bitmap(str(out.with_suffix(".png")), image, write_async=False)


def _summary(stats: dict, seconds: dict, out: Path) -> str:
    lines = [f"load     {seconds['load']:8.2f} s"]
    for phase in ("trace", "build", "eye", "estimate"):
        if f"time_{phase}" in stats:
            lines.append(f"{phase:8} {stats[f'time_{phase}']:8.2f} s")
    lines.append(f"render   {seconds['render']:8.2f} s (all phases)")
    if "peak_memory_bytes" in stats:
        lines.append(f"memory   {stats['peak_memory_bytes'] / 1e9:8.2f} GB peak (this process)")
    if stats:
        if "k" in stats:
            search = f"k = {stats['k']}, mean kNN radius {stats['mean_knn_radius']:.4g}"
        else:
            search = f"radius {stats['radius']:.4g}"
        passes = stats.get("passes", 1)
        per_pass = f" per pass, {passes} passes" if passes > 1 else ""
        lines.append(f"photons  {stats['photons_emitted']} emitted{per_pass}, "
                     f"{stats['photons_stored']} stored in {stats['map_count']} maps, {search}")
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
