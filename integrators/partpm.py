"""The ``partpm`` integrator: photon mapping with n partitioned photon maps (Tamura et al.)."""
from __future__ import annotations

import logging

import drjit as dr
import mitsuba as mi

from mi_partpm.backends import BACKENDS, make_backend
from mi_partpm.estimate import gather_flux
from mi_partpm.eyepath import estimated_lobes
from mi_partpm.gather import final_gather
from mi_partpm.kdtree import MAX_MAPS
from mi_partpm.kdtree.radius import MIN_RADIUS, below_min_radius
from mi_partpm.integrators.common import UNTIL_TIME_LIMIT, Layer, PhotonMapper, Term
from mi_partpm.photonmap import fixed_radius
from mi_partpm.progressive import (RadianceSum, SPPMState, accumulate, check_first_pass,
                                   check_schedule, radius_schedule)
from mi_partpm.trace import stream_seed
from mi_partpm.props import (MAX_RADIUS, PROGRESSIVE_RADIUS_FRACTION, RADIUS_FRACTION,
                             MAX_RAYS_PER_POINT, PM_ONLY, UNLIMITED_DEPTH, check_choice,
                             read_choice, read_float, read_int, refuse_props)

log = logging.getLogger("mi_partpm")

#: Keeps the caustic maps' photon streams apart from the global maps'.
CAUSTIC_SALT = 0x5CA7_1C00


def _read_radius_pair(props, radius_name: str, fraction_name: str):
    """(radius, fraction) of two props that exclude each other; None where not given."""
    has_radius = props is not None and radius_name in props
    has_fraction = props is not None and fraction_name in props
    if has_radius and has_fraction:
        raise ValueError(f"give either {radius_name} or {fraction_name}, not both")
    radius = read_float(props, radius_name, None, low=MIN_RADIUS, high=MAX_RADIUS,
                        low_open=False) if has_radius else None
    fraction = read_float(props, fraction_name, None, low=0.0, high=1.0) \
        if has_fraction else None
    return radius, fraction


class PartPMIntegrator(PhotonMapper):
    r"""
    .. _integrator-partpm:

    Partitioned photon mapping (:monosp:`partpm`)
    ---------------------------------------------

    Photon mapping as in "A Parallel Image Generation Algorithm based on Partitioning of
    Photon Maps" (Tamura, Takizawa, Kobayashi): ``photon_count`` photons are traced and split
    into ``map_count`` partial maps, each map is a balanced kd-tree, and the radiance at every
    eye path's visible point is the sum of the fixed-radius density estimates of all maps
    (eq. 2). With ``passes`` > 1 the render is progressive (stochastic progressive photon
    mapping, Hachisuka and Jensen 2009): every pass traces new photons and new eye paths, and
    each eye path's radius shrinks pass after pass, the same in every map, so the image
    converges.

    .. list-table::
       :header-rows: 1

       * - Parameter
         - Type
         - Description
       * - photon_count
         - |int|
         - N, photons emitted per pass in total over all maps, >= 1. (Default: 100000)
       * - map_count
         - |int|
         - n, the number of partial photon maps, in [1, min(photon_count, 2^20)]. Map i emits
           N/n photons (sizes differ by at most one) from its own random stream. (Default: 1)
       * - radius
         - |float|
         - Fixed (initial) search radius r in world units, in [1e-15, 1e18] (squared
           distances must be resolved in float32). (Default: unset, see radius_fraction)
       * - radius_fraction
         - |float|
         - r as a fraction of the longest side of the scene's bounding box, in (0, 1]; the
           paper uses about 1/20. Not together with radius. (Default: 0.05 with one pass;
           0.025 with passes > 1, since the radius then only shrinks)
       * - passes
         - |int|
         - Passes, >= 1; 1 is the paper's single pass. (Default: 1, or passes until
           ``time_limit`` when only that is given)
       * - alpha
         - |float|
         - Fraction of a pass's new photons kept by the radius reduction, in (0, 1):
           r^2 shrinks by (N + alpha M) / (N + M); a final gather's radius follows the
           schedule of a constant M. Only for a progressive render (refused with
           passes = 1). (Default: 0.7)
       * - time_limit
         - |float|
         - Seconds, >= 0: stop after the pass during which this much time has passed and
           return the image so far; 0 is no limit. Without ``passes``, the render runs
           passes until then. (Default: 0)
       * - max_depth
         - |int|
         - Longest light path, in segments from the emitter to the camera, as for Mitsuba's
           ``path``: 1 shows only emitters seen directly, 2 direct light, and so on; -1 is
           unlimited (Russian roulette ends the paths). An estimate at the end of an eye
           path of e segments uses only photons of at most max_depth - e. (Default: -1)
       * - rr_depth
         - |int|
         - Segment count from which Russian roulette may end a path, >= 1. (Default: 5)
       * - seed
         - |int|
         - Base seed of the photon streams: map i's stream depends on (seed, the seed given
           to ``mi.render``, the pass, i) only, so renders with other seeds trace other
           photons and average towards the converged image. (Default: 0)
       * - direct
         - |string|
         - ``photons``: the maps give all reflected light (the paper's direct visualisation);
           ``nee``: direct light by an emitter sample and a BSDF sample, weighted by
           multiple importance sampling as in Mitsuba's ``path``; the maps give indirect
           light only.
           (Default: photons)
       * - hide_emitters
         - |bool|
         - Emitters seen directly by the camera are a miss: black, alpha 0, as for path.
           (Default: false)
       * - kernel
         - |string|
         - Density kernel over the search disc: ``box`` (the paper's eq. 2), ``simpson``
           (3 (1 - d^2/r^2)^2, Mitsuba 0.6's), ``epanechnikov`` (2 (1 - d^2/r^2)) or ``cone``
           (3 (1 - d/r)); each integrates to pi r^2, so a uniform photon density gives the
           same radiance with every kernel, and eq. (2) holds for each. (Default: box)
       * - caustic_photon_count
         - |int|
         - Photons per pass for a caustic map, 0 (off) or >= map_count: they are traced
           apart, and only those that reach their first non-delta surface through one or
           more mirror or glass bounces (L S+ D) are stored, in their own map_count
           partitioned maps, read with their own radius; the global maps then keep every
           other photon, so nothing is counted twice. With glossy = trace, glossy bounces
           count like mirror and glass ones, up to the first surface with a diffuse lobe
           (L {S|G}+ D: the caustic under a rough glass sphere). (Default: 0)
       * - caustic_radius, caustic_radius_fraction
         - |float|
         - The caustic maps' (initial) radius in world units, in [1e-15, 1e18], or as a
           fraction of the scene's longest side, in (0, 1]; one of the two. (Default: a
           quarter of the global radius)
       * - glossy
         - |string|
         - ``map``: every surface with a non-delta lobe takes its estimate from the maps;
           ``trace``: at a surface whose lobes are all glossy or delta, the eye path goes on
           by BSDF sampling (direct light there by emitter sampling, MIS-weighted as in
           ``path``) and the estimate is taken at the next surface with a diffuse lobe.
           (Default: map)
       * - glossy_samples
         - |int|
         - With glossy = trace, the rays traced from an eye path's first glossy surface,
           >= 1. (Default: 1)
       * - final_gather
         - |int|
         - Rays of a final gather at every visible point, in [0, 4096]; 0 is off. With n > 0
           (needs direct = nee) the global maps are read only where those BSDF-sampled rays land,
           caustics come from the caustic maps (or, without them, from the gather rays that
           reach an emitter through mirrors and glass): Jensen's two-pass method. With glossy
           = trace and a caustic map, the gather rays go on through glossy surfaces too and
           read the maps at the next surface with a diffuse lobe, the glossy caustics coming
           from the caustic map; without one they read the maps on the glossy surface, which
           keeps the glossy caustics of point and spot lights that no ray can hit.
           (Default: 0)
       * - maps_per_wave
         - |int|
         - Maps traced, built and queried at once, in [0, map_count]: the maps of a pass run
           in waves, each wave's maps freed before the next are traced, which bounds the
           memory of large photon counts; eq. (2) makes the image the same. 0: as many as
           fit the memory budget (at most 1.5 GiB of maps per wave, and what is free). (Default: 0)
       * - samples_per_pass
         - |int|
         - As for Mitsuba's ``path``: a render of one pass traces its eye samples in sets of
           this many per pixel (spp a multiple of it), each set estimated against the same
           maps and added to the film, so that its eye pass holds one set at a time; unused
           with passes > 1. Unset: all at once, or in the fewest sets that fit beside the
           maps where they would not. (Default: unset)
       * - backend
         - |string|
         - ``local``: all maps in this process; ``mpi``: inside ``mpiexec -n P``, rank j
           traces, builds and queries maps j, j+P, ... and one MPI reduction per pass sums
           the eye paths' flux and photon counts (P <= map_count). (Default: local)

    Photons are stored on surfaces with a non-delta (diffuse or glossy) lobe; mirror and glass
    only redirect them. Eye paths follow delta lobes to the surfaces with a non-delta lobe,
    where the estimate is taken. Every emitter plugin of Mitsuba 3.9.1 emits photons (area,
    point, spot, directional, directionalarea, projector, constant, envmap, sunsky). The plugin
    works inside ``moment`` and ``aov`` (its ``sample()`` traces its maps with the ``seed`` prop
    and the seed of its last ``render()`` of the scene, which ``aov`` calls first, and refines
    the estimate at the wrapper's rays pass after pass), and honours
    ``render()``'s ``sensor``, ``seed``, ``spp``, ``develop`` and ``evaluate``. After a render,
    ``stats`` holds the photons stored, the map bytes and the time of every phase. Variants:
    the JIT RGB and mono variants (``llvm_ad_rgb``, ``cuda_ad_rgb``, ...); no volumes, no
    spectral or polarised rendering.

    .. code-block:: xml

        <integrator type="partpm">
            <integer name="photon_count" value="100000"/>
            <integer name="map_count" value="8"/>
            <float name="radius_fraction" value="0.05"/>
            <integer name="passes" value="64"/>
        </integrator>
    """

    def read_estimator_props(self, props):
        refuse_props(props, PM_ONLY, "pm", "partpm searches every eye path's photons within "
                     "a radius (radius or radius_fraction), not its k nearest")
        n = self.params.photon_count
        high = min(n, MAX_MAPS)
        self.map_count = read_int(props, "map_count", 1, low=1, high=high,
                                  allowed=f"in [1, photon_count = {n}]" if high == n else
                                  f"in [1, {MAX_MAPS}] (the most maps a forest holds)")
        self.time_limit = read_float(props, "time_limit", 0.0, low=0.0, low_open=False)
        # Without ``passes``, a time limit means passes until it is reached.
        self.passes = read_int(props, "passes", 1, low=1) \
            if (props is not None and "passes" in props) or not self.time_limit \
            else UNTIL_TIME_LIMIT
        self.alpha = read_float(props, "alpha", 0.7, low=0.0, high=1.0, high_open=True)
        if self.time_limit and self.passes == 1:
            raise ValueError(f"time_limit = {self.time_limit:g} stops a progressive render "
                             f"between passes: with passes = 1 the one pass runs whole (give "
                             f"passes > 1, or time_limit without passes for passes until it)")
        if props is not None and "alpha" in props and self.passes == 1:
            raise ValueError(f"alpha = {self.alpha:g} sets how fast a progressive render's "
                             f"radius shrinks between passes: it needs passes > 1, or a "
                             f"time_limit without passes (passes until it); with passes = 1 "
                             f"it would change nothing")
        self.caustic_photon_count = read_int(props, "caustic_photon_count", 0, low=0)
        self.caustic_radius, self.caustic_radius_fraction = _read_radius_pair(
            props, "caustic_radius", "caustic_radius_fraction")
        self.final_gather = read_int(props, "final_gather", 0, low=0, high=MAX_RAYS_PER_POINT)
        self.caustic_search_radius = None        # (search_radius finds it for a scene)
        if self.final_gather and self.params.direct != "nee":
            raise ValueError(f"final_gather = {self.final_gather} needs direct = 'nee': "
                             f"direct light at the first hit is sampled, and the global map "
                             f"is read only where the gather rays land")
        if not self.caustic_photon_count and (self.caustic_radius is not None or
                                              self.caustic_radius_fraction is not None):
            raise ValueError("caustic_radius and caustic_radius_fraction are the caustic maps' "
                             "radius: they need caustic maps (caustic_photon_count > 0)")
        if self.caustic_photon_count and self.caustic_photon_count < self.map_count:
            raise ValueError(f"caustic_photon_count must be 0 (off) or in [map_count = "
                             f"{self.map_count}, ...), got {self.caustic_photon_count}")
        self.maps_per_wave = read_int(props, "maps_per_wave", 0, low=0, high=self.map_count,
                                      allowed=f"in [0 (as many as fit), map_count = "
                                              f"{self.map_count}]")
        self.backend = make_backend(read_choice(props, "backend", "local", BACKENDS),
                                    self.map_count)

    def run_on(self, backend: str):
        """Run the maps on ``backend`` (one of the ``backend`` prop's values) from now on:
        the command line's ``--backend`` given with a scene file's own partpm."""
        self.backend = make_backend(check_choice("backend", backend, BACKENDS),
                                    self.map_count)

    def search_radius(self, scene: mi.Scene):
        """The fixed radius r of eq. (2) for ``scene``. The caustic maps' radius is found
        here too (``caustic_search_radius``), and both are checked against what the passes
        make of them, so a radius that cannot render is refused before any photon is
        traced."""
        r = fixed_radius(scene, self.params.radius, self.radius_fraction)
        if self.passes > 1:
            check_first_pass(r, self.alpha)
            if self.final_gather and self.passes < UNTIL_TIME_LIMIT:
                check_schedule(r, self.alpha, self.passes)
        self.caustic_search_radius = self._caustic_radius(scene) \
            if self.caustic_photon_count else None
        return r

    def _caustic_radius(self, scene: mi.Scene) -> float:
        """The caustic maps' radius: ``caustic_radius``, a fraction of the scene, or a quarter
        of the global maps' radius (the radius given, or a quarter of its fraction)."""
        if self.caustic_radius is None and self.caustic_radius_fraction is None and \
                self.params.radius is not None:
            r = self.params.radius / 4          # a quarter of the global radius given
        elif self.caustic_radius_fraction is not None:
            r = fixed_radius(scene, self.caustic_radius, self.caustic_radius_fraction,
                             ("caustic_radius", "caustic_radius_fraction"))
        else:
            r = fixed_radius(scene, self.caustic_radius, self.radius_fraction / 4,
                             ("caustic_radius", "radius_fraction"),
                             f"a quarter of radius_fraction = {self.radius_fraction:g}")
        if r < MIN_RADIUS:
            raise ValueError(f"the caustic maps' radius, a quarter of radius = "
                             f"{self.params.radius:g}, is {r:.3g}: {below_min_radius()} "
                             f"(give caustic_radius)")
        if self.passes > 1:
            check_first_pass(r, self.alpha, "caustic maps' radius", "caustic_radius")
        return r

    @property
    def radius_fraction(self) -> float:
        """The prop, or its default: 1/20 for one pass, 1/40 for a progressive render."""
        if self.params.radius_fraction is not None:
            return self.params.radius_fraction
        return RADIUS_FRACTION if self.passes == 1 else PROGRESSIVE_RADIUS_FRACTION

    def before_estimate(self):
        log.info("estimate: radius %.4g, %s ...", self.radius, self._passes_text())

    def layers(self) -> list:
        """The global maps, and the caustic maps when ``caustic_photon_count`` > 0. The global
        maps then keep every other photon, so none is counted twice at a visible point; with
        a final gather they keep all photons, since they are read only one bounce away, where
        caustic light is light like any other (Jensen)."""
        caustic = self.caustic_photon_count > 0
        paths = "global" if caustic and not self.final_gather else "all"
        layers = [Layer("global", self.params.photon_count, paths)]
        if caustic:
            layers.append(Layer("caustic", self.caustic_photon_count, "caustic",
                                salt=CAUSTIC_SALT))
        return layers

    def min_bounce(self) -> int:
        # A final gather reads the global map where its rays land: direct light there too.
        return 1 if self.final_gather else super().min_bounce()

    def _eye_kept(self) -> bool:
        # The gather keeps every eye path's visible point while its rays are traced.
        return bool(self.final_gather) or super()._eye_kept()

    def _photon_depth(self, layer=None) -> int:
        # A final gather reads the global maps one segment past the eye path: their photons
        # are a segment shorter (at max_depth 2 they would all be traced for nothing).
        depth = super()._photon_depth(layer)
        if self.final_gather and layer is not None and layer.name == "global" and \
                depth != UNLIMITED_DEPTH:
            return max(depth - 1, 0)       # (not -1 at max_depth 1: that is "unlimited")
        return depth

    def _eye_segments(self) -> str:
        return "the camera's and the final gather's take them" if self.final_gather else \
            super()._eye_segments()

    def terms(self, layers, width: int, scene) -> list:
        """Per eye path: the global maps' estimate at its visible points (or, with a final
        gather, at the gather rays' hits), and the caustic maps' with their own radius."""
        terms = []
        by_name = {layer.name: layer for layer in layers}
        if self.final_gather:
            state = RadianceSum.start(width)
            terms.append(Term("global", state, lambda points, w: self._gather(
                scene, by_name["global"].maps, points, w, state.passes)))
        else:
            terms.append(self._points_term("global", by_name["global"], width, self.radius))
        if "caustic" in by_name:
            r = self.caustic_search_radius      # (found with the radius, before any work)
            if r is None:                        # (terms called without a render)
                r = self.caustic_search_radius = self._caustic_radius(scene)
            self.stats["caustic_radius"] = r
            terms.append(self._points_term("caustic", by_name["caustic"], width, r))
        return terms

    def none_found_text(self, term: str) -> tuple:
        if term == "global" and self.final_gather:
            return ("final gather ray's hit", "the gather rays met no surface that stores "
                    "photons within max_depth (they left the scene, or went through glass "
                    "only), or the search is far smaller than the photons' spacing")
        return super().none_found_text(term)

    def scheduled_radius(self, passes_done: int):
        """A progressive final gather's radius in the pass after ``passes_done``."""
        if self.final_gather and self.passes > 1 and passes_done:
            return radius_schedule(self.radius, self.alpha, passes_done)
        return None

    def cannot_run_pass(self, pass_index: int):
        """A final gather's radius follows a schedule: with passes until a time limit, a
        small ``alpha`` can take it below the least radius before the limit (a given number
        of passes is checked before the first, in :meth:`search_radius`)."""
        if not (self.final_gather and pass_index):
            return None
        radius = radius_schedule(self.radius, self.alpha, pass_index)
        if radius >= MIN_RADIUS:
            return None
        return (f"alpha = {self.alpha:g} would shrink the final gather's radius "
                f"{self.radius:g} to {radius:.3g} in pass {pass_index + 1}, "
                f"{below_min_radius()}")

    def _points_term(self, name: str, layer, width: int, radius) -> Term:
        state = SPPMState.start(width, radius, self.alpha)

        def compute(points, w):
            values, found = self.estimate_points(layer.maps, points, state)
            return accumulate(points, values, found, w)
        return Term(name, state, compute)

    def estimate_points(self, maps, points, state: SPPMState):
        """Each visible point's flux and photon count within its eye path's radius."""
        if not len(points):
            return dr.zeros(mi.Spectrum, 0), dr.zeros(mi.UInt32, 0)
        radius = dr.gather(mi.Float, state.radius, points.lane)
        est = gather_flux(maps, points.si, points.bsdf, radius, max_bounce=points.max_bounce,
                          kernel=self.params.kernel, lobes=estimated_lobes(self.params.glossy))
        return est.flux, est.found

    def _gather(self, scene, maps, points, width: int, pass_index: int):
        """The final gather's radiance per eye path this pass (the radius follows the SPPM
        schedule of a constant photon density: :func:`~mi_partpm.progressive.
        radius_schedule`)."""
        radius = radius_schedule(self.radius, self.alpha, pass_index)
        if pass_index and radius < MIN_RADIUS:     # passes until a time limit
            check_schedule(self.radius, self.alpha, pass_index + 1)
        p = self.params
        return final_gather(scene, maps, points, width, self.final_gather, radius,
                            # (the eye rays' own stream: another per render seed, pass and
                            # set of eye samples, or the sets would share their gather rays)
                            seed=stream_seed(self._pass_seed, 0, pass_index),
                            max_depth=p.max_depth,
                            kernel=p.kernel,
                            caustics=self.caustic_photon_count == 0 and self.wave_index == 0
                            and self.backend.is_root,
                            lobes=estimated_lobes(p.glossy),
                            glossy=p.glossy == "trace" and self.caustic_photon_count > 0)

    def store_on(self) -> str:
        """A final gather without caustic maps stops its rays at glossy surfaces and reads
        the maps there (:meth:`_gather`): photons are stored there too."""
        if self.final_gather and not self.caustic_photon_count:
            return "smooth"
        return super().store_on()

    def caustic_past_landings(self) -> bool:
        return self.final_gather > 0

    def _passes_text(self) -> str:
        """The passes a render runs, in words: "1 pass", "64 passes", "passes until 30 s"."""
        if self.passes == UNTIL_TIME_LIMIT:
            return f"passes until {self.time_limit:g} s"
        limit = f" (at most {self.time_limit:g} s)" if self.time_limit > 0 else ""
        return f"{self.passes} pass{'' if self.passes == 1 else 'es'}{limit}"

    def to_string(self):
        p = self.params
        radius = f"radius = {p.radius}" if p.radius is not None \
            else f"radius_fraction = {self.radius_fraction}"
        passes = "until time_limit" if self.passes == UNTIL_TIME_LIMIT else self.passes
        # The caustic maps' radius, when they are on (search_radius derives the same).
        if self.caustic_photon_count == 0:
            caustic = ""
        elif self.caustic_radius is not None:
            caustic = f", caustic_radius = {self.caustic_radius}"
        elif self.caustic_radius_fraction is not None:
            caustic = f", caustic_radius_fraction = {self.caustic_radius_fraction}"
        elif p.radius is not None:      # a quarter of the global radius, as the render uses
            caustic = f", caustic_radius = {p.radius / 4:g}"
        else:
            caustic = f", caustic_radius_fraction = {self.radius_fraction / 4:g}"
        return (f"PartPMIntegrator[photon_count = {p.photon_count}, map_count = "
                f"{self.map_count}, {radius}, passes = {passes}, alpha = {self.alpha}, "
                f"time_limit = {self.time_limit}, caustic_photon_count = "
                f"{self.caustic_photon_count}{caustic}, final_gather = {self.final_gather}, "
                f"maps_per_wave = {self.maps_per_wave}, "
                f"{self.common_props_text()}, backend = {self.backend.name}]")
