"""Eye paths of a photon mapper: from the camera through delta bounces to visible points.

Step 2 of the paper's algorithm: shoot eye rays and intersect them with the scene. A path
follows mirror and glass (delta) lobes; every hit whose BSDF has a non-delta lobe becomes
a *visible point*, where the photon maps give the reflected radiance (and, with ``nee``,
an emitter sample and a BSDF sample, weighted by MIS, give the direct part). Emission is
added where the camera sees an emitter directly or through delta bounces, the only paths
the estimates do not already count.

:func:`eye_paths` runs all paths of a wavefront together, one step per segment (a Python loop
over depth, the lanes masked, never compacted, so every lane draws the same random numbers in
the same order as a symbolic loop would), and returns the light it found along the way and
the visible points, compacted into one buffer: the estimate then runs over that buffer in a
coherent (Morton) order instead of inside the path loop.

``max_depth`` counts the whole light path, as Mitsuba's ``path`` does: at a hit e segments from
the camera, emission counts if e <= max_depth, direct light if e + 1 <= max_depth and
photons of b segments if e + b <= max_depth.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from .kdtree import morton_order
from .props import UNLIMITED_DEPTH, segment_limit
from .scenes import surface_shapes

log = logging.getLogger("mi_partpm")

__all__ = ["EyePaths", "VisiblePoints", "eye_paths", "direct_light", "first_hits",
           "lands_on", "passes_through",
           "estimated_lobes", "lobe_context"]


def estimated_lobes(glossy: str):
    """The BSDF lobes a visible point's estimates evaluate: all of them with ``glossy = "map"``;
    only the diffuse ones with ``"trace"``, where the glossy lobes of a surface that has both
    (rough plastic) are traced on by BSDF sampling like a surface that is only glossy."""
    return mi.BSDFFlags.Diffuse if glossy == "trace" else mi.BSDFFlags.All


def lands_on(flags, glossy: bool) -> mi.Bool:
    """Where a path that goes on through delta lobes (with ``glossy``, glossy ones too) stops:
    a surface with a non-delta lobe, or with ``glossy`` one with a diffuse lobe. The photon
    tracer's caustic paths and the final gather's rays stop by this one rule."""
    return mi.has_flag(flags, mi.BSDFFlags.Diffuse if glossy else mi.BSDFFlags.Smooth)


def passes_through(flags, glossy: bool) -> mi.Bool:
    """Whether ``flags`` (a BSDF's lobes, or the lobe a sample took) hold a lobe such a path
    goes on through: a delta one, or with ``glossy`` a glossy one."""
    through = mi.has_flag(flags, mi.BSDFFlags.Delta)
    if glossy:
        through |= mi.has_flag(flags, mi.BSDFFlags.Glossy)
    return through


def lobe_context(lobes=None) -> mi.BSDFContext:
    """A BSDF context that evaluates and samples only ``lobes`` (default: all)."""
    ctx = mi.BSDFContext()
    if lobes is not None:
        ctx.type_mask = lobes
    return ctx


#: Names of the BSDFs already reported as not splitting their lobes (one warning each).
_UNSPLIT_WARNED = set()


def _splits_lobes(bsdf, samples: int = 64) -> bool:
    """Whether ``bsdf`` (with diffuse and glossy lobes) takes its lobes apart by
    ``BSDFContext.type_mask``, as ``glossy = "trace"`` needs: its diffuse and its glossy and
    delta lobes evaluated alone add up to all of them, on ``samples`` pairs of directions
    above a flat surface (Mitsuba's ``principled`` ignores the mask and evaluates every lobe
    under any of them, so a split would count its diffuse lobe twice)."""
    rng = np.random.default_rng(0)
    u = [mi.Float(a) for a in rng.random((6, samples)).astype(np.float32)]
    si = dr.zeros(mi.SurfaceInteraction3f, samples)
    si.n = mi.Normal3f(0, 0, 1)
    si.sh_frame = mi.Frame3f(si.n)
    si.uv = mi.Point2f(u[0], u[1])
    si.wi = mi.warp.square_to_cosine_hemisphere(mi.Point2f(u[2], u[3]))
    wo = mi.warp.square_to_cosine_hemisphere(mi.Point2f(u[4], u[5]))
    values = [np.array(bsdf.eval(lobe_context(lobes), si, wo)) for lobes in (
        None, mi.BSDFFlags.Diffuse, mi.BSDFFlags.Glossy | mi.BSDFFlags.Delta)]
    every, diffuse, rest = values
    return values_agree(every, [diffuse + rest])


def values_agree(reference: np.ndarray, others, tolerance: float = 1e-3) -> bool:
    """Whether every array of ``others`` equals ``reference`` within ``tolerance`` times
    the largest magnitude in ``reference`` (all agree where it is all 0): how a BSDF's
    values are compared when a scene's BSDFs are probed (:func:`unsplit_bsdfs`,
    :func:`~mi_partpm.estimate.note_bent_bsdfs`)."""
    scale = float(np.abs(reference).max(initial=0.0))
    return scale == 0.0 or all(float(np.abs(o - reference).max()) <= tolerance * scale
                               for o in others)


def _past_area_emitters(scene, ray, si, active):
    """With ``hide_emitters``, what a camera ray sees past the area emitters on its way, as
    Mitsuba's path (its ``skip_area_emitters``): the surface behind a visible light, or a
    miss (black, alpha 0) where nothing is behind it. It stopped at the light before: black,
    alpha 0 where path showed the lit wall behind it. One more intersection per light passed
    on the rays that meet one (a host loop: a few rays pass several)."""
    on = active & si.is_valid() & (si.emitter(scene, active) != None)   # noqa: E711
    while bool(dr.any(on)[0] if dr.width(on) else False):
        behind = scene.ray_intersect(si.spawn_ray(ray.d), mi.RayFlags.All, False, on)
        si[on] = behind
        on &= behind.is_valid() & (behind.emitter(scene, on) != None)   # noqa: E711
    return si


def registry_id(bsdf) -> int:
    """A BSDF's registry id: what ``dr.reinterpret_array(mi.UInt32, bsdf_ptr)`` gives per
    lane, and the index of per-BSDF tables such as :func:`registry_table`'s."""
    return int(dr.reinterpret_array(mi.UInt32, mi.BSDFPtr(bsdf))[0])


def registry_flag(table, bsdf, active=True):
    """Per lane, whether the BSDF ``bsdf`` (a ``mi.BSDFPtr``) is flagged in ``table`` (a
    :func:`registry_table`): False for lanes not ``active`` and for ids beyond the table."""
    key = dr.reinterpret_array(mi.UInt32, bsdf)
    return dr.gather(mi.UInt32, table, key, active & (key < dr.width(table))) != 0


def registry_table(flags: dict) -> mi.UInt32:
    """A device table indexed by registry id: 1 where ``flags[id]`` is true, 0 elsewhere
    (ids beyond it are 0 too, for a lookup masked by its width)."""
    table = np.zeros(max(flags, default=0) + 1, dtype=np.uint32)
    table[[key for key, value in flags.items() if value]] = 1
    return mi.UInt32(table)


def unsplit_bsdfs(scene: mi.Scene) -> mi.UInt32:
    """Per BSDF registry id: 1 for a BSDF of the scene's shapes with diffuse and glossy lobes
    that does not take them apart by ``BSDFContext.type_mask`` (:func:`_splits_lobes`), which
    ``glossy = "trace"`` then treats as ``"map"`` does (a visible point for every lobe), with
    a warning; 0 elsewhere. Ids beyond the table are BSDFs the shapes do not list: 0."""
    found = {}
    for shape, _ in surface_shapes(scene):
        bsdf = shape.bsdf()
        if bsdf is None or not (int(bsdf.flags()) & int(mi.BSDFFlags.Diffuse)
                                and int(bsdf.flags()) & int(mi.BSDFFlags.Glossy)):
            continue
        key = registry_id(bsdf)
        if key not in found:
            found[key] = not _splits_lobes(bsdf)
            name = f"{bsdf.class_name()} {bsdf.id()!r}" if bsdf.id() else bsdf.class_name()
            if found[key] and name not in _UNSPLIT_WARNED:
                _UNSPLIT_WARNED.add(name)
                log.warning("BSDF %s does not evaluate its lobes apart (it ignores "
                            "BSDFContext.type_mask): with glossy = 'trace' its surfaces are "
                            "estimated from the maps with every lobe, as with glossy = 'map'",
                            name)
    return registry_table(found)


def direct_light(scene: mi.Scene, sampler: mi.Sampler, si: mi.SurfaceInteraction3f, bsdf,
                 active, lobes=None):
    """Direct illumination at ``si`` through the BSDF's non-delta ``lobes`` (default: all),
    as Mitsuba's ``path`` takes it: one emitter sample (visibility tested) and one BSDF
    sample whose ray may find an emitter, each weighted against the other (multiple
    importance sampling, power heuristic); a delta light by its emitter sample alone. The
    emitter sample alone was unbiased but drew directions uniformly from an environment, so
    an environment-lit scene was very noisy (a ball on a floor under a sky, at 4 spp: relMSE
    0.121 against path's 0.0064; now 0.0088).
    The BSDF's delta lobes are the eye path's to follow."""
    ctx = lobe_context(lobes)
    ds, emitter_weight = scene.sample_emitter_direction(si, sampler.next_2d(active), True,
                                                        active)
    sampled = active & (ds.pdf != 0)
    f, pdf = bsdf.eval_pdf(ctx, si, si.to_local(ds.d), sampled)
    mis = dr.select(ds.delta, 1.0, _power_heuristic(ds.pdf, pdf))
    L = dr.select(sampled, f * emitter_weight * mis, 0.0)
    # The BSDF's sample, weighted against the emitter sample that could have drawn it.
    bs, weight = bsdf.sample(ctx, si, sampler.next_1d(active), sampler.next_2d(active),
                             active)
    found = active & (bs.pdf > 0) & ~mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)
    hit = scene.ray_intersect(si.spawn_ray(si.to_world(bs.wo)), found)
    emitter = hit.emitter(scene, found)
    lit = found & (emitter != None)   # noqa: E711
    mis = _emission_mis(scene, si, bs.pdf, hit, lit)
    return L + dr.select(lit, weight * emitter.eval(hit, lit) * mis, 0.0)


@dataclass
class VisiblePoints:
    """Where eye paths need a density estimate, one entry per visible point.

    Attributes
    ----------
    si : mi.SurfaceInteraction3f
        The hit (a surface with a non-delta lobe).
    bsdf : mi.BSDFPtr
        Its BSDF.
    beta : mi.Spectrum
        The path's throughput from the camera to the hit (delta bounces, Russian roulette).
    lane : mi.UInt32
        The eye path (wavefront lane) it belongs to; one path can have several (plastic).
    max_bounce : mi.UInt32
        The most segments a photon may have to count here (``max_depth`` - e), or
        0xFFFFFFFF when the depth is unlimited.
    parts : tuple of int
        How many points each depth of the paths added, in buffer order: within a part every
        lane appears at most once, so sums onto the lanes part by part are deterministic.
    """

    si: object
    bsdf: object
    beta: object
    lane: object
    max_bounce: object
    parts: tuple = ()

    def __len__(self) -> int:
        return dr.width(self.lane)

    def pieces(self) -> list:
        """The points part by part (see ``parts``), as separate :class:`VisiblePoints`."""
        sizes = self.parts or (len(self),)
        if len(sizes) == 1:
            return [self]
        out, start = [], 0
        for size in sizes:
            index = dr.arange(mi.UInt32, size) + dr.opaque(mi.UInt32, start)
            out.append(VisiblePoints(*[dr.gather(type(v), v, index) for v in (
                self.si, self.bsdf, self.beta, self.lane, self.max_bounce)], parts=(size,)))
            start += size
        return out


@dataclass
class EyePaths:
    """What :func:`eye_paths` found: per lane the light that does not come from the photon
    maps (emission, direct light with ``nee``) and whether the camera ray hit anything; and
    the visible points of all lanes."""

    emitted: object
    valid: object
    points: VisiblePoints


def _concat_points(parts) -> VisiblePoints:
    sizes = tuple(len(p) for p in parts)
    if len(parts) == 1:
        parts[0].parts = sizes
        return parts[0]
    total = sum(len(p) for p in parts)
    fields = ("si", "bsdf", "beta", "lane", "max_bounce")
    merged = {f: dr.zeros(type(getattr(parts[0], f)), total) for f in fields}
    offset = 0
    for part in parts:
        slot = dr.arange(mi.UInt32, len(part)) + dr.opaque(mi.UInt32, offset)
        for f in fields:
            dr.scatter(merged[f], getattr(part, f), slot)
        offset += len(part)
    dr.eval(merged)
    return VisiblePoints(**merged, parts=sizes)


def eye_paths(scene: mi.Scene, sampler: mi.Sampler, ray, max_depth: int, rr_depth: int,
              nee: bool, hide_emitters: bool, active=True, emission: float = 1.0,
              glossy: str = "map", glossy_samples: int = 1, beta=None,
              seed: int = 0, prev=None, unsplit=None) -> EyePaths:
    """Follow the eye rays ``ray`` (one per lane) through delta bounces.

    Parameters
    ----------
    max_depth : int
        Longest light path in segments from the emitter to the camera, as Mitsuba's ``path``
        counts it (-1: unlimited).
    rr_depth : int
        Segment count from which Russian roulette may end a delta chain.
    nee : bool
        Add direct light by emitter and BSDF sampling with MIS (the maps then hold
        indirect light only).
    hide_emitters : bool
        Emitters seen directly by the camera are black.
    emission : float
        Weight of the terms that do not come from the photon maps (emission, and direct light
        with ``nee``): 1, or 0 on all ranks but one of a distributed render, so that those
        terms are counted once. They are still evaluated, so every rank draws the same random
        numbers and follows the same eye paths.
    glossy : str
        "map": every hit with a non-delta lobe is a visible point; "trace": at a surface
        whose lobes are all glossy or delta the path goes on by BSDF sampling, and the
        visible point is the next surface with a diffuse lobe. A surface with both diffuse
        and glossy lobes (rough plastic) is a visible point for its diffuse lobes
        (:func:`estimated_lobes`), and its path goes on by sampling its glossy lobes.
    glossy_samples : int
        With "trace", the rays drawn at a path's first glossy surface (each continues alone,
        with its own random stream from ``seed``).
    beta : mi.Spectrum, optional
        The paths' starting throughput (default 1).
    prev : (mi.SurfaceInteraction3f, mi.Float), optional
        Where the rays left a glossy surface and the BSDF's pdf of their direction, for the
        MIS weight of the emission they find (a path continued from a glossy surface).
    unsplit : mi.UInt32, optional
        With "trace", :func:`unsplit_bsdfs` of the scene, if the caller has it (the paths
        continued from a glossy surface get their caller's); found here otherwise.

    With "trace", a glossy surface takes direct light by emitter sampling, and the emission
    its sampled ray finds next is weighted against it (multiple importance sampling, power
    heuristic), as Mitsuba's ``path`` does: a point light's highlight has no other way in.
    """
    bounded = max_depth != UNLIMITED_DEPTH
    limit = segment_limit(max_depth)
    # Opaque: the ranks of a distributed render (weights 1 and 0) share their kernels.
    emission = dr.opaque(mi.Float, float(emission)) if isinstance(emission, (int, float)) \
        else emission
    width = dr.width(ray.o)
    ray = mi.Ray3f(ray)
    L = dr.zeros(mi.Spectrum, width)
    beta = dr.full(mi.Spectrum, 1.0, width) if beta is None else mi.Spectrum(beta)
    trace = glossy == "trace"
    lobes = estimated_lobes(glossy)
    # With "trace", paths go on through the glossy and delta lobes; the diffuse ones are
    # the visible points'.
    ctx_traced = lobe_context(mi.BSDFFlags.Glossy | mi.BSDFFlags.Delta)
    if trace and unsplit is None:
        unsplit = unsplit_bsdfs(scene)
    splits = []
    active = dr.full(mi.Bool, True, width) & mi.Bool(active)
    # As Mitsuba's path: a ray is valid (alpha 1) once it meets a surface where it does not
    # pass straight through (a null lobe: null, mask, thindielectric's transmission), or from
    # the start where it sees a visible environment. ``passing``: lanes that met no such
    # surface yet; with hide_emitters the environment they see stays hidden.
    valid = active & (not hide_emitters and scene.environment() is not None)
    passing = mi.Bool(active)
    ctx_delta = lobe_context(mi.BSDFFlags.Delta)
    # The last glossy surface of each path and the pdf of the direction sampled there (0:
    # the path came from the camera or a delta lobe, its emission needs no MIS weight).
    prev_si, prev_pdf = prev if prev is not None else (dr.zeros(mi.SurfaceInteraction3f,
                                                                width),
                                                       dr.zeros(mi.Float, width))
    parts = []
    depth = 0
    # Once at most half of the lanes are still at work, the loop goes on over those alone
    # (``lanes``: their indices in the wavefront), reading the random numbers each would
    # have drawn in the whole wavefront (:class:`_LaneSampler`): chains of delta bounces
    # through glass (a few paths, many bounces) no longer cost whole-wavefront passes.
    lanes, wavefront = None, sampler
    while depth < limit:
        # Camera rays are coherent, as in Mitsuba's path (where two surfaces coincide,
        # Embree's coherent traversal may report the other one: path's choice is the user's)
        si = scene.ray_intersect(ray, mi.RayFlags.All, depth == 0 and prev is None, active)
        if depth == 0 and hide_emitters:
            si = _past_area_emitters(scene, ray, si, active)
        # Emission seen by the camera, directly or through delta (or sampled glossy) bounces.
        emitter = si.emitter(scene, active)
        show = active & (emitter != None)   # noqa: E711
        if depth == 0 and hide_emitters:
            # None left (past_area_emitters): the camera sees no emitter.
            show = mi.Bool(False) & show
        elif hide_emitters:                 # nor the environment past null lobes alone
            show &= si.is_valid() | ~passing
        mis = _emission_mis(scene, prev_si, prev_pdf, si, show) if trace else 1.0
        L = _add_light(L, dr.select(show, beta * emitter.eval(si, show) * mis, 0.0) * emission,
                       lanes)
        active &= si.is_valid()
        bsdf = si.bsdf(ray)
        flags = bsdf.flags()
        # A visible point where the BSDF has a non-delta lobe and the path may grow by at
        # least one more segment towards the light.
        glossy_only = mi.Bool(False)
        # Glossy lobes traced on: on surfaces that are only glossy (no visible point) and on
        # those with diffuse lobes too (a visible point for those).
        traced = mi.Bool(False)
        if trace:
            traced = active & mi.has_flag(flags, mi.BSDFFlags.Glossy)
            glossy_only = traced & ~mi.has_flag(flags, mi.BSDFFlags.Diffuse)
            # A BSDF that cannot split its lobes is a visible point for all of them.
            traced &= glossy_only | ~registry_flag(unsplit, bsdf, traced)
        if depth + 1 < limit:
            smooth = active & mi.has_flag(flags, mi.BSDFFlags.Smooth) & ~glossy_only
            # One kernel computes the hit and the mask before they are gathered from.
            dr.eval(si, bsdf, smooth, beta)
            index = dr.compress(smooth)
            if dr.width(index):
                parts.append(VisiblePoints(
                    si=dr.gather(mi.SurfaceInteraction3f, si, index),
                    bsdf=dr.gather(mi.BSDFPtr, bsdf, index),
                    beta=dr.gather(mi.Spectrum, beta, index), lane=_lanes_of(index, lanes),
                    max_bounce=dr.full(mi.UInt32, (limit - depth - 1) if bounded
                                       else 0xFFFFFFFF, dr.width(index))))
            if nee and depth + 2 <= limit:
                L = _add_light(L, beta * direct_light(scene, sampler, si, bsdf, smooth, lobes)
                               * emission, lanes)
        # Follow the delta lobes (mirror, glass, plastic's coat); with "trace", the glossy
        # surfaces by sampling their glossy and delta lobes.
        follow = active & (mi.has_flag(flags, mi.BSDFFlags.Delta) | traced) & \
            (depth + 1 < limit)
        if trace and depth + 2 <= limit:
            L = _add_light(L, beta * _glossy_direct(scene, sampler, si, bsdf, traced & active)
                           * emission, lanes)
        if trace and glossy_samples > 1:
            split = follow & traced
            index = dr.compress(split)
            if dr.width(index):
                dr.eval(si, bsdf, beta)
                splits.append((depth, dr.gather(mi.SurfaceInteraction3f, si, index),
                               dr.gather(mi.Spectrum, beta, index), _lanes_of(index, lanes)))
            follow &= ~traced
        bs, weight = bsdf.sample(ctx_delta, si, sampler.next_1d(follow),
                                 sampler.next_2d(follow), follow & ~traced)
        if trace:
            bs_g, weight_g = bsdf.sample(ctx_traced, si, sampler.next_1d(follow & traced),
                                         sampler.next_2d(follow & traced), follow & traced)
            bs = dr.select(traced, bs_g, bs)
            weight = dr.select(traced, weight_g, weight)
            glossy_sampled = follow & traced & \
                ~mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)
            prev_si = dr.select(glossy_sampled, si, prev_si)
            prev_pdf = dr.select(glossy_sampled, bs.pdf, 0.0)
            dr.eval(prev_si, prev_pdf)
        # A hit is met (the ray valid) unless the path passed straight through it.
        met = active & ~(follow & mi.has_flag(bs.sampled_type, mi.BSDFFlags.Null))
        valid = _or_lanes(valid, met, lanes)
        passing &= ~met
        beta *= weight
        ray = si.spawn_ray(si.to_world(bs.wo))
        follow &= dr.any(beta != 0)
        if depth + 1 >= rr_depth:
            q = dr.minimum(dr.max(beta), 0.95)
            survive = sampler.next_1d(follow) < q
            beta = dr.select(survive, beta / q, 0.0)
            follow &= survive
        active = follow
        wavefront.schedule_state()
        dr.eval(L, beta, valid, passing, active, ray)
        depth += 1
        at_work = int(dr.count(active)[0])
        if at_work == 0:
            break
        if at_work <= dr.width(active) * COMPACT_SHARE:
            keep = dr.compress(active)
            ray, beta = dr.gather(mi.Ray3f, ray, keep), dr.gather(mi.Spectrum, beta, keep)
            passing = dr.gather(mi.Bool, passing, keep)
            if trace:
                prev_si = dr.gather(mi.SurfaceInteraction3f, prev_si, keep)
                prev_pdf = dr.gather(mi.Float, prev_pdf, keep)
                dr.eval(prev_si, prev_pdf)
            lanes = _lanes_of(keep, lanes)
            active = dr.full(mi.Bool, True, at_work)
            sampler = _LaneSampler(wavefront, lanes, width)
            dr.eval(ray, beta, passing, lanes)
    for depth_at, si, beta_at, lanes in splits:
        L = _split_paths(scene, si, beta_at, lanes, depth_at, limit, bounded, rr_depth, nee,
                         emission, glossy_samples, seed, L, parts, ctx_traced, unsplit)
    if not parts:
        parts = [VisiblePoints(dr.zeros(mi.SurfaceInteraction3f, 0), dr.zeros(mi.BSDFPtr, 0),
                               dr.zeros(mi.Spectrum, 0), dr.zeros(mi.UInt32, 0),
                               dr.zeros(mi.UInt32, 0))]
    return EyePaths(emitted=L, valid=valid, points=_concat_points(parts))


#: The eye-path loop goes on over the lanes still at work alone once they are at most this
#: share of those it ran over (0: never).
COMPACT_SHARE = 0.5


def _lanes_of(index, lanes):
    """The wavefront lanes of ``index`` (positions among the lanes at work, ``lanes``; None:
    all lanes, in order)."""
    return index if lanes is None else dr.gather(mi.UInt32, lanes, index)


def _or_lanes(mask, value, lanes):
    """``mask`` (per wavefront lane) or'ed with ``value`` (per lane at work)."""
    if lanes is None:
        return mask | value
    dr.scatter(mask, True, lanes, value)
    return mask


def _add_light(L, value, lanes):
    """``L`` (per wavefront lane) with ``value`` (per lane at work) added to it."""
    if lanes is None:
        return L + value
    # distinct lanes: plain adds (the default mode compiles L's size into the kernel)
    dr.scatter_add(L, value, lanes, mode=dr.ReduceMode.NoConflicts)
    return L


class _LaneSampler:
    """A sampler's random numbers for the lanes ``lanes`` of its wavefront of ``width``: each
    draw is the whole wavefront's, with the mask of those lanes spread over it, read at
    them; so every lane draws what it would without the others (the same image)."""

    def __init__(self, sampler, lanes, width: int):
        self.sampler, self.lanes, self.width = sampler, lanes, width

    def _mask(self, active):
        mask = dr.zeros(mi.Bool, self.width)
        dr.scatter(mask, dr.full(mi.Bool, True, dr.width(self.lanes)) & mi.Bool(active),
                   self.lanes)
        return mask

    def next_1d(self, active=True):
        return dr.gather(mi.Float, self.sampler.next_1d(self._mask(active)), self.lanes)

    def next_2d(self, active=True):
        return dr.gather(mi.Point2f, self.sampler.next_2d(self._mask(active)), self.lanes)

    def schedule_state(self):
        self.sampler.schedule_state()


def _power_heuristic(a, b):
    """a^2 / (a^2 + b^2), finite: 1 (or 1/2) where a (and b) is infinite, as a pdf of a
    direction at a grazing angle to an area light is (inf / inf was a NaN pixel)."""
    a2, b2 = dr.square(a), dr.square(b)
    w = dr.select(a2 + b2 > 0, a2 / dr.select(a2 + b2 > 0, a2 + b2, 1.0), 0.0)
    return dr.select(dr.isinf(a2), dr.select(dr.isinf(b2), 0.5, 1.0), w)


def _glossy_direct(scene, sampler, si, bsdf, active):
    """Direct light through the glossy lobes by one emitter sample, MIS-weighted against
    sampling those lobes (delta lights take it all)."""
    ctx = lobe_context(mi.BSDFFlags.Glossy)
    ds, emitter_weight = scene.sample_emitter_direction(si, sampler.next_2d(active), True,
                                                        active)
    active = active & (ds.pdf != 0)
    value, pdf = bsdf.eval_pdf(ctx, si, si.to_local(ds.d), active)
    mis = dr.select(ds.delta, 1.0, _power_heuristic(ds.pdf, pdf))
    return dr.select(active, value * emitter_weight * mis, 0.0)


def _emission_mis(scene, prev_si, prev_pdf, si, active):
    """The MIS weight of emission found by a ray sampled at a glossy surface (1 where the
    ray came from the camera or a delta lobe)."""
    sampled = active & (prev_pdf > 0)
    ds = mi.DirectionSample3f(scene, si, prev_si)
    em_pdf = scene.pdf_emitter_direction(prev_si, ds, sampled)
    return dr.select(sampled, _power_heuristic(prev_pdf, em_pdf), 1.0)


def _split_paths(scene, si, beta, lanes, depth, limit, bounded, rr_depth, nee, emission,
                 samples, seed, L, parts, ctx, unsplit):
    """Continue paths from their first glossy surface ``samples`` times through its glossy
    and delta lobes (``ctx``), each with weight 1/samples and a sampler of its own; their
    light is added to ``L`` and their visible points to ``parts``, on the paths' own lanes."""
    count = dr.width(lanes)
    bsdf = si.bsdf()
    left = (limit - depth - 1) if bounded else UNLIMITED_DEPTH
    for j in range(samples):
        sampler = mi.load_dict({"type": "independent"})
        sampler.seed((seed * 7919 + depth * 131 + j) & 0x7FFFFFFF, count)
        bs, weight = bsdf.sample(ctx, si, sampler.next_1d(), sampler.next_2d())
        ray = si.spawn_ray(si.to_world(bs.wo))
        glossy_pdf = dr.select(mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta), 0.0, bs.pdf)
        sub = eye_paths(scene, sampler, ray, left, max(1, rr_depth - depth - 1), nee, False,
                        dr.any(weight != 0), emission, "trace", 1, beta * weight / samples,
                        seed, prev=(si, glossy_pdf), unsplit=unsplit)
        dr.scatter_add(L, sub.emitted, lanes, mode=dr.ReduceMode.NoConflicts)
        for points in sub.points.pieces():
            if len(points):
                points.lane = dr.gather(mi.UInt32, lanes, points.lane)
                dr.eval(points.lane, L)
                parts.append(points)
    return L


def first_hits(scene: mi.Scene, spp: int = 1, seed: int = 0, max_depth: int = 16,
               sensor: int = 0, limit: int = 0):
    """Where each eye path first needs a density estimate: its first non-delta hit.

    One path per sample (``spp`` per pixel, pixel-major), through the camera and along
    mirror and glass (delta) lobes, as :func:`eye_paths` follows them. Paths that leave the
    scene, or stay on delta surfaces for ``max_depth`` segments, give no hit.
    ``max_depth = 1`` gives the camera rays' own first hits (no delta bounce followed).
    ``limit`` > 0 keeps at most that many hits, spread evenly over the samples. This is the
    one generator of query points for the experiments (speedup, comparison, benchmarks).

    Returns
    -------
    (mi.SurfaceInteraction3f, mi.BSDFPtr, mi.UInt32)
        The hits, their BSDFs and the index of the sample each came from. The hits are in
        Morton order of their positions (:func:`~mi_partpm.kdtree.morton_order`), so a
        batch of density estimates over them is spatially coherent.
    """
    cam = scene.sensors()[sensor]
    size = cam.film().crop_size()
    count = int(size[0]) * int(size[1]) * int(spp)
    sampler = cam.sampler().clone()
    sampler.set_sample_count(spp)
    sampler.seed(seed, count)
    idx = dr.arange(mi.UInt32, count)
    pixel = idx // spp
    pos = mi.Vector2f(mi.Float(pixel % int(size[0])), mi.Float(pixel // int(size[0])))
    uv = (pos + sampler.next_2d()) / mi.ScalarVector2f(size)
    ray, _ = cam.sample_ray(0.0, 0.5, uv, sampler.next_2d())
    ctx_delta = lobe_context(mi.BSDFFlags.Delta)
    active = dr.full(mi.Bool, True, count)
    found = dr.full(mi.Bool, False, count)
    hits = dr.zeros(mi.SurfaceInteraction3f, count)
    for _ in range(max_depth):
        si = scene.ray_intersect(ray, active)
        active &= si.is_valid()
        bsdf = si.bsdf(ray)
        smooth = active & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)
        hits = dr.select(smooth, si, hits)
        found |= smooth
        active &= ~smooth & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Delta)
        bs, weight = bsdf.sample(ctx_delta, si, sampler.next_1d(active), sampler.next_2d(active),
                                 active)
        active &= dr.any(weight != 0)
        ray = si.spawn_ray(si.to_world(bs.wo))
        dr.eval(ray, active, hits, found)
        if not dr.any(active)[0]:
            break
    keep = dr.compress(found)
    if 0 < limit < dr.width(keep):
        keep = dr.gather(mi.UInt32, keep, mi.UInt32(
            np.linspace(0, dr.width(keep) - 1, limit).round().astype(np.uint32)))
    points = dr.gather(mi.Point3f, hits.p, keep)
    keep = dr.gather(mi.UInt32, keep, mi.UInt32(morton_order(points).astype(np.uint32)))
    hits = dr.gather(mi.SurfaceInteraction3f, hits, keep)
    return hits, hits.bsdf(), keep
