"""Density estimation: reflected radiance at a surface point from partitioned photon maps.

Eq. (1) of the paper is the conventional estimate over the k nearest photons (``pm``);
eq. (2): with the same fixed radius r for every map,

    L_r(x, w) ~= 1/(pi r^2) * sum over maps i, sum over photons p of map i within r of x
                  of f_r(x, w_p, w) * dPhi_p

so the gathered estimate is the sum of the per-map estimates. A photon counts only if it
arrived on the side of the surface the query looks at, so light never leaks through a thin wall.

The density kernel is one function of a photon's squared distance (:data:`KERNELS`): the
queries of :mod:`mi_partpm.kdtree` pass the distance of every photon they accept to
:meth:`_Estimator.contribution`, which weighs it. A kernel's weight w(d^2, r^2) integrates to
pi r^2 over the disc of radius r, so every kernel shares the normalisation 1/(pi r^2).
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from .kdtree import knn_query, radius_query
from .photonmap import PhotonMaps

__all__ = ["radiance_estimate", "knn_radiance_estimate", "is_plain_diffuse", "KERNELS"]

#: Density kernels: name -> weight of a photon at squared distance d2 for radius^2 r2, or None
#: for the box kernel of the paper's eq. (2) (weight 1 within r, nothing to multiply).
KERNELS = {"box": None}


def is_plain_diffuse(flags):
    """True where the BSDF is diffuse reflection and nothing else (f_r = albedo / pi)."""
    varying = int(mi.BSDFFlags.Glossy) | int(mi.BSDFFlags.Delta) | int(mi.BSDFFlags.Transmission)
    return mi.has_flag(flags, mi.BSDFFlags.DiffuseReflection) & ((flags & varying) == 0)


class _Estimator:
    """What eq. (1) needs at a batch of query points, whatever chooses the photons.

    For a plain diffuse BSDF, f_r is the same for every photon, so the photons' powers are
    summed and multiplied by f_r once. Any other BSDF with a non-delta lobe (glossy, plastic's
    diffuse base, diffuse transmission) is evaluated per photon: f_r = eval(w_p) / |cos w_p|.
    """

    def __init__(self, maps: PhotonMaps, si, bsdf, active, radius2=None, kernel: str = "box"):
        self.maps, self.si, self.bsdf = maps, si, bsdf
        self.radius2 = radius2
        self.weight = KERNELS[kernel]
        self.ctx = mi.BSDFContext()
        self.active = mi.Bool(active)
        self.plain = is_plain_diffuse(bsdf.flags())
        # The side of the surface the query sees: the shading normal turned towards the viewer.
        self.facing = dr.select(mi.Frame3f.cos_theta(si.wi) < 0, -1.0, 1.0)
        self.n_view = si.sh_frame.n * self.facing

    def contribution(self, i, dist2, found):
        """f_r * power of photon ``i`` (power alone for plain diffuse), weighted by the kernel
        at squared distance ``dist2``; 0 from the far side."""
        maps, si = self.maps, self.si
        wi_photon = maps.photon_direction(i, found)
        power = maps.photon_power(i, found)
        same_side = dr.dot(wi_photon, self.n_view) > 0
        wo = si.to_local(wi_photon)
        cos = dr.abs(mi.Frame3f.cos_theta(wo))
        general = found & ~self.plain & (cos > 1e-6)
        f = self.bsdf.eval(self.ctx, si, wo, general) / dr.select(general, cos, 1.0)
        value = dr.select(self.plain, dr.select(same_side, power, 0.0), f * power)
        if self.weight is not None:
            value = value * self.weight(dist2, self.radius2)
        return value

    def radiance(self, total, radius2):
        """1/(pi r^2) times the summed contributions (times f_r for plain diffuse)."""
        f_plain = self.bsdf.eval(self.ctx, self.si, mi.Vector3f(0, 0, self.facing),
                                 self.active & self.plain)
        ok = self.active & (radius2 > 0) & dr.isfinite(radius2)
        scale = dr.select(ok, dr.rcp(dr.pi * dr.select(ok, radius2, 1.0)), 0.0)
        return dr.select(self.plain, f_plain * total, total) * scale


def _bounce_filter(maps: PhotonMaps, max_bounce):
    """The query's ``accept``: photons of at most ``max_bounce`` segments (None: all)."""
    if max_bounce is None or maps.bounce is None:
        return None
    limit = mi.UInt32(max_bounce)
    return lambda i, active: maps.photon_bounce(i, active) <= limit


def radiance_estimate(maps: PhotonMaps, si: mi.SurfaceInteraction3f, bsdf, radius,
                      active=True, map_range=None, with_stats: bool = False, max_bounce=None):
    """Reflected radiance towards ``si.wi`` from the photons within ``radius`` of ``si.p``.

    Parameters
    ----------
    maps : PhotonMaps
        The partitioned photon maps.
    si : mi.SurfaceInteraction3f
        Query points (eye-path hits on surfaces with a non-delta lobe).
    bsdf : mi.BSDFPtr
        The BSDF at each query point.
    radius : float
        The fixed search radius r, the same for every map.
    active : mi.Bool
        Lanes to estimate.
    map_range : (first, stop), optional
        Only maps first .. stop-1: one map's partial term of eq. (2). Default: all maps.
    with_stats : bool
        Also return the traversal statistics per query.
    max_bounce : mi.UInt32, optional
        Only photons of at most this many segments from the emitter count (per query): the
        rest of a ``max_depth`` not used by the eye path. Needs maps built with their bounce
        counts. Default: every photon.
    """
    est = _Estimator(maps, si, bsdf, active)
    result = radius_query(maps.forest, si.p, radius, est.contribution, mi.Spectrum,
                          est.active, maps=map_range, with_stats=with_stats,
                          accept=_bounce_filter(maps, max_bounce))
    total, stats = result if with_stats else (result, None)
    L = est.radiance(total, dr.square(mi.Float(radius)))
    return (L, stats) if with_stats else L


def knn_radiance_estimate(maps: PhotonMaps, si: mi.SurfaceInteraction3f, bsdf, k: int,
                          max_radius=None, active=True, with_stats: bool = False,
                          max_bounce=None):
    """Conventional (Jensen) estimate: the k nearest photons, r = distance to the k-th.

    Returns ``(L, result)``: the radiance and the :class:`~mi_partpm.kdtree.KnnResult`
    (``radius2`` per query: the squared kNN radius; where fewer than k photons are found,
    ``max_radius**2`` as in Jensen's ``locate_photons``, or without a cap the squared distance
    to the farthest one found). ``max_bounce`` as in :func:`radiance_estimate`.
    """
    est = _Estimator(maps, si, bsdf, active)
    res = knn_query(maps.forest, si.p, k, est.contribution, mi.Spectrum, max_radius,
                    est.active, with_stats=with_stats, accept=_bounce_filter(maps, max_bounce))
    return est.radiance(res.total, res.radius2), res
