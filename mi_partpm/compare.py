"""The paper's image comparison (figures 7-12): conventional ``pm`` vs partitioned ``partpm``.

:func:`run_compare` renders one scene three ways with the same camera and eye samples: Jensen's
k-nearest-neighbour photon mapper (one map), the partitioned fixed-radius photon mapper (n maps)
and Mitsuba's own path tracer as an independent reference. It writes the images (EXR and PNG),
signed difference heat maps, a side-by-side sheet and ``metrics.json``.

``k`` is chosen so that the kNN radius is on average close to the fixed radius r
(:func:`calibrate_k`), so the two estimators blur the same amount and the comparison is about
partitioning, not about bandwidth.
"""
from __future__ import annotations

import json
import logging
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Optional, Tuple

import drjit as dr
import mitsuba as mi
import numpy as np

from . import figures, metrics
from .kdtree import knn_query, radius_query
from .photonmap import PhotonMaps, fixed_radius
from .scenes import load_scene

__all__ = ["CompareSettings", "camera_hits", "calibrate_k", "run_compare", "format_table"]

log = logging.getLogger("mi_partpm")


@dataclass
class CompareSettings:
    """What :func:`run_compare` renders. Defaults are the paper's (section 4)."""

    scene: str = "cornell_box"
    maps: int = 8
    photons: int = 100_000
    resolution: Tuple[int, int] = (480, 480)
    spp: int = 4
    reference_spp: int = 512
    radius_fraction: float = 0.05
    k: Optional[int] = None           # None: calibrated so the mean kNN radius is close to r
    seed: int = 0
    direct: str = "photons"
    data_dir: Optional[str] = None
    extra: dict = field(default_factory=dict)   # further scene parameters

    def check(self):
        def positive_int(name, value, high=None):
            if isinstance(value, bool) or not isinstance(value, int) or value < 1 \
                    or (high is not None and value > high):
                allowed = f"in [1, {high}]" if high is not None else ">= 1"
                raise ValueError(f"{name} must be an integer {allowed}, got {value!r}")
        positive_int("photons", self.photons)
        positive_int("maps", self.maps, self.photons)
        positive_int("spp", self.spp)
        positive_int("reference_spp", self.reference_spp)
        if len(self.resolution) != 2:
            raise ValueError(f"resolution must be (width, height), got {self.resolution!r}")
        for v in self.resolution:
            positive_int("resolution", v)
        if min(self.resolution) < 7:
            raise ValueError(f"resolution must be at least 7x7 (SSIM's window), got "
                             f"{self.resolution[0]}x{self.resolution[1]}")
        if not 0 < self.radius_fraction <= 1:
            raise ValueError(f"radius_fraction must be in (0, 1], got {self.radius_fraction}")
        if self.k is not None:
            positive_int("k", self.k, self.photons)
        if self.direct not in ("photons", "nee"):
            raise ValueError(f"direct must be 'photons' or 'nee', got {self.direct!r}")


def camera_hits(scene: mi.Scene, size: int = 64, seed: int = 0) -> mi.Point3f:
    """Where the camera's rays first meet a surface with a non-delta BSDF.

    One ray through a random point of each pixel of a ``size`` x ``size`` grid over the film:
    the query points the density estimate sees most (before mirrors and glass).
    """
    sensor = scene.sensors()[0]
    rng = np.random.default_rng(seed)
    u = (np.arange(size * size) % size + rng.random(size * size)) / size
    v = (np.arange(size * size) // size + rng.random(size * size)) / size
    uv = mi.Point2f(mi.Float(u.astype(np.float32)), mi.Float(v.astype(np.float32)))
    ray, _ = sensor.sample_ray(0.0, 0.5, uv, mi.Point2f(0.5, 0.5))
    si = scene.ray_intersect(ray)
    bsdf = si.bsdf(ray)
    ok = si.is_valid() & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)
    keep = np.flatnonzero(ok.numpy())
    p = np.array(si.p)[:, keep]
    return mi.Point3f(p[0], p[1], p[2])


def calibrate_k(maps: PhotonMaps, points: mi.Point3f, radius: float, tolerance: float = 0.02,
                max_rounds: int = 6):
    """The k whose mean kNN radius over ``points`` is closest to ``radius``.

    Starts from the mean number of photons within ``radius`` and rescales k by the squared
    ratio of ``radius`` to the measured mean kNN radius (photon density ~ k / r^2) until the
    two agree within ``tolerance``. Returns ``(k, mean_knn_radius)``.
    """
    if dr.width(points) == 0 or maps.photon_count == 0:
        raise ValueError("cannot calibrate k: no camera ray meets a lit non-delta surface")
    forest = maps.forest
    _, stats = radius_query(forest, points, radius, lambda i, a: mi.Float(0.0),
                            with_stats=True)
    k = int(np.clip(round(float(dr.mean(mi.Float(stats.photons_found))[0])), 1,
                    maps.photon_count))
    tried = {}
    for _ in range(max_rounds):
        res = knn_query(forest, points, k)
        mean_r = float(np.mean(np.sqrt(res.radius2.numpy())))
        tried[k] = mean_r
        if abs(mean_r / radius - 1) < tolerance:
            break
        k_next = int(np.clip(round(k * (radius / mean_r) ** 2), 1, maps.photon_count))
        if k_next in tried:
            break
        k = k_next
    k = min(tried, key=lambda kk: abs(tried[kk] - radius))
    return k, tried[k]


def _render(scene, desc, seed):
    integrator = mi.load_dict(desc)
    t0 = time.perf_counter()
    image = mi.render(scene, integrator=integrator, seed=seed)
    dr.eval(image)
    dr.sync_thread()
    seconds = time.perf_counter() - t0
    return np.array(image, dtype=np.float64)[..., :3], integrator, seconds


def _write(out: Path, name: str, img: np.ndarray):
    mi.Bitmap(img.astype(np.float32)).write(str(out / f"{name}.exr"))
    mi.util.write_bitmap(str(out / f"{name}.png"), mi.Bitmap(img.astype(np.float32)),
                         write_async=False)


def run_compare(settings: CompareSettings, out_dir, progress=print) -> dict:
    """Render ``pm``, ``partpm`` and a ``path`` reference of one scene and compare them.

    Writes into ``out_dir``: ``pm``, ``partpm``, ``reference`` (EXR and PNG), the heat maps
    ``diff_partpm_pm.png``, ``diff_pm_reference.png``, ``diff_partpm_reference.png``, the sheet
    ``comparison.png`` and ``metrics.json``. Returns the contents of ``metrics.json``.
    """
    settings.check()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    say = progress or (lambda *a: None)
    s = settings
    scene = load_scene(s.scene, resolution=s.resolution, spp=s.spp, data_dir=s.data_dir,
                       **s.extra)
    if not scene.emitters():
        raise ValueError(f"scene {s.scene!r} has no emitter: nothing would be lit")
    radius = fixed_radius(scene, None, s.radius_fraction)
    common = {"photon_count": s.photons, "seed": s.seed, "direct": s.direct}

    pm_desc = {"type": "pm", **common, "k": s.k or 1}
    k, calibrated_r = s.k, None
    if k is None:
        say(f"[1/4] calibrating k: mean kNN radius close to r = {radius:.4g} ...")
        maps = mi.load_dict(pm_desc).build_maps(scene)
        k, calibrated_r = calibrate_k(maps, camera_hits(scene), radius)
        del maps
        say(f"      k = {k} (mean kNN radius {calibrated_r:.4g} at the camera's hits)")
    pm_desc["k"] = k

    say(f"[2/4] pm: one map, {s.photons} photons, k = {k} ...")
    img_pm, pm, t_pm = _render(scene, pm_desc, s.seed)
    say(f"[3/4] partpm: {s.maps} maps, r = {radius:.4g} ...")
    img_part, part, t_part = _render(
        scene, {"type": "partpm", **common, "map_count": s.maps,
                "radius_fraction": s.radius_fraction}, s.seed)
    say(f"[4/4] path reference: {s.reference_spp} spp ...")
    ref_scene = load_scene(s.scene, resolution=s.resolution, spp=s.reference_spp,
                           data_dir=s.data_dir, **s.extra)
    img_ref, _, t_ref = _render(ref_scene, {"type": "path", "max_depth": -1}, s.seed + 1)

    for name, img in (("pm", img_pm), ("partpm", img_part), ("reference", img_ref)):
        _write(out, name, img)
    pairs = {"partpm_vs_pm": (img_part, img_pm), "pm_vs_reference": (img_pm, img_ref),
             "partpm_vs_reference": (img_part, img_ref)}
    result = {
        "settings": {**asdict(s), "resolution": list(s.resolution), "k": k},
        "radius": radius,
        "mean_knn_radius": pm.stats.get("mean_knn_radius"),
        "calibrated_knn_radius": calibrated_r,
        "photons_stored": {"pm": pm.stats["photons_stored"],
                           "partpm": part.stats["photons_stored"]},
        "seconds": {"pm": t_pm, "partpm": t_part, "reference": t_ref,
                    "pm_estimate": pm.stats["time_estimate"],
                    "partpm_estimate": part.stats["time_estimate"]},
        "metrics": {name: metrics.compare_images(a, b) for name, (a, b) in pairs.items()},
    }
    vmax = figures.difference_range(*[figures.luminance(a) - figures.luminance(b)
                                      for a, b in pairs.values()])
    titles = {"partpm_vs_pm": "partpm - pm", "pm_vs_reference": "pm - reference",
              "partpm_vs_reference": "partpm - reference"}
    for name, (a, b) in pairs.items():
        m = result["metrics"][name]
        figures.save_heatmap(out / f"diff_{name.replace('_vs_', '_')}.png", a, b,
                             f"{titles[name]} (relMSE {m['rel_mse']:.4f}, "
                             f"SSIM {m['ssim']:.3f})", vmax)
    mp = result["metrics"]
    figures.save_comparison(
        out / "comparison.png",
        {f"conventional pm (k = {k})": img_pm,
         f"proposed partpm (n = {s.maps}, r = {radius:.3g})": img_part,
         f"path tracer, {s.reference_spp} spp": img_ref},
        {f"partpm - pm\nrelMSE {mp['partpm_vs_pm']['rel_mse']:.4f}": pairs["partpm_vs_pm"],
         f"pm - reference\nrelMSE {mp['pm_vs_reference']['rel_mse']:.4f}":
             pairs["pm_vs_reference"],
         f"partpm - reference\nrelMSE {mp['partpm_vs_reference']['rel_mse']:.4f}":
             pairs["partpm_vs_reference"]},
        vmax, suptitle=f"{s.scene}: {s.photons} photons, {s.resolution[0]}x{s.resolution[1]}, "
                       f"{s.spp} spp")
    (out / "metrics.json").write_text(json.dumps(result, indent=2) + "\n")
    return result


def format_table(result: dict) -> str:
    """The metrics of :func:`run_compare` as a small text table."""
    lines = [f"r = {result['radius']:.4g}   k = {result['settings']['k']}   "
             f"mean kNN radius = {result['mean_knn_radius']:.4g}",
             f"{'pair':22} {'RMSE':>9} {'relMSE':>9} {'MARE':>7} {'SSIM':>6} "
             f"{'mean ratio':>10} {'max 8x8 share':>13}"]
    for name, m in result["metrics"].items():
        lines.append(f"{name:22} {m['rmse']:9.5f} {m['rel_mse']:9.5f} {m['mare']:7.4f} "
                     f"{m['ssim']:6.3f} {m['mean_ratio']:10.4f} "
                     f"{m['max_block_error_share']:13.4f}")
    sec = result["seconds"]
    lines.append(f"time: pm {sec['pm']:.1f} s (estimate {sec['pm_estimate']:.1f} s), "
                 f"partpm {sec['partpm']:.1f} s (estimate {sec['partpm_estimate']:.1f} s), "
                 f"reference {sec['reference']:.1f} s")
    return "\n".join(lines)
