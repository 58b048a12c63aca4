"""Final gathering (Jensen's two-pass method): the global map read one bounce away.

At every visible point, ``samples`` rays are drawn from its BSDF; each follows mirror and glass
to the next surface with a non-delta lobe, where the global photon map gives the radiance
arriving back (:func:`~mi_partpm.estimate.gather_flux`). Their mean, times the throughput, is
the light the visible point reflects from other surfaces. The global map is thus never read
at the visible point itself, where its blur would show; direct light there comes from emitter
sampling and caustics from the caustic map. Without a caustic map, a gather ray that reaches
an emitter through mirrors or glass brings the caustic light instead (``caustics``). With
``glossy`` (eye paths that trace glossy surfaces on, and caustic maps that hold the paths
bouncing on glossy lobes as well), the gather rays go on through glossy-only surfaces too, to
the first surface with a diffuse lobe: a rough conductor or dielectric is then not read from
a map, where a narrow lobe makes the estimate blur and flicker (a rough plastic, which has a
diffuse lobe, is read with all its lobes).

The gather rays draw their random numbers from their own streams (seed, pass, ray), so the
eye paths' sampler is left as Mitsuba's loop expects it.
"""
from __future__ import annotations

import logging

import drjit as dr
import mitsuba as mi

from .estimate import gather_flux
from .eyepath import lands_on, lobe_context, passes_through
from .props import UNLIMITED_DEPTH, segment_limit
from .timing import Heartbeat

__all__ = ["final_gather", "BATCH_LANES"]

log = logging.getLogger("mi_partpm")

#: Gather rays traced together at most when the visible points are fewer: several rays per
#: point run side by side (a preview of 16 x 16 pixels took 13 ms per ray, the kernels'
#: launches, whatever its size). With this many points or more, one ray per point at a time.
BATCH_LANES = 1 << 18


def final_gather(scene: mi.Scene, maps, points, width: int, samples: int, radius: float,
                 seed: int = 0, max_depth: int = -1, kernel: str = "box",
                 caustics: bool = False, lobes=None, glossy: bool = False):
    """The final gather's radiance per eye path (``width`` of them) and the photons found,
    summed over ``samples`` rays from each visible point of ``points``, sampled from the
    BSDF's ``lobes`` (default all; the visible points' :func:`~mi_partpm.eyepath.
    estimated_lobes`). ``glossy``: the rays go on through glossy lobes as through delta
    ones."""
    from .progressive import accumulate
    total = dr.zeros(mi.Spectrum, width)
    found = dr.zeros(mi.Float, width)
    if not len(points):
        return total, found
    limit = segment_limit(max_depth)
    # With lobes given (glossy = "trace": the diffuse ones), the null lobe too: Mitsuba 3.9's
    # mask samples its null lobe whenever the type mask leaves it out (weight 1, even at
    # opacity 1), and a gather ray from a masked diffuse surface was never a diffuse one. The
    # null samples are dropped below with the other delta ones.
    ctx = lobe_context(None if lobes is None else lobes | mi.BSDFFlags.Null)
    count = len(points)
    # The ray index and the sample count enter the kernels as opaque values, so every ray
    # runs the same kernels (compiled once) instead of kernels of its own.
    n_samples = dr.opaque(mi.UInt64, samples)
    bounded = max_depth != UNLIMITED_DEPTH
    batch = max(1, min(samples, BATCH_LANES // count))
    beat, j = Heartbeat(), 0
    while j < samples:
        rays = min(batch, samples - j)
        # Lane l: ray j + l // count of point l % count (one ray at a time, the points
        # themselves, not copies).
        lane = dr.arange(mi.UInt32, count * rays)
        if rays > 1:
            point = lane % dr.opaque(mi.UInt32, count)
            ray_index = mi.UInt64(lane // dr.opaque(mi.UInt32, count)) + dr.opaque(mi.UInt64, j)
            si = dr.gather(type(points.si), points.si, point)
            bsdf = dr.gather(mi.BSDFPtr, points.bsdf, point)
            max_bounce = dr.gather(mi.UInt32, points.max_bounce, point)
        else:
            point, ray_index = lane, dr.opaque(mi.UInt64, j)
            si, bsdf, max_bounce = points.si, points.bsdf, points.max_bounce
        # The stream of (point, ray): PCG32's constructor adds the lane to both seeds, so
        # they are given here with the point's index added instead, whatever the batch.
        rng = mi.PCG32(count * rays)
        rng.seed(dr.opaque(mi.UInt64, seed & 0xFFFFFFFFFFFFFFFF) + mi.UInt64(point),
                 mi.UInt64(point) * (n_samples + 1) + ray_index)
        bs, weight = bsdf.sample(ctx, si, rng.next_float32(),
                                 mi.Point2f(rng.next_float32(), rng.next_float32()))
        # Only the non-delta lobes: the delta ones are the eye path's own continuation.
        active = dr.any(weight != 0) & ~mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)
        # The ray's own throughput: accumulate() multiplies by the visible point's beta.
        beta = weight / dr.opaque(mi.Float, samples)
        ray = si.spawn_ray(si.to_world(bs.wo))
        # A light path here is the eye path's segments, the gather ray's and a photon's, at
        # most max_bounce after the eye path's: the photons read after k gather segments
        # may have max_bounce - k at most (bounce_left), the emission seen after k must
        # have k <= max_bounce.
        hit, hit_bsdf, active, beta, seen, bounce_left = _to_non_delta(
            scene, ray, beta, active, rng, limit, caustics, glossy,
            max_bounce=max_bounce if bounded else None)
        est = gather_flux(maps, hit, hit_bsdf, radius, active, max_bounce=bounce_left,
                          kernel=kernel)
        value = dr.select(active, beta * est.radiance(), 0.0) + seen
        got = mi.Float(est.found)
        if rays > 1:
            value, got = _per_point(value, got, count, rays)
        part_total, part_found = accumulate(points, value, got, width)
        total += part_total
        found += part_found
        dr.eval(total, found)
        j += rays
        elapsed = beat.due() if j < samples else None      # a line every 10 s or so
        if elapsed is not None:
            log.info("final gather: %d of %d rays per visible point, %.0f s, about %.0f s "
                     "left", j, samples, elapsed, elapsed / j * (samples - j))
    return total, found


def _per_point(value, found, count: int, rays: int):
    """Sums over a batch's ``rays`` rays of each of ``count`` points (lane ``l`` is point
    ``l % count``), added ray after ray in one loop: the same order in every run."""
    point = dr.arange(mi.UInt32, count)
    total_value = dr.zeros(mi.Spectrum, count)
    total_found = dr.zeros(mi.Float, count)
    k = dr.zeros(mi.UInt32, count)
    stride, n = dr.opaque(mi.UInt32, count), dr.opaque(mi.UInt32, rays)
    dr.eval(value, found)

    def body(k, total_value, total_found):
        at = point + k * stride
        return (k + 1, total_value + dr.gather(mi.Spectrum, value, at),
                total_found + dr.gather(mi.Float, found, at))
    k, total_value, total_found = dr.while_loop((k, total_value, total_found),
                                                lambda k, *_: k < n, body)
    return total_value, total_found


def _to_non_delta(scene, ray, beta, active, rng, limit: int, caustics: bool,
                  glossy: bool = False, chain: int = 8, max_bounce=None):
    """Follow delta lobes (and with ``glossy`` glossy ones) from ``ray`` to the first surface
    with a non-delta lobe (with ``glossy``: a diffuse lobe) where the ray stops (at one with
    delta lobes too, half the rays go on through those), at most ``chain`` bounces: (hit,
    its BSDF, reached, throughput, emission seen after one bounce or more when
    ``caustics``, the most segments a photon read at the hit may have). ``max_bounce`` (per
    ray; None: unlimited) bounds the segments of the ray's chain and a photon's together:
    emission seen after k segments counts where k <= max_bounce, the hit reached after k is
    read for photons of max_bounce - k segments at most (and not at all below 1)."""
    seen = dr.zeros(mi.Spectrum, dr.width(beta))
    bounded = max_bounce is not None
    left = mi.UInt32(max_bounce) if bounded else None     # segments left before this one
    bounce_left = dr.zeros(mi.UInt32, dr.width(beta)) if bounded else None
    ctx_through = lobe_context(mi.BSDFFlags.Delta | mi.BSDFFlags.Glossy if glossy
                               else mi.BSDFFlags.Delta)
    ctx_delta = lobe_context(mi.BSDFFlags.Delta)
    hit = dr.zeros(mi.SurfaceInteraction3f, dr.width(beta))
    reached = dr.zeros(mi.Bool, dr.width(beta))
    for step in range(min(chain, max(limit - 1, 1))):
        if bounded:                      # this segment must fit, and leaves left - 1
            active &= left >= 1
            left = dr.select(left >= 1, left - 1, 0)
        si = scene.ray_intersect(ray, active)
        if caustics and step > 0:
            emitter = si.emitter(scene, active)
            lit = active & (emitter != None)    # noqa: E711
            seen += dr.select(lit, beta * emitter.eval(si, lit), 0.0)
        active &= si.is_valid()
        bsdf = si.bsdf(ray)
        flags = bsdf.flags()
        lands = active & lands_on(flags, glossy)
        # A surface read from the map that has delta lobes as well (a mask's or a null
        # BSDF's pass-through, plastic's coat, a blend with glass): the map there holds only
        # its other lobes, so the ray either stops there or goes on through the delta
        # lobes, each with probability 1/2 and weight 2.
        both = lands & mi.has_flag(flags, mi.BSDFFlags.Delta)
        on = both & (rng.next_float32() < 0.5)
        stop = lands & ~on
        if bounded:                      # a photon read here needs a segment of its own
            stop &= left >= 1
            bounce_left = dr.select(stop, left, bounce_left)
        beta = dr.select(both, beta * 2.0, beta)
        hit = dr.select(stop, si, hit)
        reached |= stop
        active &= (~lands & passes_through(flags, glossy)) | on
        u1, u2 = rng.next_float32(), mi.Point2f(rng.next_float32(), rng.next_float32())
        bs, weight = bsdf.sample(ctx_through, si, u1, u2, active & ~on)
        bs_on, weight_on = bsdf.sample(ctx_delta, si, u1, u2, on)
        bs = dr.select(on, bs_on, bs)
        weight = dr.select(on, weight_on, weight)
        beta = dr.select(active, beta * weight, beta)
        active &= dr.any(weight != 0)
        ray = si.spawn_ray(si.to_world(bs.wo))
        dr.eval(hit, reached, active, beta, ray, seen, left, bounce_left)
        if not dr.any(active)[0]:
            break
    return hit, hit.bsdf(), reached, beta, seen, bounce_left
