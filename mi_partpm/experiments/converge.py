"""``partpm converge``: error against wall time for progressive partpm, pm and Mitsuba's path.

Every method renders the same scene, film and camera, and each image is compared with one
reference: Mitsuba's ``path`` at a high sample count, rendered in chunks of
``CHUNK_SPP`` samples with different seeds (a single wavefront of that many samples would not
fit in memory) and cached in the output directory (``reference.exr`` and ``reference.json``,
reused when the scene's files (by content, wherever they are), size, sample count, seed,
Mitsuba version and variant match: the reference does not depend on this project's code).
Its own noise is estimated from its two halves (the even and the odd chunks,
:func:`~.reference.noise_rel_mse`), said, drawn in the plot and recorded as
``reference_rel_mse``: errors near it measure the reference rather than the method.

- **partpm**: one progressive render with ``time_limit = seconds``; after passes 1, 2, 3, 4,
  6, 8, 11, 16, 23, ... (about sqrt 2 apart) the image so far is developed and measured (the
  time spent doing so is not counted).
- **path**: renders of 1, 2, 4, ... samples per pixel, each timed on its own, until one takes
  longer than ``seconds`` (above ``PATH_CHUNK_SPP`` samples, in chunks of that many, whose
  times add up).
- **pm**: single-pass renders of 10^4, 2 x 10^4, 4 x 10^4, ... photons with k nearest, until
  one takes longer than ``seconds``.

``props`` (direct light, kernel, glossy surfaces: :data:`SHARED_PROPS`) go to both photon
mappers, ``partpm_props`` (caustic maps, final gather: :data:`PARTPM_PROPS`) to partpm alone,
so the curves can be those of the settings a user renders with. Where the scene holds light
that ``path`` cannot render (:func:`~.reference.caustics_path_misses`), the run warns and
records it (``reference_misses``). A curve that ends before ``seconds`` (a render that does
not fit in memory) has no error after its last point (``ends``).

Each method runs once untimed at a tiny size first, so no curve pays for compiling kernels.
The error is the relative MSE of :func:`mi_partpm.experiments.metrics.rel_mse` on the linear,
unclamped images. Writes ``converge.csv`` (method, seconds, relMSE, setting),
``converge.json``, ``converge.png`` (log-log) and each method's last image
(``partpm.exr``, ``pm.exr``, ``path.exr``), to look at where its error lies.
"""
from __future__ import annotations

import csv
import json
import logging
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Optional, Tuple

import drjit as dr
import mitsuba as mi
import numpy as np

from . import metrics
from .provenance import code_version, scene_digest
from .reference import caustics_path_misses, noise_rel_mse, path_in_chunks
from ..plugins import load_integrator
from ..props import PARTPM_QUALITY_PROPS, QUALITY_PROPS, check_float, check_int
from ..scenes import check_scene, load_scene
from ..timing import timed

__all__ = ["ConvergeSettings", "run_converge", "format_converge", "path_reference",
           "METHODS", "CHUNK_SPP", "SHARED_PROPS", "PARTPM_PROPS", "settings_text",
           "ended_text"]

log = logging.getLogger("mi_partpm")

#: The methods a run can compare.
METHODS = ("partpm", "pm", "path")

#: Samples per pixel of one chunk of the reference (rendered and averaged chunk by chunk).
CHUNK_SPP = 64

#: Props a run may give both photon mappers, and props for partpm alone.
SHARED_PROPS = QUALITY_PROPS
PARTPM_PROPS = PARTPM_QUALITY_PROPS

#: Why a curve ends before the time limit, by the reason its method gives.
ENDED_BY = {"memory": "its next render did not fit in memory",
            "radius": "its next pass's radius would be below the least a search takes",
            "request": "it was asked to stop"}


@dataclass
class ConvergeSettings:
    """What :func:`run_converge` renders."""

    scene: str = "cornell_box"
    seconds: float = 25.0
    resolution: Tuple[int, int] = (160, 160)
    spp: int = 4                    # partpm: eye samples per pixel and pass
    photons: int = 100_000          # partpm: photons per pass (pm's curve: PM_START, doubled)
    maps: int = 8
    radius_fraction: Optional[float] = None   # partpm's initial radius (None: its default)
    alpha: float = 0.7
    k: int = 50                     # pm
    reference_spp: int = 8192
    methods: Tuple[str, ...] = METHODS
    seed: int = 0
    data_dir: Optional[str] = None
    props: dict = field(default_factory=dict)          # both photon mappers (SHARED_PROPS)
    partpm_props: dict = field(default_factory=dict)   # partpm alone (PARTPM_PROPS)

    def check(self):
        check_float("seconds", self.seconds, low=0.0)
        for v in self.resolution:
            check_int("resolution", v, low=1)
        check_int("spp", self.spp, low=1)
        check_int("photons", self.photons, low=1)
        check_int("maps", self.maps, low=1, high=self.photons)
        if self.radius_fraction is not None:
            check_float("radius_fraction", self.radius_fraction, low=0.0, high=1.0)
        check_float("alpha", self.alpha, low=0.0, high=1.0, high_open=True)
        check_int("k", self.k, low=2)               # pm's k nearest photons
        check_int("reference_spp", self.reference_spp, low=1)
        unknown = [m for m in self.methods if m not in METHODS]
        if unknown or not self.methods:
            raise ValueError(f"methods must be some of {', '.join(METHODS)}, got "
                             f"{', '.join(self.methods) or 'none'}")
        twice = sorted({m for m in self.methods if self.methods.count(m) > 1})
        if twice:
            raise ValueError(f"methods must name each method once, got {', '.join(twice)} "
                             f"more than once")
        for given, allowed, name in ((self.props, SHARED_PROPS, "props"),
                                     (self.partpm_props, PARTPM_PROPS, "partpm_props")):
            unknown = sorted(set(given) - set(allowed))
            if unknown:
                raise ValueError(f"{name} must be some of {', '.join(allowed)}, got "
                                 f"{', '.join(unknown)}")
        # Props for a method the run does not render would be named in its table unused.
        mappers = [m for m in ("partpm", "pm") if m in self.methods]
        if self.props and not mappers:
            raise ValueError(f"methods must include partpm or pm for "
                             f"{settings_text(self.props)} (the photon mappers' props), got "
                             f"{', '.join(self.methods)}")
        if self.partpm_props and "partpm" not in self.methods:
            raise ValueError(f"methods must include partpm for "
                             f"{settings_text(self.partpm_props)} (partpm's props), got "
                             f"{', '.join(self.methods)}")
        # Every value as the plugins check them, before any rendering.
        if "partpm" in self.methods:
            load_integrator({**self._partpm_desc(), "passes": 2})
        if "pm" in self.methods:
            load_integrator(self._pm_desc(max(PM_START, 4 * self.k)))

    def check_scene(self, scene):
        """What depends on the scene, before any rendering: partpm's radii (the caustic
        maps' radius below the least a search takes, say), as its first pass would find
        them."""
        if "partpm" in self.methods:
            load_integrator({**self._partpm_desc(), "time_limit": self.seconds}) \
                .search_radius(scene)

    def _partpm_desc(self) -> dict:
        desc = {"type": "partpm", "photon_count": self.photons, "map_count": self.maps,
                "alpha": self.alpha, "seed": self.seed, **self.props, **self.partpm_props}
        if self.radius_fraction is not None:
            desc["radius_fraction"] = self.radius_fraction
        return desc

    def _pm_desc(self, photons: int) -> dict:
        return {"type": "pm", "photon_count": photons, "k": self.k, "seed": self.seed,
                **self.props}


def settings_text(props: dict) -> str:
    """The props a run gave the photon mappers, as words for a label ("" for none)."""
    return ", ".join(f"{k} = {v}" for k, v in props.items())


def _scene(s: ConvergeSettings, spp: int = 1):
    scene = load_scene(s.scene, resolution=s.resolution, spp=spp, data_dir=s.data_dir)
    check_scene(scene, s.scene)
    return scene


def _image(img) -> np.ndarray:
    return np.array(img, dtype=np.float64)[..., :3]


def path_reference(s: ConvergeSettings, out: Path, say, scene=None):
    """Mitsuba's ``path`` at ``reference_spp``, averaged over chunks, of ``scene`` (default:
    loaded from the settings); cached in ``out``. Returns (image, its estimated relative MSE against the truth or None for one chunk,
    whether it was reused)."""
    # The scene by its files' contents: the same file named another way is the same scene.
    meta = {"scene_sha256": scene_digest(s.scene, s.data_dir),
            "resolution": list(s.resolution), "spp": s.reference_spp, "seed": s.seed,
            "mitsuba": mi.__version__, "variant": mi.variant()}
    exr, info = out / "reference.exr", out / "reference.json"
    recorded = _json_or_none(info) if info.is_file() else None
    if exr.is_file() and isinstance(recorded, dict) and "noise_rel_mse" in recorded and \
            {k: recorded.get(k) for k in meta} == meta:
        try:
            image = _image(mi.Bitmap(str(exr)))
        except RuntimeError as e:            # cut short, or damaged since
            say(f"reference: {exr} cannot be read ({str(e).strip()}): rendering it again")
        else:
            if image.shape[:2] == tuple(s.resolution[::-1]):
                say(f"reference: reusing {exr}")
                return image, recorded["noise_rel_mse"], True
            say(f"reference: {exr} is not {s.resolution[0]}x{s.resolution[1]}: rendering it "
                f"again")
    ref, _, halves = path_in_chunks(scene or _scene(s), s.reference_spp, 1_000_003 + s.seed * 10_007,
                                    CHUNK_SPP, say=say, label="reference: path", halves=True)
    noise = noise_rel_mse(halves)
    # The record goes first and comes back last: an image cut short is never vouched for.
    info.unlink(missing_ok=True)
    temporary = exr.with_name(".reference.writing.exr")
    mi.Bitmap(ref.astype(np.float32)).write(str(temporary))
    temporary.replace(exr)
    info.write_text(json.dumps({"scene": s.scene, **meta, "noise_rel_mse": noise}, indent=2)
                    + "\n")
    return ref, noise, False


def _json_or_none(path: Path):
    """The JSON in ``path``, or None where it is not JSON (cut short)."""
    try:
        return json.loads(path.read_text())
    except ValueError:
        return None


def _partpm(s: ConvergeSettings, ref, say, out: Path) -> tuple:
    scene = _scene(s, s.spp)
    desc = s._partpm_desc()
    mi.render(_scene(s, 1), integrator=mi.load_dict({**desc, "passes": 2}))   # warm-up
    rows = []
    checkpoints = {1, 2, 3, 4} | {int(round(2 ** (e / 2))) for e in range(4, 60)}

    def on_pass(info):
        if info["pass"] in checkpoints or info["last"]:
            image = _image(info["image"]())
            if info["last"]:
                _write_image(image, out / "partpm.exr")
            err = metrics.rel_mse(image, ref)
            rows.append({"method": "partpm", "seconds": info["elapsed"], "rel_mse": err,
                         "setting": f"{info['pass']} passes"})
            say(f"partpm: pass {info['pass']}, {info['elapsed']:.1f} s, relMSE {err:.5f}, "
                f"mean radius {info['mean_radius']:.4g}")
    integrator = mi.load_dict({**desc, "time_limit": s.seconds})     # passes until then
    integrator.on_pass = on_pass
    mi.render(scene, integrator=integrator, seed=s.seed)
    stopped = integrator.stats.get("stopped_by")
    return rows, None if stopped in (None, "time_limit") else stopped


def _doubling(method: str, s: ConvergeSettings, ref, say, render, start: int, unit: str,
              out: Path):
    """Renders at ``start``, 2 ``start``, ... until one takes longer than ``seconds``; the
    last image is written to ``out/<method>.exr``. Returns the rows and why the curve
    ended before ``seconds`` ("memory") or None."""
    render(max(1, start // 4))                    # warm-up
    rows, amount, img, stopped = [], start, None, None
    while True:
        try:
            img, seconds = render(amount)
        except RuntimeError as e:
            if "MemoryGuardError" not in repr(e.__cause__) and "needs about" not in str(e):
                raise
            say(f"{method}: {amount} {unit} do not fit in memory; the curve stops here")
            stopped = "memory"
            break
        err = metrics.rel_mse(img, ref)
        rows.append({"method": method, "seconds": seconds, "rel_mse": err,
                     "setting": f"{amount} {unit}"})
        say(f"{method}: {amount} {unit}, {seconds:.1f} s, relMSE {err:.5f}")
        if seconds > s.seconds:
            break
        amount *= 2
    if rows:                      # (img: the last render that ran)
        _write_image(img, out / f"{method}.exr")
    return rows, stopped


def _write_image(image, path: Path):
    mi.Bitmap(np.asarray(image, dtype=np.float32)).write(str(path))


#: Most samples per pixel of one ``path`` render; more are rendered in chunks of this many
#: (one wavefront of 160 x 160 x 16384 samples needs about 10 GB).
PATH_CHUNK_SPP = 1024


def _path(s: ConvergeSettings, ref, say, out: Path) -> tuple:
    scene = _scene(s)
    integrator = mi.load_dict({"type": "path"})

    rendered = []

    def render(spp):
        rendered.append(spp)
        return path_in_chunks(scene, spp, s.seed, PATH_CHUNK_SPP, integrator)
    rows, stopped = _doubling("path", s, ref, say, render, 1, "spp", out)
    most = max(rendered, default=0)
    if 4 * most > s.reference_spp:
        # The error of path at n spp against a reference of R spp is its own noise plus the
        # reference's, which is n / R of it: over a quarter, the curve measures the reference.
        log.warning("path reached %d spp, more than a quarter of the reference's %d spp: its "
                    "last points measure the reference's own noise too; raise "
                    "--reference-spp (or lower --time)", most, s.reference_spp)
    return rows, stopped


#: Photons of pm's first render (more when k asks for it); each next render doubles them.
PM_START = 10_000


def _pm(s: ConvergeSettings, ref, say, out: Path) -> tuple:
    scene = _scene(s, s.spp)

    def render(photons):
        integrator = mi.load_dict(s._pm_desc(photons))
        img, seconds = timed(lambda: mi.render(scene, integrator=integrator, seed=s.seed))
        return _image(img), seconds
    # From 10,000 photons, or 4 k: the warm-up's quarter of it holds k photons.
    return _doubling("pm", s, ref, say, render, max(PM_START, 4 * s.k), "photons", out)


def run_converge(settings: ConvergeSettings, out_dir, progress=print) -> dict:
    """Run every method of ``settings``; write the CSV, JSON and plot into ``out_dir``."""
    settings.check()
    s, say = settings, progress or (lambda *a: None)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    scene = _scene(s)
    s.check_scene(scene)
    misses = caustics_path_misses(scene)
    if misses:
        log.warning("%s", misses)
    ref, noise, reused = path_reference(s, out, say, scene)
    if noise is not None:
        say(f"reference: its own noise, relMSE about {noise:.3g} against the truth (from its "
            f"two halves): errors near it measure the reference")
    runners = {"partpm": _partpm, "pm": _pm, "path": _path}
    rows, stopped = [], {}
    for method in s.methods:
        rows_of, stopped[method] = runners[method](s, ref, say, out)
        rows += rows_of
    ends = {m: _last_time(rows, m) for m in s.methods
            if _last_time(rows, m) is not None and _last_time(rows, m) < s.seconds}
    result = {"settings": {**asdict(s), "resolution": list(s.resolution),
                           "methods": list(s.methods)},
              "code": code_version(), "rows": rows, "reference_rel_mse": noise,
              "reference_reused": reused,
              # (a method writes its last image when it has a row)
              "images": [f"{m}.exr" for m in s.methods if any(r["method"] == m for r in rows)],
              "at": {str(t): {m: _error_at(rows, m, t) for m in s.methods}
                     for t in sorted({5.0, s.seconds}) if t <= s.seconds},
              "ends": ends,
              "ended_by": {m: stopped[m] for m in ends if stopped[m]},
              "reference_misses": misses}
    with open(out / "converge.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=["method", "seconds", "rel_mse", "setting"])
        writer.writeheader()
        writer.writerows(rows)
    (out / "converge.json").write_text(json.dumps(result, indent=2) + "\n")
    _plot(rows, out / "converge.png", s, noise)
    return result


def ended_text(result: dict, method: str) -> str:
    """Why ``method``'s curve in ``result`` ended before the time limit, in words."""
    if "ended_by" not in result:         # (a run that recorded memory as the only reason)
        return ENDED_BY["memory"]
    why = result["ended_by"].get(method)
    return ENDED_BY.get(why, f"it stopped ({why})") if why else "it stopped early"


def _last_time(rows, method: str):
    """The seconds of ``method``'s last run (None without one)."""
    return max((r["seconds"] for r in rows if r["method"] == method), default=None)


def _error_at(rows, method: str, seconds: float):
    """The error of ``method`` at ``seconds``: log-log interpolation between its runs (None
    before its first run and after its last: a curve that stopped early, its next render
    not fitting in memory, says nothing of later times)."""
    pts = sorted((r["seconds"], r["rel_mse"]) for r in rows if r["method"] == method)
    if not pts or seconds < pts[0][0] or seconds > pts[-1][0]:
        return None
    t = np.log([p[0] for p in pts])
    e = np.log([p[1] for p in pts])
    return float(np.exp(np.interp(np.log(seconds), t, e)))


def _plot(rows, path, s: ConvergeSettings, noise=None):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(5.5, 4.2))
    styles = {"partpm": "o-", "pm": "s--", "path": "^-"}
    shared = settings_text(s.props)
    labels = {"partpm": f"partpm, progressive ({s.maps} maps, {s.photons:,} photons and "
                        f"{s.spp} spp per pass"
                        + "".join(f", {t}" for t in (shared, settings_text(s.partpm_props)) if t)
                        + ")",
              "pm": f"pm (k = {s.k}{', ' + shared if shared else ''}), more photons",
              "path": "Mitsuba path, more spp"}
    for method in s.methods:
        pts = sorted((r["seconds"], r["rel_mse"]) for r in rows if r["method"] == method)
        if pts:
            ax.plot(*zip(*pts), styles[method], label=labels[method], markersize=4)
    if noise:
        ax.axhline(noise, color="grey", linestyle=":", linewidth=1,
                   label="the reference's own noise (estimated)")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("wall time (s)")
    ax.set_ylabel(f"relative MSE vs path at {s.reference_spp} spp")
    ax.set_title(f"{s.scene}, {s.resolution[0]}x{s.resolution[1]}", fontsize=10)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def format_converge(result) -> str:
    """The error of every method at 5 s and at the full time, as a small table."""
    s = result["settings"]
    times = sorted({t for t in (5.0, s["seconds"]) if t <= s["seconds"]})
    lines = [f"{s['scene']} {s['resolution'][0]}x{s['resolution'][1]}: relMSE vs path at "
             f"{s['reference_spp']} spp",
             f"{'method':8} " + " ".join(f"{f'at {t:g} s':>12}" for t in times)]
    for m in s["methods"]:
        cells = []
        for t in times:
            v = _error_at(result["rows"], m, t)
            cells.append(f"{v:12.5f}" if v is not None else f"{'-':>12}")
        lines.append(f"{m:8} " + " ".join(cells))
    for m, last in result.get("ends", {}).items():
        lines.append(f"({m}'s curve ends at {last:.1f} s: {ended_text(result, m)})")
    if result.get("reference_rel_mse") is not None:
        lines.append(f"(the reference's own noise: relMSE about {result['reference_rel_mse']:.3g})")
    mappers = " and ".join(m for m in ("partpm", "pm") if m in s["methods"])
    by_who = {}                 # (partpm's own props join the shared ones where pm is not run)
    for who, props in ((mappers, s.get("props", {})), ("partpm", s.get("partpm_props", {}))):
        if props:
            by_who.setdefault(who, {}).update(props)
    given = [f"{who}: {settings_text(props)}" for who, props in by_who.items()]
    if given:
        lines.append("(" + "; ".join(given) + ")")
    if result.get("reference_misses"):
        lines.append(f"(warning: {result['reference_misses']})")
    return "\n".join(lines)
