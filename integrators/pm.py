"""The ``pm`` integrator: conventional photon mapping with one map and k nearest neighbours."""
from __future__ import annotations

import logging

import drjit as dr
import mitsuba as mi

from mi_partpm.estimate import knn_flux
from mi_partpm.kdtree.knn import MAX_K
from mi_partpm.eyepath import estimated_lobes
from mi_partpm.integrators.common import PhotonMapper, Term
from mi_partpm.progressive import RadianceSum, accumulate
from mi_partpm.kdtree.radius import MIN_RADIUS
from mi_partpm.props import (MAX_RADIUS, PARTPM_ONLY, read_bool, read_float, read_int,
                             refuse_props)

log = logging.getLogger("mi_partpm")



class PMIntegrator(PhotonMapper):
    r"""
    .. _integrator-pm:

    Conventional photon mapping (:monosp:`pm`)
    ------------------------------------------

    Jensen's photon mapping, the baseline the paper compares against: all ``photon_count``
    photons in one balanced kd-tree, and the radiance at every eye-ray hit estimated from its
    ``k`` nearest photons, with r the distance to the k-th (eq. 1). Photon tracing, kd-tree
    and eye paths are those of ``partpm`` (both are :class:`~mi_partpm.integrators.common.
    PhotonMapper` s); it takes the same props (``max_depth``, ``rr_depth``, ``seed``,
    ``direct``, ``hide_emitters``, ``kernel``, ``glossy``, ``glossy_samples``,
    ``samples_per_pass``) except those
    of partitioned, progressive or caustic maps (``map_count``, ``radius``,
    ``radius_fraction``, ``backend``, ``passes``, ``alpha``, ``time_limit``,
    ``caustic_*``, ``final_gather``: one map, one pass, in this process), and adds:

    .. list-table::
       :header-rows: 1

       * - Parameter
         - Type
         - Description
       * - k
         - |int|
         - Photons per estimate, in [2, photon_count], at most 16383. (Default: 50)
       * - count_kth
         - |boolean|
         - Count the k-th photon, which lies on the circle of radius r, as eq. (1) and
           Jensen do: the box kernel's estimate is then k / (k - 1) too bright on average
           (2% at k = 50). False leaves it out and removes that bias (the other kernels
           weigh it 0 either way). (Default: true)
       * - max_radius
         - |float|
         - Only photons within this distance are searched, in [1e-15, 1e18]; where fewer than k lie
           within it, r = max_radius (Jensen's cap). (Default: unset, no cap)

    After a render, ``stats["mean_knn_radius"]`` is the mean r over all estimates, and
    ``stats["capped_share"]`` the share of estimates that found fewer than k photons.

    .. code-block:: xml

        <integrator type="pm">
            <integer name="photon_count" value="100000"/>
            <integer name="k" value="50"/>
        </integrator>
    """

    fixed_radius = False
    progressive = False

    def read_estimator_props(self, props):
        refuse_props(props, PARTPM_ONLY, "partpm", "pm is the single-pass k-nearest-neighbour "
                     "photon mapper of one map (its radius is the k-th photon's; max_radius "
                     "caps it)")
        n = self.params.photon_count
        # k = 1: pi r^2 then holds no photon on average, and the estimate's mean is unbounded.
        self.k = read_int(props, "k", 50, low=2, high=min(n, MAX_K),
                          allowed=f"in [2, photon_count = {n}]" if n <= MAX_K else
                          f"in [2, {MAX_K}] (the most the kNN query keeps)")
        self.count_kth = read_bool(props, "count_kth", True)
        has_cap = props is not None and "max_radius" in props
        self.max_radius = read_float(props, "max_radius", None, low=MIN_RADIUS, high=MAX_RADIUS,
                                     low_open=False) \
            if has_cap else None
        self._acc = None

    def search_radius(self, scene):
        return self.max_radius

    def before_estimate(self):
        cap = "none" if self.max_radius is None else f"{self.max_radius:.4g}"
        log.info("estimate: k = %d nearest photons, max_radius %s, rendering ...", self.k, cap)
        stored = int(self.stats.get("photons_stored", 0))
        if self.max_radius is None and 0 < stored <= self.k:     # (a cap bounds the blur)
            log.warning("only %d photons were stored, no more than k = %d: every estimate "
                        "gathers the whole map, a blur of the whole scene (lower k or raise "
                        "photon_count)", stored, self.k)
        # Sum of r, number of estimates, number that found fewer than k (filled by
        # estimate_points(); host sums: float32 atomics put a mean of capped radii above
        # the cap, and stop counting at 2^24 estimates).
        self._acc = [0.0, 0, 0]

    def after_estimate(self):
        acc = self._acc
        count = max(float(acc[1]), 1.0)
        self.stats.update(k=self.k, max_radius=self.max_radius,
                          mean_knn_radius=float(acc[0]) / count,
                          capped_share=float(acc[2]) / count, estimates=int(acc[1]))
        log.info("estimate: mean kNN radius %.4g over %d estimates (%.1f%% with fewer than "
                 "k photons)", self.stats["mean_knn_radius"], int(acc[1]),
                 100 * self.stats["capped_share"])

    def terms(self, layers, width: int, scene) -> list:
        global_maps = layers[0]
        return [Term("global", RadianceSum.start(width),
                     lambda points, w: accumulate(points, *self.estimate_points(
                         global_maps.maps, points), w))]

    def estimate_points(self, maps, points):
        """Each visible point's radiance from its k nearest photons (already normalised by
        its own kNN radius), and the photons found."""
        if not len(points):
            return dr.zeros(mi.Spectrum, 0), dr.zeros(mi.UInt32, 0)
        est = knn_flux(maps, points.si, points.bsdf, self.k, self.max_radius,
                       max_bounce=points.max_bounce, kernel=self.params.kernel,
                       lobes=estimated_lobes(self.params.glossy), count_kth=self.count_kth)
        # An empty map finds nothing at radius 0 (no cap): not an estimate of any radius.
        counted = dr.isfinite(est.radius2) & ((est.found > 0) | (est.radius2 > 0))
        r = dr.select(counted, dr.sqrt(est.radius2), 0.0)
        self._acc[0] += float(dr.sum(mi.Float64(r))[0])
        self._acc[1] += int(dr.count(counted)[0])
        self._acc[2] += int(dr.count(counted & (est.found < self.k))[0])
        return est.radiance(), est.found

    def to_string(self):
        return (f"PMIntegrator[photon_count = {self.params.photon_count}, k = {self.k}, "
                f"max_radius = {self.max_radius}, count_kth = {self.count_kth}, "
                f"{self.common_props_text()}]")
