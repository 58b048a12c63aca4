"""The ``partpm`` integrator: photon mapping with n partitioned photon maps (Tamura et al.)."""
from __future__ import annotations

import logging

import mitsuba as mi

from mi_partpm.backends import BACKENDS, make_backend
from mi_partpm.estimate import radiance_estimate
from mi_partpm.integrators.common import PhotonMapper
from mi_partpm.photonmap import fixed_radius
from mi_partpm.props import read_choice, read_int

log = logging.getLogger("mi_partpm")


class PartPMIntegrator(PhotonMapper):
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
           to ``mi.render``, i) only, so renders with other seeds trace other photons and
           average towards the converged image. (Default: 0)
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
    only redirect them. Every emitter plugin of Mitsuba 3.9.1 emits photons (area, point,
    spot, directional, directionalarea, projector, constant, envmap, sunsky). The plugin works
    inside ``moment`` and ``aov`` (it then traces its maps with the ``seed`` prop alone), and
    honours ``render()``'s ``sensor``, ``seed``, ``spp``, ``develop`` and ``evaluate``. Eye paths follow delta lobes to the surfaces with a non-delta lobe,
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

    def read_estimator_props(self, props):
        n = self.params.photon_count
        self.map_count = read_int(props, "map_count", 1, low=1, high=n,
                                  allowed=f"in [1, photon_count = {n}]")
        self.backend = make_backend(read_choice(props, "backend", "local", BACKENDS),
                                    self.map_count)

    def search_radius(self, scene: mi.Scene):
        """The fixed radius r of eq. (2) for ``scene``."""
        return fixed_radius(scene, self.params.radius, self.params.radius_fraction)

    def before_estimate(self):
        log.info("estimate: radius %.4g, rendering ...", self.radius)

    def estimate(self, si, bsdf, active, max_bounce=None):
        return radiance_estimate(self.maps, si, bsdf, self.radius, active,
                                 max_bounce=max_bounce)

    def to_string(self):
        p = self.params
        radius = f"radius = {p.radius}" if p.radius is not None \
            else f"radius_fraction = {p.radius_fraction}"
        return (f"PartPMIntegrator[photon_count = {p.photon_count}, map_count = "
                f"{self.map_count}, {radius}, {self.common_props_text()}, "
                f"backend = {self.backend.name}]")
