"""Eye paths of a photon mapper: from the camera through delta bounces to density estimates.

Step 2 of the paper's algorithm: shoot eye rays and intersect them with the scene. The path
follows mirror and glass (delta) lobes; at every hit whose BSDF has a non-delta lobe the
photon maps give the reflected radiance there (and, with ``nee``, emitter sampling gives the
direct part). Emission is added where the camera sees an emitter directly or through delta
bounces, the only paths the estimates do not already count.
"""
from __future__ import annotations

from typing import Callable

import drjit as dr
import mitsuba as mi
import numpy as np

from .kdtree import morton_order

from .props import UNLIMITED_DEPTH, segment_limit

__all__ = ["eye_path_radiance", "direct_light", "first_hits"]


def direct_light(scene: mi.Scene, sampler: mi.Sampler, si: mi.SurfaceInteraction3f, bsdf,
                 active):
    """Direct illumination at ``si`` by one emitter sample (visibility tested)."""
    ctx = mi.BSDFContext()
    ds, emitter_weight = scene.sample_emitter_direction(si, sampler.next_2d(active), True,
                                                        active)
    active = active & (ds.pdf != 0)
    f = bsdf.eval(ctx, si, si.to_local(ds.d), active)
    return dr.select(active, f * emitter_weight, 0.0)


@dr.syntax
def eye_path_radiance(scene: mi.Scene, sampler: mi.Sampler, ray: mi.Ray3f,
                      estimate: Callable, max_depth: int, rr_depth: int, nee: bool,
                      hide_emitters: bool, active=True, emission: float = 1.0):
    """Radiance along ``ray``: emission plus photon-map estimates at non-delta hits.

    Parameters
    ----------
    estimate : callable(si, bsdf, active, max_bounce) -> mi.Spectrum
        Reflected radiance from the photon maps at a hit, from photons of at most
        ``max_bounce`` segments (None: any).
    max_depth : int
        Longest light path in segments from the emitter to the camera, as Mitsuba's ``path``
        counts it (-1: unlimited): at a hit e segments from the camera, emission counts if
        e <= max_depth, emitter sampling if e + 1 <= max_depth, photons of b segments if
        e + b <= max_depth.
    rr_depth : int
        Segment count from which Russian roulette may end a delta chain.
    nee : bool
        Add direct light by emitter sampling (the maps then hold indirect light only).
    hide_emitters : bool
        Emitters seen directly by the camera are black.
    emission : float
        Weight of the terms that do not come from the photon maps (emission, and direct light
        with ``nee``): 1, or 0 on all ranks but one of a distributed render, so that the ranks'
        partial images add up to the image. They are still evaluated, so every rank draws the
        same random numbers and follows the same eye paths.

    Returns
    -------
    (mi.Spectrum, mi.Bool)
        The radiance and whether the camera ray hit a surface.
    """
    bounded = max_depth != UNLIMITED_DEPTH
    max_depth = segment_limit(max_depth)
    ray = mi.Ray3f(ray)
    L = mi.Spectrum(0)
    beta = mi.Spectrum(1)
    depth = mi.UInt32(0)
    valid = mi.Bool(False)
    active = mi.Bool(active)
    ctx_delta = mi.BSDFContext()
    ctx_delta.type_mask = mi.BSDFFlags.Delta

    while dr.hint(active, label="partpm_eye_path"):
        si = scene.ray_intersect(ray, active)
        valid |= active & si.is_valid() & (depth == 0)

        # Emission seen by the camera, directly or through delta bounces.
        emitter = si.emitter(scene, active)
        show = active & (emitter != None) & ((depth > 0) | (not hide_emitters))  # noqa: E711
        L += dr.select(show, beta * emitter.eval(si, show), 0.0) * emission

        active &= si.is_valid()
        bsdf = si.bsdf(ray)
        flags = bsdf.flags()

        # Density estimate (and direct light) where the BSDF has a non-delta lobe and the
        # path may grow by at least one more segment towards the light.
        smooth = active & mi.has_flag(flags, mi.BSDFFlags.Smooth) & (depth + 1 < max_depth)
        max_bounce = mi.UInt32(max_depth) - (depth + 1) if bounded else None
        L += beta * estimate(si, bsdf, smooth, max_bounce)
        if nee:
            L += beta * direct_light(scene, sampler, si, bsdf, smooth) * emission

        # Follow the delta lobes (mirror, glass, plastic's coat).
        follow = active & mi.has_flag(flags, mi.BSDFFlags.Delta) & (depth + 1 < max_depth)
        bs, weight = bsdf.sample(ctx_delta, si, sampler.next_1d(follow),
                                 sampler.next_2d(follow), follow)
        beta *= weight
        ray = si.spawn_ray(si.to_world(bs.wo))
        follow &= dr.any(beta != 0)
        if depth + 1 >= rr_depth:
            q = dr.minimum(dr.max(beta), 0.95)
            survive = sampler.next_1d(follow) < q
            beta = dr.select(survive, beta / q, 0.0)
            follow &= survive
        depth += 1
        active = follow

    return L, valid


def first_hits(scene: mi.Scene, spp: int = 1, seed: int = 0, max_depth: int = 16,
               sensor: int = 0, limit: int = 0):
    """Where each eye path first needs a density estimate: its first non-delta hit.

    One path per sample (``spp`` per pixel, pixel-major), through the camera and along
    mirror and glass (delta) lobes, as :func:`eye_path_radiance` follows them. Paths that
    leave the scene, or stay on delta surfaces for ``max_depth`` segments, give no hit.
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
    ctx_delta = mi.BSDFContext()
    ctx_delta.type_mask = mi.BSDFFlags.Delta
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
        if not dr.any(active):
            break
    keep = dr.compress(found)
    if 0 < limit < dr.width(keep):
        keep = dr.gather(mi.UInt32, keep, mi.UInt32(
            np.linspace(0, dr.width(keep) - 1, limit).round().astype(np.uint32)))
    points = np.array(dr.gather(mi.Point3f, hits.p, keep)).T
    keep = dr.gather(mi.UInt32, keep, mi.UInt32(morton_order(points).astype(np.uint32)))
    hits = dr.gather(mi.SurfaceInteraction3f, hits, keep)
    return hits, hits.bsdf(), keep
