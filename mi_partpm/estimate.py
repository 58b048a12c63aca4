"""Density estimation: reflected radiance at a surface point from partitioned photon maps.

Eq. (1) of the paper is the conventional estimate over the k nearest photons (``pm``);
eq. (2): with the same fixed radius r for every map,

    L_r(x, w) ~= 1/(pi r^2) * sum over maps i, sum over photons p of map i within r of x
                  of f_r(x, w_p, w) * dPhi_p

so the gathered estimate is the sum of the per-map estimates. A photon counts only if it
arrived on the side of the surface the query looks at (of its shading and of its geometric
surface), so light never leaks through a thin wall, nor over the edge of a smooth-shaded mesh.

The functions here return the *flux* sum (sum of f_r * dPhi_p, weighted by the kernel) and the
count of photons found, :class:`Flux`; the radiance is flux / (pi r^2). A progressive render
accumulates the flux and the count pass after pass (:mod:`mi_partpm.progressive`).

The density kernel is one function of a photon's squared distance (:data:`KERNELS`): the
queries of :mod:`mi_partpm.kdtree` pass the distance of every photon they accept to the
estimator's contribution, which weighs it. A kernel's weight w(d^2, r^2) integrates to pi r^2
over the disc of radius r, so every kernel shares the normalisation 1/(pi r^2).
"""
from __future__ import annotations

import logging
from dataclasses import dataclass

import drjit as dr
import numpy as np
import mitsuba as mi

from .eyepath import lobe_context, registry_flag, registry_id, registry_table, values_agree
from .kdtree import knn_query, radius_query
from .kdtree.radius import radius_array
from .photonmap import PhotonMaps
from .scenes import surface_shapes

log = logging.getLogger("mi_partpm")

__all__ = ["Flux", "gather_flux", "knn_flux", "radiance_estimate", "knn_radiance_estimate",
           "is_plain_diffuse", "note_bent_bsdfs", "bent_table", "KERNELS"]

def _simpson(d2, r2):
    """Silverman's biweight, Mitsuba 0.6's "Simpson" kernel: 3 (1 - d^2/r^2)^2."""
    t = dr.maximum(1.0 - d2 / r2, 0.0)
    return 3.0 * t * t


def _epanechnikov(d2, r2):
    """2 (1 - d^2/r^2)."""
    return 2.0 * dr.maximum(1.0 - d2 / r2, 0.0)


def _cone(d2, r2):
    """Jensen's cone filter with k = 1: 3 (1 - d/r)."""
    return 3.0 * dr.maximum(1.0 - dr.sqrt(d2 / r2), 0.0)


#: Density kernels: name -> weight of a photon at squared distance d2 for radius^2 r2, or None
#: for the box kernel of the paper's eq. (2) (weight 1 within r, nothing to multiply). Every
#: weight integrates to pi r^2 over the disc, so 1/(pi r^2) normalises them all: a uniform
#: photon density gives the same radiance with every kernel.
KERNELS = {"box": None, "simpson": _simpson, "epanechnikov": _epanechnikov, "cone": _cone}


def is_plain_diffuse(flags, bsdf=None):
    """True where the BSDF is diffuse reflection and nothing else (f_r = albedo / pi), by its
    flags, and (given the ``bsdf`` pointers) not one that bends the shading normal inside
    (:func:`note_bent_bsdfs`)."""
    varying = int(mi.BSDFFlags.Glossy) | int(mi.BSDFFlags.Delta) | int(mi.BSDFFlags.Transmission)
    plain = mi.has_flag(flags, mi.BSDFFlags.DiffuseReflection) & ((flags & varying) == 0)
    table = _BENT["table"]
    if bsdf is not None and table is not None:
        plain &= ~registry_flag(table, bsdf, plain)
    return plain


#: The class of Mitsuba's ``diffuse`` plugin, albedo / pi by construction.
LAMBERTIAN_CLASS = "SmoothDiffuse"

#: The device table of the BSDFs of the scene being rendered whose flags say diffuse
#: reflection only but which are not Lambertian about the shading frame Mitsuba hands them
#: (``normalmap`` and ``bumpmap`` bend the normal inside), by registry id; None: none is.
_BENT = {"table": None}


def note_bent_bsdfs(scene: mi.Scene, samples: int = 16) -> dict:
    """Find the BSDFs of ``scene``'s shapes that look plain diffuse by their flags but whose
    value over cos(wo) is not the same in every direction at a point of their shape (tested
    at ``samples`` points, three directions each): those are estimated per photon, with
    f_r = eval / |cos|, instead of with one f_r for all photons (a normal map's light went
    to the wrong places: from 0.79 to 1.29 of path's). Called when a render starts; made
    again for every scene, since Dr.Jit gives a freed BSDF's registry id to a new one.
    Returns {registry id: bent} of the BSDFs that look plain."""
    bent = {}
    for shape, grouped in surface_shapes(scene):
        bsdf = shape.bsdf()
        if bsdf is None or not is_plain_diffuse(int(bsdf.flags())):
            continue
        key = registry_id(bsdf)
        if key not in bent or (not bent[key] and grouped):
            # Mitsuba's own diffuse BSDF is Lambertian: only other plugins with its flags
            # (wrappers such as normalmap, bumpmap, twosided, blendbsdf) are tested, on the
            # scene's own shapes by rays onto them; one on a shape group's shape, where no
            # ray of the scene reaches, is taken as bent (estimated per photon: exact for
            # a plain one too, at the cost of one BSDF evaluation per photon).
            bent[key] = bsdf.class_name() != LAMBERTIAN_CLASS and \
                (grouped or not _lambertian(scene, shape, bsdf, samples))
    _BENT["table"] = registry_table(bent) if any(bent.values()) else None
    return bent


def bent_table():
    """The device table of the bent BSDFs :func:`note_bent_bsdfs` found last, by registry id
    (1: bent); None where none is."""
    return _BENT["table"]


def _lambertian(scene, shape, bsdf, samples: int) -> bool:
    """Whether ``bsdf`` is albedo / pi about the shading frame at ``samples`` points of
    ``shape`` (found by rays onto it from just above), within 1e-3."""
    rng = np.random.default_rng(1)
    u = [mi.Float(a) for a in rng.random((6, samples)).astype(np.float32)]
    ps = shape.sample_position(0.0, mi.Point2f(u[0], u[1]))
    ray = mi.Ray3f(ps.p + ps.n * 1e-3 * (1.0 + dr.max(dr.abs(ps.p))), -ps.n)
    si = scene.ray_intersect(ray)
    mine = dr.reinterpret_array(mi.UInt32, mi.ShapePtr(shape))[0]
    ok = si.is_valid() & (dr.reinterpret_array(mi.UInt32, si.shape) == mine)
    if not bool(dr.any(ok)[0]):
        log.warning("could not test BSDF %s for a bent normal (no probe ray reached its "
                    "shape): it is estimated as plain diffuse", bsdf.class_name())
        return True
    si.wi = mi.warp.square_to_cosine_hemisphere(mi.Point2f(u[2], u[3]))
    ratios = [np.array(mi.Spectrum(bsdf.eval(mi.BSDFContext(), si, wo, ok) /
                                   dr.maximum(mi.Frame3f.cos_theta(wo), 1e-4)))
              for wo in (mi.Vector3f(0, 0, 1),
                         mi.warp.square_to_cosine_hemisphere(mi.Point2f(u[4], u[5])),
                         mi.warp.square_to_uniform_hemisphere(mi.Point2f(u[5], u[4])))]
    return values_agree(ratios[0], ratios[1:])


@dataclass
class Flux:
    """A density estimate before its normalisation, one entry per query.

    Attributes
    ----------
    flux : mi.Spectrum
        Sum over the photons found of f_r * power * kernel weight.
    found : mi.UInt32
        Photons found (within r, on the query's side or not, accepted).
    radius2 : mi.Float
        The squared radius the photons were gathered in.
    stats : QueryStats or None
        Traversal counts, when asked for.
    """

    flux: object
    found: object
    radius2: object
    stats: object = None

    def radiance(self):
        """flux / (pi r^2), 0 where the radius is 0 or infinite."""
        ok = (self.radius2 > 0) & dr.isfinite(self.radius2)
        return self.flux * dr.select(ok, dr.rcp(dr.pi * dr.select(ok, self.radius2, 1.0)), 0.0)


@dataclass
class _Lane:
    """What the contribution of a photon needs of its query: the hit, its BSDF, the side it
    is seen from, whether f_r is constant. Put in the walk's order with the queries."""

    si: mi.SurfaceInteraction3f = None
    bsdf: mi.BSDFPtr = None
    n_view: mi.Vector3f = None
    n_geo: mi.Vector3f = None
    plain: mi.Bool = None
    radius2: mi.Float = None
    max_bounce: mi.UInt32 = None

    DRJIT_STRUCT = {"si": mi.SurfaceInteraction3f, "bsdf": mi.BSDFPtr, "n_view": mi.Vector3f,
                    "n_geo": mi.Vector3f, "plain": mi.Bool, "radius2": mi.Float,
                    "max_bounce": mi.UInt32}


class _Estimator:
    """What eqs. (1) and (2) need at a batch of query points, whatever chooses the photons.

    For a plain diffuse BSDF, f_r is the same for every photon, so the photons' powers are
    summed and multiplied by f_r once. Any other BSDF with a non-delta lobe (glossy, plastic's
    diffuse base, diffuse transmission) is evaluated per photon: f_r = eval(w_p) / |cos w_p|.
    """

    def __init__(self, maps: PhotonMaps, si, bsdf, active, radius2, max_bounce=None,
                 kernel: str = "box", lobes=None):
        self.maps = maps
        self.ctx = lobe_context(lobes)
        self.weight = KERNELS[kernel]
        self.active = mi.Bool(active)
        width = dr.width(si.p)
        # The side of the surface the query sees: the shading normal turned towards the viewer.
        facing = dr.select(mi.Frame3f.cos_theta(si.wi) < 0, -1.0, 1.0)
        self.bounded = max_bounce is not None and maps.bounce is not None
        # And the geometric normal: a photon counts only where it lies on the same side
        # of the geometric surface as of the shading one (:meth:`contribution`). Where a
        # mesh's smooth normals tilt from its faces, the shading side alone let in the
        # photons of the next face over an edge (a box's side face at 1.14 of path's, 1.01
        # with both). The viewer's own geometric side is not asked: near a smooth mesh's
        # silhouette the camera sees faces from behind that the shading normal turns
        # towards it, and path lights them (a test of the viewer's side blackened patches
        # of the Buddha). The same image where the two normals agree.
        # n_geo is the geometric normal turned to n_view's side (once per query, not per
        # photon), so a photon's two sides agree where its two dot products share a sign.
        n_view = si.sh_frame.n * facing
        n_geo = si.n * dr.select(dr.dot(n_view, si.n) < 0, -1.0, 1.0)
        self.lane = _Lane(si=si, bsdf=bsdf, n_view=n_view, n_geo=n_geo,
                          plain=is_plain_diffuse(bsdf.flags(), bsdf),
                          radius2=dr.zeros(mi.Float, width) + radius2,
                          max_bounce=dr.zeros(mi.UInt32, width) + (
                              max_bounce if self.bounded else 0))
        self.f_plain = bsdf.eval(self.ctx, si, mi.Vector3f(0, 0, facing),
                                 self.active & self.lane.plain)
        # Where every query is plain diffuse (the common case), the walk's kernel evaluates
        # no BSDF per photon: even masked off, a BSDF call in the loop costs its dispatch over
        # the scene's BSDFs for every photon found.
        self.all_plain = not bool(dr.any(self.active & ~self.lane.plain)[0])

    def contribution(self, i, dist2, found, lane: _Lane, code=None):
        """f_r * power of photon ``i`` (power alone for plain diffuse), weighted by the kernel
        at squared distance ``dist2``; 0 from the far side. ``code``: the photon's direction
        code, as the query read it with the photon's position."""
        maps = self.maps
        wi_photon = maps.photon_direction(i, found, code)
        power = maps.photon_power(i, found)
        on_view = dr.dot(wi_photon, lane.n_view)
        # On the same side of the geometric surface as of the shading one (either side:
        # transmission).
        agree = on_view * dr.dot(wi_photon, lane.n_geo) > 0
        value = dr.select((on_view > 0) & agree, power, 0.0)
        if not self.all_plain:
            wo = lane.si.to_local(wi_photon)
            cos = dr.abs(mi.Frame3f.cos_theta(wo))
            general = found & ~lane.plain & (cos > 1e-6)
            f = lane.bsdf.eval(self.ctx, lane.si, wo, general) / dr.select(general, cos, 1.0)
            # The BSDF reads the shading side; ``agree`` asks the geometric one too, or a
            # rough plastic on smooth normals took in the next face's photons over an edge
            # (a tile at 1.13 of path's).
            value = dr.select(lane.plain, value, dr.select(agree, f * power, 0.0))
        if self.weight is not None:
            value = value * self.weight(dist2, lane.radius2)
        return value

    def accept(self):
        """The queries' ``accept``: photons of at most the lane's ``max_bounce`` segments."""
        if not self.bounded:
            return None
        return lambda i, active, lane: self.maps.photon_bounce(i, active) <= lane.max_bounce

    def flux(self, total, found, radius2, stats=None) -> Flux:
        """The summed contributions as :class:`Flux` (times f_r for plain diffuse)."""
        return Flux(dr.select(self.lane.plain, self.f_plain * total, total), found, radius2,
                    stats)


def gather_flux(maps: PhotonMaps, si: mi.SurfaceInteraction3f, bsdf, radius, active=True,
                map_range=None, with_stats: bool = False, max_bounce=None,
                kernel: str = "box", order: str = "morton", lobes=None,
                walk: str = "group") -> Flux:
    """The flux of the photons within ``radius`` of ``si.p`` towards ``si.wi`` (eq. 2).

    Parameters
    ----------
    maps : PhotonMaps
        The partitioned photon maps.
    si : mi.SurfaceInteraction3f
        Query points (eye-path hits on surfaces with a non-delta lobe).
    bsdf : mi.BSDFPtr
        The BSDF at each query point.
    radius : float or mi.Float
        The search radius r: the same for every map (eq. 2), one value or one per query.
    active : mi.Bool
        Lanes to estimate.
    map_range : (first, stop), optional
        Only maps first .. stop-1: one map's partial term of eq. (2). Default: all maps.
    with_stats : bool
        Also record the traversal statistics per query.
    max_bounce : mi.UInt32, optional
        Only photons of at most this many segments from the emitter count (per query): the
        rest of a ``max_depth`` not used by the eye path. Needs maps built with their bounce
        counts. Default: every photon.
    kernel : str
        A density kernel of :data:`KERNELS`.
    order : str
        "morton" (the queries are sorted for the walk) or "given" (the caller sorted them).
    lobes : mi.BSDFFlags, optional
        The BSDF lobes evaluated (:func:`~mi_partpm.eyepath.estimated_lobes`); default all.
    walk : str
        "group" (queries side by side walk together) or "own": see
        :func:`~mi_partpm.kdtree.radius_query`.
    """
    radius = radius_array(radius)
    est = _Estimator(maps, si, bsdf, active, dr.square(radius), max_bounce, kernel, lobes)
    res = radius_query(maps.forest, si.p, radius, est.contribution, mi.Spectrum,
                       est.active, maps=map_range, with_stats=True, accept=est.accept(),
                       state=est.lane, order=order, walk=walk, with_payload=True)
    total, stats = res
    return est.flux(total, stats.photons_found, est.lane.radius2,
                    stats if with_stats else None)


def _inside(d2, r2):
    """The box kernel without the circle itself: weight 1 strictly within r."""
    return dr.select(d2 < r2, 1.0, 0.0)


def knn_flux(maps: PhotonMaps, si: mi.SurfaceInteraction3f, bsdf, k: int, max_radius=None,
             active=True, with_stats: bool = False, max_bounce=None, kernel: str = "box",
             order: str = "morton", lobes=None, walk: str = "group",
             count_kth: bool = True) -> Flux:
    """The conventional (Jensen) estimate's flux: the k nearest photons, r = distance to the
    k-th. Where fewer than k are found, r is ``max_radius`` as in Jensen's
    ``locate_photons``, or without a cap the distance to the farthest one found. Arguments
    as for :func:`gather_flux`; ``walk`` as for :func:`~mi_partpm.kdtree.knn_query`.

    ``count_kth``: eq. (1) counts the k-th photon, which lies on the circle by construction;
    under a uniform density pi r^2 then holds k - 1 photons on average (pi r^2 times the
    density is Gamma(k)-distributed), so the box kernel's estimate is k / (k - 1) too bright.
    False leaves it out (photons strictly within r), which removes that bias; the other
    kernels weigh a photon on the circle 0 and are unbiased either way."""
    est = _Estimator(maps, si, bsdf, active, 0.0, max_bounce, kernel, lobes)
    if not count_kth and est.weight is None:
        est.weight = _inside
    res = knn_query(maps.forest, si.p, k, est.contribution, mi.Spectrum, max_radius,
                    est.active, with_stats=with_stats, accept=est.accept(), state=est.lane,
                    order=order, walk=walk, with_payload=True)
    return est.flux(res.total, res.count, res.radius2, res.stats)


def radiance_estimate(maps: PhotonMaps, si, bsdf, radius, active=True, map_range=None,
                      with_stats: bool = False, max_bounce=None, order: str = "morton",
                      walk: str = "group"):
    """Reflected radiance towards ``si.wi`` from the photons within ``radius`` of ``si.p``:
    :func:`gather_flux` over pi r^2. With ``with_stats``, also the traversal counts (of the
    ``walk`` that ran)."""
    est = gather_flux(maps, si, bsdf, radius, active, map_range, with_stats, max_bounce,
                      order=order, walk=walk)
    return (est.radiance(), est.stats) if with_stats else est.radiance()


def knn_radiance_estimate(maps: PhotonMaps, si, bsdf, k: int, max_radius=None, active=True,
                          with_stats: bool = False, max_bounce=None):
    """Eq. (1): :func:`knn_flux` over pi r^2. Returns ``(L, Flux)``."""
    est = knn_flux(maps, si, bsdf, k, max_radius, active, with_stats, max_bounce)
    return est.radiance(), est
