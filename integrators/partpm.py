"""The ``partpm`` integrator: photon mapping with n partitioned photon maps (Tamura et al.)."""
from __future__ import annotations

import logging
import time

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_partpm import memory, mpi
from mi_partpm.estimate import radiance_estimate
from mi_partpm.eyepath import eye_path_radiance
from mi_partpm.photonmap import build_photon_maps, fixed_radius
from mi_partpm.photons import map_sizes, trace_photons
from mi_partpm.props import read_choice, read_int, read_photon_map_params, UNLIMITED

log = logging.getLogger("mi_partpm")


class PartPMIntegrator(mi.SamplingIntegrator):
    r"""
    .. _integrator-partpm:

    Partitioned photon mapping (:monosp:`partpm`)
    ---------------------------------------------

    Photon mapping as in "A Parallel Image Generation Algorithm based on Partitioning of
    Photon Maps" (Tamura, Takizawa, Kobayashi): ``photon_count`` photons are traced and split
    into ``map_count`` partial maps, each map is a balanced kd-tree, and the radiance at every
    eye-ray hit is the sum of the fixed-radius density estimates of all maps (eq. 2).

    .. list-table::
       :header-rows: 1

       * - Parameter
         - Type
         - Description
       * - photon_count
         - |int|
         - N, photons emitted in total over all maps, >= 1. (Default: 100000)
       * - map_count
         - |int|
         - n, the number of partial photon maps, in [1, photon_count]. Map i emits N/n photons
           (sizes differ by at most one) from its own random stream. (Default: 1)
       * - radius
         - |float|
         - Fixed search radius r in world units, > 0. (Default: unset, see radius_fraction)
       * - radius_fraction
         - |float|
         - r as a fraction of the longest side of the scene's bounding box, in (0, 1]; the
           paper uses about 1/20. Not together with radius. (Default: 0.05)
       * - max_depth
         - |int|
         - Longest path in segments, for photon paths and eye paths alike; -1 is unlimited
           (Russian roulette ends the paths). (Default: -1)
       * - rr_depth
         - |int|
         - Segment count from which Russian roulette may end a path, >= 1. (Default: 5)
       * - seed
         - |int|
         - Seed of the photon streams; map i's stream depends on (seed, i) only. (Default: 0)
       * - direct
         - |string|
         - ``photons``: the maps give all reflected light (the paper's direct visualisation);
           ``nee``: direct light by emitter sampling, the maps give indirect light only.
           (Default: photons)
       * - hide_emitters
         - |bool|
         - Emitters seen directly by the camera are black. (Default: false)
       * - backend
         - |string|
         - ``local``: all maps in this process; ``mpi``: inside ``mpiexec -n P``, rank j
           traces, builds and queries maps j, j+P, ... and one MPI reduction sums the partial
           images onto rank 0 (P <= map_count). (Default: local)

    Photons are stored on surfaces with a non-delta (diffuse or glossy) lobe; mirror and glass
    only redirect them. Eye paths follow delta lobes to the surfaces with a non-delta lobe,
    where the estimate is taken. Photons are traced and the maps built once per ``render()``
    call. Variants: the JIT RGB and mono variants (``llvm_ad_rgb``, ``cuda_ad_rgb``, ...);
    no volumes, no spectral or polarised rendering.

    .. code-block:: xml

        <integrator type="partpm">
            <integer name="photon_count" value="100000"/>
            <integer name="map_count" value="8"/>
            <float name="radius_fraction" value="0.05"/>
        </integrator>
    """

    def __init__(self, props=None):
        super().__init__(props if props is not None else mi.Properties())
        self.maps = None
        self.radius = None
        self.stats = {}
        self.comm = None
        self._rendering = False
        self.read_props(props)

    def read_props(self, props):
        """Read and check this plugin's props (subclasses read their own)."""
        self.params = read_photon_map_params(props)
        self.map_count = read_int(props, "map_count", 1, low=1, high=self.params.photon_count,
                                  allowed=f"in [1, photon_count = {self.params.photon_count}]")
        self.backend = read_choice(props, "backend", "local", ("local", "mpi"))
        if self.backend == "mpi":
            self.comm = mpi.comm_world()
            mpi.check_ranks(self.comm.size, self.map_count)
            mpi.share_cores(self.comm)

    # ------------------------------------------------------------------ phases

    def search_radius(self, scene: mi.Scene):
        """The fixed radius r of eq. (2) for ``scene``."""
        return fixed_radius(scene, self.params.radius, self.params.radius_fraction)

    def owned_maps(self):
        """The maps this process traces and queries: all, or this MPI rank's share."""
        if self.comm is None:
            return np.arange(self.map_count)
        return mpi.owned_maps(self.comm.rank, self.comm.size, self.map_count)

    def build_maps(self, scene: mi.Scene):
        """Steps 1 of figure 4: trace every (owned) map's photons and build its kd-tree."""
        p = self.params
        self.radius = self.search_radius(scene)
        owned = self.owned_maps()
        traced_here = int(map_sizes(p.photon_count, self.map_count)[owned].sum())
        film = scene.sensors()[0].film().crop_size()
        spp = scene.sensors()[0].sampler().sample_count()

        def estimate(ratio=None):
            return memory.estimate_render(traced_here, p.photon_depth, int(film[0]),
                                          int(film[1]), int(spp), ratio)
        # Before any photon is traced: the estimate from the props and the film.
        memory.check_fits(estimate(), f"photon_count = {p.photon_count}")

        def check_during(ratio, done):
            memory.check_fits(estimate(ratio), f"photon_count = {p.photon_count} (projected "
                                               f"from the first {done:,} photons traced)")

        log.info("trace: emitting %d photons into %d maps ...", p.photon_count, self.map_count)
        t0 = time.perf_counter()
        photons = trace_photons(scene, p.photon_count, self.map_count, p.seed,
                                p.photon_depth, p.rr_depth,
                                maps=None if self.comm is None else owned,
                                min_bounce=2 if p.direct == "nee" else 1,
                                progress=lambda line: log.debug("trace: %s", line),
                                memory_check=check_during)
        if self.comm is not None:
            # This rank's maps become its local maps 0 .. len(owned)-1.
            photons = photons.with_maps(np.searchsorted(owned, photons.map_id), len(owned))
        t1 = time.perf_counter()
        self.maps = build_photon_maps(photons)
        dr.eval(self.maps.direction32, self.maps.power)
        t2 = time.perf_counter()
        if len(photons) == 0:
            log.warning("no photon was stored: the scene has no surface with a non-delta "
                        "BSDF lit by its emitters; only emitted light will show")
        self.stats = {
            "photons_emitted": p.photon_count, "photons_stored": len(photons),
            "photons_traced": traced_here,
            "map_count": self.map_count, "maps_owned": owned.tolist(), "radius": self.radius,
            "map_bytes": self.maps.nbytes, "time_trace": t1 - t0, "time_build": t2 - t1,
        }
        log.info("trace: %d photons emitted, %d stored in %d maps (%.2f s)",
                 self.stats["photons_traced"], len(photons), len(owned), t1 - t0)
        log.info("build: %d kd-trees, %.1f MB (%.2f s)", len(owned),
                 self.maps.nbytes / 1e6, t2 - t1)
        return self.maps

    def render(self, scene, sensor=0, seed=0, spp=0, develop=True, evaluate=True):
        """Trace and build the maps, then render. With ``backend="mpi"`` rank 0 returns the
        gathered image and every other rank its partial image (its maps' terms of eq. 2);
        ``stats["ranks"]`` on rank 0 lists every rank's figures."""
        if self._rendering:
            # Mitsuba's base render() dispatches back here once: let it do the film work.
            return super().render(scene, sensor, seed, spp, develop, evaluate)
        if self.comm is None:
            return self._render_here(scene, sensor, seed, spp, develop, evaluate)
        with mpi.abort_on_error(self.comm):
            image = self._render_here(scene, sensor, seed, spp, develop, evaluate)
            total, wait, seconds, nbytes = mpi.reduce_image(self.comm, np.array(image))
            self.stats.update(time_wait=wait, time_reduce=seconds, reduce_bytes=nbytes,
                              rank=self.comm.rank, ranks=None)
            log.info("reduce: %d bytes to rank 0 (%.3f s, after waiting %.3f s)", nbytes,
                     seconds, wait)
            ranks = self.comm.gather(dict(self.stats), root=0)   # reporting only
            if self.comm.rank == 0:
                # Rank 0 reports the whole job; its own figures stay in ranks[0].
                self.stats.update(ranks=ranks, photons_stored=sum(r["photons_stored"]
                                                                  for r in ranks),
                                  map_bytes=sum(r["map_bytes"] for r in ranks))
                return mi.TensorXf(total)
            return image

    def _render_here(self, scene, sensor, seed, spp, develop, evaluate):
        self.build_maps(scene)
        self.before_estimate()
        t0 = time.perf_counter()
        self._rendering = True
        try:
            image = super().render(scene, sensor, seed, spp, develop, evaluate)
        finally:
            self._rendering = False
        dr.eval(image)  # also when asked not to: the estimate phase is timed here
        dr.sync_thread()
        self.stats["time_estimate"] = time.perf_counter() - t0
        self.stats["peak_memory_bytes"] = memory.peak_rss_bytes()
        log.info("estimate: %.2f s (peak memory of the process %.2f GB)",
                 self.stats["time_estimate"], self.stats["peak_memory_bytes"] / 1e9)
        self.after_estimate()
        return image

    def before_estimate(self):
        log.info("estimate: radius %.4g, rendering ...", self.radius)

    def after_estimate(self):
        """Hook for subclasses: read statistics gathered during the estimate."""

    # ------------------------------------------------------------------ per sample

    def estimate(self, si, bsdf, active):
        return radiance_estimate(self.maps, si, bsdf, self.radius, active)

    def sample(self, scene, sampler, ray, medium=None, active=True):
        if self.maps is None:
            raise RuntimeError("partpm: sample() called before the photon maps were built; "
                               "render through render() / mi.render()")
        p = self.params
        # Emission and direct light belong to one rank only; the maps' terms to every rank.
        emission = 1.0 if self.comm is None or self.comm.rank == 0 else 0.0
        L, valid = eye_path_radiance(scene, sampler, ray, self.estimate, p.max_depth,
                                     p.rr_depth, p.direct == "nee", p.hide_emitters, active,
                                     emission)
        return L, valid, []

    def aov_names(self):
        return []

    def to_string(self):
        p = self.params
        radius = f"radius = {p.radius}" if p.radius is not None \
            else f"radius_fraction = {p.radius_fraction}"
        depth = -1 if p.max_depth == UNLIMITED else p.max_depth
        return (f"PartPMIntegrator[photon_count = {p.photon_count}, map_count = "
                f"{self.map_count}, {radius}, max_depth = {depth}, rr_depth = {p.rr_depth}, "
                f"seed = {p.seed}, direct = {p.direct}, hide_emitters = {p.hide_emitters}, "
                f"backend = {self.backend}]")
