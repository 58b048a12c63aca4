"""Mitsuba's ``path`` at many samples per pixel, rendered in chunks: the experiments'
references and their path-traced curves. One wavefront of 480 x 480 x 2048 samples would
hold half a billion lanes; chunks bound the memory and let a progress line come per chunk."""
from __future__ import annotations

from typing import Callable, Optional

import drjit as dr
import mitsuba as mi
import numpy as np

from ..scenes import surface_shapes
from ..timing import Heartbeat, timed
from .metrics import EPSILON

__all__ = ["path_in_chunks", "noise_rel_mse", "caustics_path_misses", "specular_shares",
           "SPECULAR_SHARE"]


def path_in_chunks(scene, spp: int, seed: int, chunk_spp: int, integrator=None,
                   say: Optional[Callable[[str], None]] = None,
                   label: str = "path", halves: bool = False) -> tuple:
    """``spp`` samples per pixel of ``integrator`` (default Mitsuba's ``path``) in chunks of at
    most ``chunk_spp``, chunk c seeded ``seed + c`` (mod 2^32, mi.render's range), averaged
    by their sample counts; returns the (H, W, 3) image and the seconds the renders took,
    and with ``halves`` a third item: the images of the even and of the odd chunks and their
    sample counts (None for one chunk), for :func:`noise_rel_mse`. ``say`` receives a line
    for the first chunk, about every 10 s and for the last, when there is more than one."""
    integrator = integrator or mi.load_dict({"type": "path"})
    chunks = max(1, -(-spp // chunk_spp))
    sums, counts, seconds = [0.0, 0.0], [0, 0], 0.0
    beat = Heartbeat()
    for c in range(chunks):
        n = min(chunk_spp, spp - c * chunk_spp)
        if say is not None and chunks > 1 and (c in (0, chunks - 1) or beat.due()):
            say(f"{label}, chunk {c + 1} of {chunks} ({n} spp)")
        img, t = timed(lambda: mi.render(scene, integrator=integrator, spp=n,
                                         seed=(seed + c) % 2**32))
        sums[c % 2] = sums[c % 2] + np.array(img, dtype=np.float64)[..., :3] * n
        counts[c % 2] += n
        seconds += t
    image = (sums[0] + sums[1]) / spp
    if not halves:
        return image, seconds
    return image, seconds, ((sums[0] / counts[0], sums[1] / counts[1], counts[0], counts[1])
                            if chunks > 1 else None)


def noise_rel_mse(halves) -> Optional[float]:
    """The relative MSE (:func:`~.metrics.rel_mse`) of an image against the truth, roughly,
    from its ``halves`` (the images of two parts of its samples and their counts n0 and n1,
    :func:`path_in_chunks`): their difference has N^2 / (n0 n1) times the variance of the
    whole (four times for equal halves), so that share of its square, over the square of
    the lesser half (over the image's own square, a firefly's pixel
    divided itself away: a third of the error on caustic_glass). Against path at 16,384 spp
    (32 x 32): at 2048 spp 0.0017 and 0.0015 for 0.0018 and 0.0015 (Cornell box), 0.024 and
    0.029 for 0.021 and 0.025 (caustic_glass); at 128 spp up to 3.6 times too high. None
    without halves."""
    if halves is None:
        return None
    a, b, n0, n1 = halves
    share = n0 * n1 / (n0 + n1) ** 2
    return float(np.mean((a - b) ** 2 / (np.minimum(a, b) ** 2 + EPSILON)) * share)


def _name(obj) -> str:
    return obj.id() or obj.class_name()


#: The share of the light a surface scatters by delta or null lobes (mirror, glass,
#: pass-through) above which :func:`caustics_path_misses` counts it: half a mirror
#: (blendbsdf of a mirror and a diffuse surface, 0.5) made partpm's mean 1.115 times path's
#: under a spot light; plastic's coat (about 0.05 to 0.1) a few percent.
SPECULAR_SHARE = 0.2

#: Incidence angles' cosines and samples per angle of :func:`specular_shares`.
_COSINES = (1.0, 0.7, 0.4)
_SAMPLES = 2048


def specular_shares(bsdfs) -> list:
    """Per BSDF, the share of the light it scatters (reflects or lets through) by its delta
    and null lobes: the light a ray carries that ``path`` cannot connect to a point emitter.
    Estimated in one vectorised call per BSDF by sampling it at normal and at two oblique
    incidences, at random points of uv space (a textured mask's opacity is taken over the
    texture): the mean of the sampled weights (over the colour channels) whose lobe was
    delta or null, over the mean of all. A BSDF that cannot be sampled so (a texture
    without the derivatives a bump map asks for), or whose samples all weigh nothing,
    counts by its lobes: 1 without a smooth one, else 0."""
    shares = []
    n = _SAMPLES * len(_COSINES)
    cos = np.repeat(np.array(_COSINES), _SAMPLES)
    wi = mi.Vector3f(np.sqrt(1 - cos ** 2), 0 * cos, cos)
    si = dr.zeros(mi.SurfaceInteraction3f, n)
    si.t = mi.Float(np.ones(n))
    si.wi = wi
    si.n = mi.Normal3f(0, 0, 1)
    si.sh_frame = mi.Frame3f(mi.Vector3f(0, 0, 1))
    si.dp_du, si.dp_dv = mi.Vector3f(1, 0, 0), mi.Vector3f(0, 1, 0)
    sampler = mi.load_dict({"type": "independent"})
    sampler.seed(0, n)
    si.uv = sampler.next_2d()
    ctx = mi.BSDFContext()
    u1, u2 = sampler.next_1d(), sampler.next_2d()
    for bsdf in bsdfs:
        by_lobes = 0.0 if bsdf.flags() & mi.BSDFFlags.Smooth else 1.0
        try:
            bs, weight = bsdf.sample(ctx, si, u1, u2)
        except RuntimeError:
            shares.append(by_lobes)
            continue
        grey = sum(weight[c] for c in range(len(weight))) / len(weight)
        # (a lobe or weight the same in every lane comes back as one value)
        value = np.broadcast_to(np.nan_to_num(np.array(grey, dtype=np.float64), nan=0.0,
                                              posinf=0.0, neginf=0.0), (n,))
        kind = np.broadcast_to(np.array(bs.sampled_type), (n,))
        special = (kind & int(mi.BSDFFlags.Delta | mi.BSDFFlags.Null)) != 0
        total = float(np.sum(value))
        shares.append(float(np.sum(value[special])) / total if total > 0 else by_lobes)
    return shares


def caustics_path_misses(scene) -> Optional[str]:
    """What a reference of Mitsuba's ``path`` cannot show in ``scene``, in words, or None:
    the light of an emitter at a point or from one direction (point, spot, projector,
    directional) that reaches a surface through a mirror or glass: a BSDF that scatters
    more than :data:`SPECULAR_SHARE` of its light by delta or null lobes
    (:func:`specular_shares`: a mirror, glass, thin glass, a masked or half mirror).
    ``path`` finds a surface's light by sampling an emitter, which a mirror or glass in
    between blocks, or by sampling the BSDF, whose ray never hits a point; the photon
    mappers carry that light from the emitter, so their errors against such a reference
    count the caustic it lacks (a glass cube lit by a spot: partpm's mean 1.41 times
    path's at 1024 spp)."""
    delta_lights = [e for e in scene.emitters()
                    if e.flags() & (mi.EmitterFlags.DeltaPosition | mi.EmitterFlags.DeltaDirection)]
    if not delta_lights:
        return None
    shapes, bsdfs = [], {}
    for shape, _ in surface_shapes(scene):
        bsdf = shape.bsdf()
        if bsdf is not None and bsdf.flags() & (mi.BSDFFlags.Delta | mi.BSDFFlags.Null):
            shapes.append(shape)
            bsdfs.setdefault(id(bsdf), bsdf)
    share = dict(zip(bsdfs, specular_shares(list(bsdfs.values()))))
    specular = [s for s in shapes if share[id(s.bsdf())] > SPECULAR_SHARE]
    if not specular:
        return None
    lights = ", ".join(f"'{_name(e)}'" for e in delta_lights[:3])
    surfaces = ", ".join(f"'{_name(s)}'" for s in specular[:3])
    return (f"Mitsuba's path cannot render the light of a point or directional emitter "
            f"({lights}) that reaches a surface by way of a mirror, glass or a surface that "
            f"is largely either ({surfaces}): "
            f"such caustics are missing from a path-traced reference, and a photon mapper's "
            f"error against it counts them (use an area light to compare them)")
