"""What ``partpm`` and ``pm`` share: the photon-mapping integrator base, :class:`PhotonMapper`.

A render is a fixed sequence of phases (the paper's figure 4):

1. trace: the photons of the maps this process owns (:mod:`mi_partpm.trace`);
2. build: one kd-tree per map (:mod:`mi_partpm.photonmap`);
3. estimate: eye paths to the non-delta surfaces and the density estimate there
   (:mod:`mi_partpm.eyepath`, :mod:`mi_partpm.estimate`), through Mitsuba's own film loop;
4. gather: the backend sums the processes' partial images (:mod:`mi_partpm.backends`).

A subclass says how the radiance at a hit is estimated (:meth:`PhotonMapper.estimate`), which
search radius the maps are built for (:meth:`PhotonMapper.search_radius`) and reads its own
props (:meth:`PhotonMapper.read_estimator_props`). Where the maps run is the backend object
chosen once in the constructor; the phases never ask which one it is.
"""
from __future__ import annotations

import logging

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_partpm import memory
from mi_partpm.backends import LocalBackend, alpha_channel
from mi_partpm.eyepath import eye_path_radiance
from mi_partpm.photonmap import build_photon_maps
from mi_partpm.props import UNLIMITED_DEPTH, read_photon_map_params
from mi_partpm.trace import map_sizes, stream_seed, trace_photons
from mi_partpm.timing import Stopwatch

log = logging.getLogger("mi_partpm")

__all__ = ["PhotonMapper"]


def _as_int(seed) -> int:
    """``render()``'s seed as a Python int (Mitsuba may pass a 1-wide ``UInt32``)."""
    return seed if isinstance(seed, int) else int(dr.ravel(mi.UInt32(seed))[0])


class PhotonMapper(mi.SamplingIntegrator):
    """Base of the photon-mapping integrators (see the module's text)."""

    #: Whether the plugin takes ``radius`` / ``radius_fraction`` (a fixed search radius).
    fixed_radius = True

    def __init__(self, props=None):
        super().__init__(props if props is not None else mi.Properties())
        self.maps = None
        self.radius = None
        self.stats = {}
        self._rendering = False
        self.params = read_photon_map_params(props, fixed_radius=self.fixed_radius)
        self.map_count = 1
        self.backend = LocalBackend()
        self.read_estimator_props(props)

    # ------------------------------------------------------------------ for subclasses

    def read_estimator_props(self, props):
        """Read and check the props of this estimator (may set ``map_count``, ``backend``)."""

    def search_radius(self, scene: mi.Scene):
        """The search radius the estimate uses (None: chosen per query)."""
        return None

    def estimate(self, si, bsdf, active, max_bounce=None):
        """Reflected radiance from the maps at the hits ``si`` (``bsdf`` there), from photons
        of at most ``max_bounce`` segments (None: any)."""
        raise NotImplementedError

    def before_estimate(self):
        """Called after the maps are built, before the eye pass."""

    def after_estimate(self):
        """Called after the eye pass: read statistics gathered during the estimate."""

    # ------------------------------------------------------------------ phases

    def build_maps(self, scene: mi.Scene, sensor=0, spp: int = 0, render_seed: int = 0):
        """Phases 1 and 2: trace every owned map's photons and build its kd-tree.

        ``sensor`` and ``spp`` (0: the sensor's sampler's) size the eye pass for the memory
        guard; ``render_seed`` is ``render()``'s seed, which selects the photon streams with
        the ``seed`` prop (:func:`~mi_partpm.trace.stream_seed`).
        """
        p = self.params
        self.radius = self.search_radius(scene)
        owned = self.backend.owned_maps(self.map_count)
        traced_here = int(map_sizes(p.photon_count, self.map_count)[owned].sum())
        sensor = scene.sensors()[sensor] if isinstance(sensor, int) else sensor
        film = sensor.film().crop_size()
        spp = int(spp) or sensor.sampler().sample_count()
        bounded = p.max_depth != UNLIMITED_DEPTH
        # Photon paths leave one segment at least for the eye path.
        photon_depth = p.max_depth - 1 if bounded else UNLIMITED_DEPTH

        def estimate(ratio=None):
            return memory.estimate_render(traced_here, photon_depth, int(film[0]),
                                          int(film[1]), spp, ratio)
        # Before any photon is traced: the estimate from the props and the film.
        memory.check_fits(estimate(), f"photon_count = {p.photon_count}")

        def check_during(ratio, done):
            memory.check_fits(estimate(ratio), f"photon_count = {p.photon_count} (projected "
                                               f"from the first {done:,} photons traced)")

        log.info("trace: emitting %d photons into %d maps ...", p.photon_count, self.map_count)
        clock = Stopwatch()
        photons = trace_photons(scene, p.photon_count, self.map_count,
                                stream_seed(p.seed, render_seed), photon_depth,
                                p.rr_depth, maps=owned,
                                min_bounce=2 if p.direct == "nee" else 1,
                                progress=lambda line: log.debug("trace: %s", line),
                                memory_check=check_during)
        # The owned maps become this process's maps 0 .. len(owned)-1.
        photons = photons.with_maps(np.searchsorted(owned, photons.map_id), len(owned))
        t_trace = clock.lap()
        self.maps = build_photon_maps(photons, keep_bounce=bounded)
        t_build = clock.lap(self.maps.direction32, self.maps.power)
        if len(photons) == 0:
            log.warning("no photon was stored: the scene has no surface with a non-delta "
                        "BSDF lit by its emitters; only emitted light will show")
        self.stats = {
            "photons_emitted": p.photon_count, "photons_stored": len(photons),
            "photons_traced": traced_here,
            "map_count": self.map_count, "maps_owned": owned.tolist(), "radius": self.radius,
            "render_seed": render_seed,
            "map_bytes": self.maps.nbytes, "time_trace": t_trace, "time_build": t_build,
        }
        log.info("trace: %d photons emitted, %d stored in %d maps (%.2f s)", traced_here,
                 len(photons), len(owned), t_trace)
        log.info("build: %d kd-trees, %.1f MB (%.2f s)", len(owned), self.maps.nbytes / 1e6,
                 t_build)
        return self.maps

    def render(self, scene, sensor=0, seed=0, spp=0, develop=True, evaluate=True):
        """Trace and build the maps, render, gather. With ``backend="mpi"`` rank 0 returns
        the gathered image and every other rank its partial image (its maps' terms of eq. 2);
        ``stats["ranks"]`` on rank 0 lists every rank's figures."""
        if self._rendering:
            # Mitsuba's base render() dispatches back here once: let it do the film work.
            return super().render(scene, sensor, seed, spp, develop, evaluate)
        if not develop and self.backend.name != "local":
            raise ValueError(f"develop=False is not supported with backend={self.backend.name!r}"
                             f": the ranks' images are summed once developed; render with "
                             f"develop=True")
        with self.backend.running():
            image = self._render_here(scene, sensor, _as_int(seed), spp, develop, evaluate)
            film = (scene.sensors()[sensor] if isinstance(sensor, int) else sensor).film()
            return self.backend.gather(image, self.stats, alpha_channel(film))

    def _render_here(self, scene, sensor, seed, spp, develop, evaluate):
        self.build_maps(scene, sensor, spp, seed)
        self.before_estimate()
        clock = Stopwatch()
        self._rendering = True
        try:
            image = super().render(scene, sensor, seed, spp, develop, evaluate)
        finally:
            self._rendering = False
        # Evaluated also when asked not to: the estimate phase is timed here.
        self.stats["time_estimate"] = clock.lap(image)
        self.stats["peak_memory_bytes"] = memory.peak_rss_bytes()
        log.info("estimate: %.2f s (peak memory of the process %.2f GB)",
                 self.stats["time_estimate"], self.stats["peak_memory_bytes"] / 1e9)
        self.after_estimate()
        return image

    # ------------------------------------------------------------------ per sample

    def sample(self, scene, sampler, ray, medium=None, active=True):
        if not self._rendering:
            # Called by another integrator (moment, aov), whose render() this one never saw:
            # build maps for this call, with the seed prop's photons.
            if self.backend.name != "local":
                raise ValueError(f"{type(self).__name__} with backend="
                                 f"{self.backend.name!r} must be the scene's top-level "
                                 f"integrator (its ranks gather whole images); use "
                                 f"backend='local' inside moment or aov")
            self.build_maps(scene)
            self.before_estimate()
        p = self.params
        L, valid = eye_path_radiance(scene, sampler, ray, self.estimate, p.max_depth,
                                     p.rr_depth, p.direct == "nee", p.hide_emitters, active,
                                     self.backend.emission_weight)
        return L, valid, []

    def aov_names(self):
        return []

    def common_props_text(self) -> str:
        """The shared props as ``key = value`` pairs for :meth:`to_string`."""
        p = self.params
        return (f"max_depth = {p.max_depth}, rr_depth = {p.rr_depth}, seed = {p.seed}, "
                f"direct = {p.direct}, hide_emitters = {p.hide_emitters}")
