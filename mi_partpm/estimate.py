"""Density estimation: reflected radiance at a surface point from partitioned photon maps.

Eq. (2) of the paper: with the same fixed radius r for every map,

    L_r(x, w) ~= 1/(pi r^2) * sum over maps i, sum over photons p of map i within r of x
                  of f_r(x, w_p, w) * dPhi_p

so the gathered estimate is the sum of the per-map estimates. A photon counts only if it
arrived on the side of the surface the query looks at, so light never leaks through a thin wall.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from .kdtree import radius_query
from .photonmap import PhotonMaps

__all__ = ["radiance_estimate", "is_plain_diffuse"]

def is_plain_diffuse(flags):
    """True where the BSDF is diffuse reflection and nothing else (f_r = albedo / pi)."""
    varying = int(mi.BSDFFlags.Glossy) | int(mi.BSDFFlags.Delta) | int(mi.BSDFFlags.Transmission)
    return mi.has_flag(flags, mi.BSDFFlags.DiffuseReflection) & ((flags & varying) == 0)


def radiance_estimate(maps: PhotonMaps, si: mi.SurfaceInteraction3f, bsdf, radius,
                      active=True, map_range=None, with_stats: bool = False):
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

    Notes
    -----
    For a plain diffuse BSDF, f_r is the same for every photon, so the photons' powers are
    summed and multiplied by f_r once. Any other BSDF with a non-delta lobe (glossy, plastic's
    diffuse base, diffuse transmission) is evaluated per photon: f_r = eval(w_p) / |cos w_p|.
    """
    ctx = mi.BSDFContext()
    active = mi.Bool(active)
    plain = is_plain_diffuse(bsdf.flags())
    # The side of the surface the query sees: the shading normal turned towards the viewer.
    facing = dr.select(mi.Frame3f.cos_theta(si.wi) < 0, -1.0, 1.0)
    n_view = si.sh_frame.n * facing

    def contribution(i, found):
        wi_photon = dr.gather(mi.Vector3f, maps.direction, i, found)
        power = dr.gather(mi.Spectrum, maps.power, i, found)
        same_side = dr.dot(wi_photon, n_view) > 0
        wo = si.to_local(wi_photon)
        cos = dr.abs(mi.Frame3f.cos_theta(wo))
        general = found & ~plain & (cos > 1e-6)
        f = bsdf.eval(ctx, si, wo, general) / dr.select(general, cos, 1.0)
        return dr.select(plain, dr.select(same_side, power, 0.0), f * power)

    result = radius_query(maps.forest, si.p, radius, contribution, mi.Spectrum, active,
                          maps=map_range, with_stats=with_stats)
    total, stats = result if with_stats else (result, None)

    # Plain diffuse: f_r from one evaluation at the normal on the viewer's side.
    f_plain = bsdf.eval(ctx, si, mi.Vector3f(0, 0, facing), active & plain)
    scale = 1.0 / (dr.pi * dr.square(mi.Float(radius)))
    L = dr.select(plain, f_plain * total, total) * scale
    L = dr.select(active, L, 0.0)
    return (L, stats) if with_stats else L
