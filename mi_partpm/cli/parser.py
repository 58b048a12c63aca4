"""The ``partpm`` command line: every subcommand's options."""
from __future__ import annotations

import argparse
import os

from hwsim.cli import add_arguments as hwsim_arguments

from ..kdtree.knn import MAX_K
from ..trace import MAX_RUN
from .common import (parse_resolution, positive_float, positive_int, radius_float,
                     scene_parameter, seed_int)

__all__ = ["build_parser"]


class _Parser(argparse.ArgumentParser):
    """argparse's parser whose errors are one line: the error, and where the options are
    listed (not the whole usage); ``argument --x: --x must ...`` says --x once. An option
    is taken only by its whole name (argparse took ``--pass 2`` for ``--passes 2``), and an
    unknown one is reported by the command it was given to, with the nearest of its
    options (a prop's name, ``--radius_fraction``, suggests ``--radius-fraction``)."""

    def __init__(self, *args, **kwargs):
        kwargs.setdefault("allow_abbrev", False)
        super().__init__(*args, **kwargs)

    def parse_args(self, args=None, namespace=None):
        values, unknown = self.parse_known_args(args, namespace)
        if unknown:
            parser = self
            for action in self._actions:
                if isinstance(action, argparse._SubParsersAction):
                    parser = action.choices.get(getattr(values, action.dest, None), self)
            parser.error(parser.unknown_message(unknown))
        return values

    def unknown_message(self, unknown) -> str:
        import difflib
        options = [o for action in self._actions for o in action.option_strings]
        message = f"unrecognized arguments: {' '.join(unknown)}"
        for word in unknown:
            if word.startswith("--"):
                name = word.split("=")[0].replace("_", "-")
                near = difflib.get_close_matches(name, options, n=1, cutoff=0.6)
                if near:
                    return f"{message} (did you mean {near[0]}?)"
        return message

    def error(self, message):
        import re
        found = re.match(r"argument (\S+?)(?:/\S+)?: (.*)", message)
        if found and found.group(2).startswith(found.group(1)):
            message = found.group(2)
        self.exit(2, f"{self.prog}: error: {message} ('{self.prog} --help' lists the "
                     f"options)\n")


def _scene_options(p, compare: bool = False):
    """Options shared by the subcommands that render a scene (render, compare)."""
    p.add_argument("scene", nargs="?", help="built-in scene name or Mitsuba XML file")
    p.add_argument("--list", action="store_true", help="list the built-in scenes and exit")
    p.add_argument("--maps", type=positive_int("--maps"),
                   help="number of partial photon maps n, in [1, --photons] (default 8)")
    # An experiment traces every map's photons in one run, of at most 2^32 - 1 paths.
    # compare renders pm too, whose k nearest photons are at least 2.
    p.add_argument("--photons", default=100_000,
                   type=positive_int("--photons", low=2 if compare else 1,
                                     high=MAX_RUN if compare else None),
                   help="photons emitted in total N, " + (">= 2 and < 2^32" if compare else
                                                          ">= 1") + " (default 100000)")
    p.add_argument("--k", type=positive_int("--k", 2, MAX_K),
                   help=f"photons per kNN estimate of pm, in [2, {MAX_K}] " + (
                       "(default: the k whose mean radius matches partpm's)" if compare
                       else "(default 50)"))
    p.add_argument("--direct", choices=("photons", "nee"), default="photons",
                   help="direct light from the maps (the paper's) or by emitter and BSDF "
                        "sampling with MIS, as path (default photons)")
    p.add_argument("--spp", type=positive_int("--spp"),
                   help="samples per pixel, >= 1 " + (
                       "(default 4)" if compare else "(default: the scene's; 4 for the "
                                                     "built-in ones)"))
    p.add_argument("--resolution", type=parse_resolution,
                   help="film size WxH, e.g. 480x480 " + (
                       "(default 480x480)" if compare else "(default: the scene's, 480x480 "
                                                           "for the built-in ones)"))
    p.add_argument("--seed", type=seed_int(), default=0,
                   help="seed of photons and eye samples, in [0, 2^32) (default 0)")
    p.add_argument("--data", metavar="DIR",
                   help="directory of scene data such as happy_buddha_20k.ply "
                        "(default: $PARTPM_DATA, else the package's copy)")
    p.add_argument("--variant", default="llvm_ad_rgb",
                   help="Mitsuba variant (default llvm_ad_rgb)")
    p.add_argument("-q", "--quiet", action="store_true", help="print only warnings and errors")


def _size_options(p, spp, repeats, repeats_help):
    """The workload-size options of the experiment commands (paper sizes by default)."""
    p.add_argument("--photons", type=positive_int("--photons", high=MAX_RUN), default=100_000,
                   help="photons emitted N, in [1, 2^32) (default 100000)")
    p.add_argument("--resolution", type=parse_resolution, default=(480, 480),
                   help="film size WxH (default 480x480)")
    if spp is not None:
        p.add_argument("--spp", type=positive_int("--spp"), default=spp,
                       help=f"samples per pixel (default {spp})")
    p.add_argument("--repeats", type=positive_int("--repeats"), default=repeats,
                   help=f"{repeats_help}; medians are reported (default {repeats})")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="partpm", description=(
        "Partitioned photon maps for Mitsuba 3 (Tamura, Takizawa, Kobayashi)."))
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)
    _render_options(sub)
    _experiment_options(sub)
    _figures_options(sub)
    return parser


def _render_options(sub):
    r = sub.add_parser("render", help="render a scene with partpm, pm or Mitsuba's path tracer")
    _scene_options(r)
    # Unset unless given, so that an option the chosen integrator ignores can be refused.
    r.set_defaults(photons=None, direct=None)
    r.add_argument("--integrator", choices=("partpm", "pm", "path"),
                   help="the renderer (default partpm; a scene file's own <integrator> when no "
                        "integrator option is given)")
    g = r.add_mutually_exclusive_group()
    g.add_argument("--radius", type=radius_float("--radius"),
                   help="search radius in world units (partpm), in [1e-15, 1e18] (default: "
                        "--radius-fraction of the scene)")
    g.add_argument("--radius-fraction", type=positive_float("--radius-fraction", 1.0),
                   help="radius as a fraction of the scene's longest side, in (0, 1] "
                        "(default 0.05; "
                        "0.025 for a progressive render: --passes > 1, or --time without "
                        "--passes)")
    r.add_argument("--max-radius", type=radius_float("--max-radius"),
                   help="cap of the kNN radius in world units (pm; default: none)")
    r.add_argument("--max-depth", type=int,
                   help="longest light path in segments, as for Mitsuba's path: -1 "
                        "(unlimited, the default) or >= 1")
    r.add_argument("--passes", type=positive_int("--passes"),
                   help="progressive passes of partpm, >= 1 (default 1: the paper's single "
                        "pass)")
    r.add_argument("--alpha", type=positive_float("--alpha", 1.0, high_open=True),
                   help="fraction of a pass's photons kept by the radius reduction, in (0, 1) "
                        "(default 0.7)")
    r.add_argument("--time", type=positive_float("--time"),
                   help="stop after the pass during which this many seconds have passed, > 0 "
                        "(without --passes: passes until then; default: no limit)")
    r.add_argument("--checkpoint-every", type=positive_int("--checkpoint-every"), metavar="K",
                   help="write the image so far every K passes, K in [1, --passes] (default: "
                        "only at the end)")
    r.add_argument("-D", dest="define", action="append", metavar="NAME=VALUE",
                   type=scene_parameter,
                   help="set the scene's parameter $NAME (value=\"$NAME\" in the scene file) "
                        "to VALUE, as mitsuba -D does; repeatable (the film size and the "
                        "sample count with --resolution and --spp)")
    _quality_options(r)
    r.add_argument("--backend", choices=("local", "mpi"),
                   help="where the maps run: this process (local, the default), or the ranks "
                        "of an MPI job (mpiexec -n P partpm render ... --backend mpi); given, "
                        "it also overrides a scene file's partpm's backend")
    r.add_argument("--stats-json", metavar="FILE",
                   help="also write the run's figures (per rank with --backend mpi) as JSON")
    r.add_argument("-o", "--output", help="output EXR file, required (a PNG is written beside "
                                          "it)")


def _quality_options(r):
    """The estimator's options beyond the paper (see the partpm plugin's docstring)."""
    from ..props import GLOSSY_MODES, KERNEL_NAMES, MAX_RAYS_PER_POINT
    r.add_argument("--kernel", choices=KERNEL_NAMES,
                   help="density kernel over the search disc (default box, the paper's)")
    r.add_argument("--caustic-photons", type=positive_int("--caustic-photons", low=0),
                   help="photons per pass for caustic maps of their own, 0 (off) or >= "
                        "--maps (partpm; default: none)")
    g = r.add_mutually_exclusive_group()
    g.add_argument("--caustic-radius", type=radius_float("--caustic-radius"),
                   help="the caustic maps' radius in world units, in [1e-15, 1e18] (default: "
                        "a quarter of the global radius)")
    g.add_argument("--caustic-radius-fraction",
                   type=positive_float("--caustic-radius-fraction", 1.0),
                   help="the caustic maps' radius over the scene's longest side, in (0, 1] "
                        "(default: a quarter of the global radius)")
    r.add_argument("--glossy", choices=GLOSSY_MODES,
                   help="at glossy surfaces: estimate from the map there (default), or trace "
                        "on by BSDF sampling")
    r.add_argument("--glossy-samples",
                   type=positive_int("--glossy-samples", high=MAX_RAYS_PER_POINT),
                   help="rays traced from an eye path's first glossy surface, in [1, 4096] "
                        "(with --glossy trace; default 1)")
    r.add_argument("--final-gather", metavar="RAYS",
                   type=positive_int("--final-gather", low=0, high=MAX_RAYS_PER_POINT),
                   help="final gather rays per visible point, 0 (off) or in [1, 4096] (partpm; "
                        "rays need --direct nee; default 0), as the final_gather prop")


def _experiment_options(sub):
    c = sub.add_parser("compare", help="pm vs partpm vs a path-traced reference "
                                       "(the paper's figures 7-12)")
    _scene_options(c, compare=True)
    c.add_argument("--radius-fraction", type=positive_float("--radius-fraction", 1.0),
                   default=0.05, help="r as a fraction of the scene's longest side "
                                      "(default 0.05, the paper's 1/20)")
    c.add_argument("--reference-spp", type=positive_int("--reference-spp"), default=512,
                   help="samples per pixel of the path-traced reference (default 512)")
    c.add_argument("--no-best", action="store_true",
                   help="skip partpm's best configuration (rendered beside the paper's by "
                        "default)")
    c.add_argument("--out", help="output directory, required (not with --list)")

    v = sub.add_parser("converge", help="error against wall time: progressive partpm, pm and "
                                        "Mitsuba's path against a path-traced reference")
    v.add_argument("scene", help="built-in scene name or Mitsuba XML file")
    v.add_argument("--time", type=positive_float("--time"), default=25.0,
                   help="the longest render of each method's curve: renders at doubling "
                        "sizes until one takes longer than this (so the last one, and the "
                        "run, take more; default 25)")
    v.add_argument("--resolution", type=parse_resolution, default=(160, 160),
                   help="film size WxH (default 160x160)")
    v.add_argument("--spp", type=positive_int("--spp"),
                   help="eye samples per pixel of partpm's passes and pm's renders (default "
                        "4)")
    v.add_argument("--photons", type=positive_int("--photons", high=MAX_RUN),
                   help="partpm's photons per pass, in [1, 2^32) (default 100000; pm's "
                        "curve doubles its photons from 10000, or from 4 x k when that is more)")
    v.add_argument("--maps", type=positive_int("--maps"),
                   help="partpm's maps (default 8)")
    v.add_argument("--radius-fraction", type=positive_float("--radius-fraction", 1.0),
                   help="partpm's initial radius over the scene (default: partpm's, 0.025 for "
                        "a progressive render)")
    v.add_argument("--alpha", type=positive_float("--alpha", 1.0, high_open=True),
                   help="partpm's alpha (default 0.7)")
    v.add_argument("--k", type=positive_int("--k", 2, MAX_K),
                   help="pm's k (default 50)")
    v.add_argument("--direct", choices=("photons", "nee"),
                   help="direct light of both photon mappers: from the maps (their default) or "
                        "by emitter and BSDF sampling with MIS, as path")
    _quality_options(v)
    v.add_argument("--reference-spp", type=positive_int("--reference-spp"), default=8192,
                   help="samples per pixel of the path-traced reference (default 8192)")
    v.add_argument("--methods", default="partpm,pm,path",
                   help="comma-separated methods (default partpm,pm,path)")
    v.add_argument("--seed", type=seed_int(), default=0, help="seed (default 0)")
    v.add_argument("--data", metavar="DIR", help="scene data directory ($PARTPM_DATA)")
    v.add_argument("--variant", default="llvm_ad_rgb", help="Mitsuba variant (llvm_ad_rgb)")
    v.add_argument("--out", required=True, help="output directory (CSV, JSON, plot, reference)")
    v.add_argument("-q", "--quiet", action="store_true", help="print only warnings and errors")

    e = sub.add_parser("speedup", help="the paper's experiment: per-map density-estimation "
                                       "time vs the number of maps (figures 5-6)")
    e.add_argument("scene", help="built-in scene name or Mitsuba XML file")
    e.add_argument("--maps", default="1,2,4,8,16,32",
                   help="comma-separated map counts n, 1 among them (the speedup is against "
                        "one map; default 1,2,4,8,16,32)")
    _size_options(e, spp=1, repeats=3, repeats_help="timed passes over every map")
    e.add_argument("--radius-fraction", type=positive_float("--radius-fraction", 1.0),
                   default=0.05, help="r as a fraction of the scene's longest side (0.05)")
    e.add_argument("--seed", type=seed_int(), default=0, help="photon seed (default 0)")
    e.add_argument("--data", metavar="DIR", help="scene data directory ($PARTPM_DATA)")
    e.add_argument("--variant", default="llvm_ad_rgb", help="Mitsuba variant (llvm_ad_rgb)")
    e.add_argument("--out", required=True, help="output directory (CSV, JSON, plot, workloads)")
    e.add_argument("-q", "--quiet", action="store_true", help="print only warnings and errors")

    b = sub.add_parser("bench", help="kd-tree, estimate, build, tracer and memory benchmarks "
                                     "against scipy, pykdtree and Mitsuba's path tracer")
    b.add_argument("--scene", default="cornell_box", help="scene (default cornell_box)")
    b.add_argument("--repeats", type=positive_int("--repeats"),
                   help="timed runs of every benchmark; medians are reported (default 5; "
                        "1 with --smoke)")
    b.add_argument("--smoke", action="store_true",
                   help="tiny sizes: checks that every benchmark runs, measures nothing")
    b.add_argument("--variant", default="llvm_ad_rgb", help="Mitsuba variant (llvm_ad_rgb)")
    b.add_argument("--out", help="write the table as JSON to this file")
    b.add_argument("-q", "--quiet", action="store_true", help="print only the table")

    h = sub.add_parser("hwsim", help="simulate a PE array on the workloads of 'partpm speedup'")
    hwsim_arguments(h)

    k = sub.add_parser("calibrate", help="per-map times and counts at several leaf sizes and "
                                         "radii; hwsim's costs fitted to them (the file "
                                         "[pe] costs = \"fitted\" runs on)")
    k.add_argument("scene", nargs="*", help="built-in scene names or Mitsuba XML files (not "
                                            "with --refit); with two or more, their maps are "
                                            "timed interleaved in one run, each scene's files "
                                            "go into --out/SCENE/ and each fit predicts the "
                                            "next scene's times (two: both ways)")
    k.add_argument("--leaf-sizes", default="8,32,128",
                   help="comma-separated kd-tree leaf sizes (default 8,32,128)")
    k.add_argument("--radius-fractions", default="0.025,0.05,0.1",
                   help="comma-separated radii over the scene's longest side (default "
                        "0.025,0.05,0.1)")
    k.add_argument("--maps", default="1,2,4,8,16,32",
                   help="comma-separated map counts n (default 1,2,4,8,16,32)")
    k.add_argument("--photons", default="100000",
                   help="photons emitted N: one count, or comma-separated, one per scene "
                        "(default 100000)")
    k.add_argument("--resolution", type=parse_resolution, default=(240, 240),
                   help="film size WxH (default 240x240)")
    k.add_argument("--spp", type=positive_int("--spp"), default=1,
                   help="samples per pixel (default 1)")
    k.add_argument("--repeats", type=positive_int("--repeats"), default=3,
                   help="timed runs of every map, interleaved over the sets; medians are "
                        "fitted (default 3)")
    k.add_argument("--threads", type=positive_int("--threads", high=4 * (os.cpu_count() or 1)),
                   default=1, help="Dr.Jit threads of the timed kernels, at most 4 per core "
                                   "(default 1: one thread's costs)")
    k.add_argument("--seed", type=seed_int(), default=0, help="photon seed (default 0)")
    k.add_argument("--check", metavar="DIR",
                   help="another scene's calibration measured earlier (its --out): fit on "
                        "each scene, predict the other's per-map times (timing both scenes in "
                        "one run, 'calibrate A B', keeps the machine's drift out)")
    k.add_argument("--refit", action="store_true",
                   help="fit the sets already in --out again (and --check), measure nothing")
    k.add_argument("--data", metavar="DIR", help="scene data directory ($PARTPM_DATA)")
    k.add_argument("--variant", default="llvm_ad_rgb", help="Mitsuba variant (llvm_ad_rgb)")
    k.add_argument("--out", required=True, help="output directory (sets/, calibration.json, "
                                                "fitted_costs.toml, hwsim_fitted.toml)")
    k.add_argument("-q", "--quiet", action="store_true", help="print only warnings and errors")

    m = sub.add_parser("scaling", help="strong scaling of the MPI backend over P ranks")
    m.add_argument("scene", help="built-in scene name or Mitsuba XML file")
    m.add_argument("--ranks", default="1,2", help="comma-separated rank counts P (default 1,2)")
    m.add_argument("--maps", type=positive_int("--maps"), default=8,
                   help="number of partial photon maps n (default 8)")
    _size_options(m, spp=4, repeats=3, repeats_help="runs per P")
    m.add_argument("--data", metavar="DIR", help="scene data directory ($PARTPM_DATA)")
    m.add_argument("--hostfile", help="MPI hostfile, passed to mpiexec -f (clusters)")
    m.add_argument("--variant", default="llvm_ad_rgb",
                   help="Mitsuba variant of every rank (llvm_ad_rgb)")
    m.add_argument("--bench-repeats", type=positive_int("--bench-repeats"), default=15,
                   help="timed reductions per message size in the micro-benchmark that fits "
                        "the alpha-beta model (default 15)")
    m.add_argument("--out", required=True, help="output directory (CSV, JSON, images)")
    m.add_argument("-q", "--quiet", action="store_true", help="print only warnings and errors")


def _figures_options(sub):
    f = sub.add_parser("figures", help="run every experiment behind the README and the "
                                       "notebooks (reusing runs of the same code and "
                                       "settings), then rewrite the README's tables, "
                                       "docs/images/ and docs/figures.json")
    f.add_argument("--out", help="where the runs go, one folder per step (default "
                                 "out/figures; with --smoke a new temporary folder)")
    f.add_argument("--only", metavar="NAME,...",
                   help="only these steps or groups (demo, speedup, hwsim, compare, "
                        "converge, scaling, bench, calibrate, large, notebooks), and the "
                        "steps they read; --list names them")
    f.add_argument("--smoke", action="store_true",
                   help="tiny sizes; writes nothing into docs/, notebooks/ or README.md (a "
                        "README copy with its blocks filled, the images and the provenance "
                        "go into --out)")
    f.add_argument("--list", action="store_true",
                   help="list the steps, their commands and whether each would be reused, "
                        "and the README blocks; run nothing")
    f.add_argument("-q", "--quiet", action="store_true", help="print only warnings and errors")
