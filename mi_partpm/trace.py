"""Photon tracing: emit photons from a Mitsuba scene's emitters and store them on surfaces.

Step 1 of the paper's algorithm (figure 4): every map i of n traces its own share of the N
photons from its own random stream, so the n partial maps are independent and, together, are
the full photon map. Photon power is normalised by the TOTAL photon count N, so the per-map
density estimates add up to the full estimate with no rescaling (eq. 2).

Tracing is a wavefront in Dr.Jit: one kernel per bounce over all live photon paths, after
which the paths that ended are compacted away. The Python loop runs over bounces, never over
photons. The photons of this phase are :class:`Photons`, on the host; :mod:`.photonmap` builds
the maps from them.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Optional, Sequence

import drjit as dr
import mitsuba as mi
import numpy as np

from .memory import TRACE_BATCH
from .props import segment_limit
from .scenes import check_scene

__all__ = ["Photons", "map_sizes", "map_seeds", "stream_seed", "trace_photons", "check_emitters",
           "emit"]


@dataclass
class Photons:
    """Photons stored on non-delta surfaces, on the host.

    Attributes
    ----------
    position : (K, 3) float32
        Where the photon was stored.
    direction : (K, 3) float32
        Unit incident direction, pointing from the surface back along the arriving photon.
    power : (K, C) float32
        Flux carried (C colour channels), already divided by the total emitted count N.
    normal : (K, 3) float32
        Shading normal at the hit, turned to the side the photon arrived from.
    map_id : (K,) uint32
        The partial map the photon belongs to (the map whose emission produced it).
    bounce : (K,) uint16
        Number of segments from the emitter (1 = direct illumination).
    emitted : int
        N, the photons emitted in total over all maps (also those of maps not traced here).
    map_count : int
        n, the number of partial maps.
    segments : int
        Ray segments traced to make them (one scene intersection each): the tracer's work.
    """

    position: np.ndarray
    direction: np.ndarray
    power: np.ndarray
    normal: np.ndarray
    map_id: np.ndarray
    bounce: np.ndarray
    emitted: int
    map_count: int
    segments: int = 0

    def __len__(self) -> int:
        return int(self.position.shape[0])

    def select(self, mask: np.ndarray) -> "Photons":
        """The photons where ``mask`` holds (same N and n)."""
        return Photons(self.position[mask], self.direction[mask], self.power[mask],
                       self.normal[mask], self.map_id[mask], self.bounce[mask],
                       self.emitted, self.map_count)

    def with_maps(self, map_id: np.ndarray, map_count: int) -> "Photons":
        """The same photons assigned to other maps (for partition-invariance checks)."""
        return Photons(self.position, self.direction, self.power, self.normal,
                       np.asarray(map_id, dtype=np.uint32), self.bounce, self.emitted,
                       int(map_count))

    @property
    def nbytes(self) -> int:
        return int(sum(a.nbytes for a in (self.position, self.direction, self.power,
                                          self.normal, self.map_id, self.bounce)))


def map_sizes(photon_count: int, map_count: int) -> np.ndarray:
    """Emitted photons per map: as even as possible, sizes differ by at most one, sum is N."""
    base, extra = divmod(int(photon_count), int(map_count))
    return np.array([base + (i < extra) for i in range(map_count)], dtype=np.int64)


def _splitmix64(x: np.ndarray) -> np.ndarray:
    x = (x + np.uint64(0x9E3779B97F4A7C15)).astype(np.uint64)
    x = ((x ^ (x >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)).astype(np.uint64)
    x = ((x ^ (x >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)).astype(np.uint64)
    return (x ^ (x >> np.uint64(31))).astype(np.uint64)


def stream_seed(seed: int, render_seed: int = 0, pass_index: int = 0) -> int:
    """The seed of a render's photon streams: the ``seed`` prop for render seed 0 and pass 0,
    else a hash of (seed, render seed, pass), so every ``mi.render(..., seed=s)`` and every
    progressive pass traces other photons."""
    if render_seed == 0 and pass_index == 0:
        return int(seed)
    with np.errstate(over="ignore"):
        x = _splitmix64(np.array([int(seed) & 0xFFFFFFFFFFFFFFFF], dtype=np.uint64))
        x = _splitmix64(x ^ np.uint64((int(render_seed) * 0x9E3779B97F4A7C15)
                                      & 0xFFFFFFFFFFFFFFFF))
        x = _splitmix64(x ^ np.uint64((int(pass_index) * 0xC2B2AE3D27D4EB4F)
                                      & 0xFFFFFFFFFFFFFFFF))
    return int(x[0])


def map_seeds(seed: int, map_count: int) -> np.ndarray:
    """The random-stream state of each map: a hash of (seed, map index) and nothing else."""
    with np.errstate(over="ignore"):
        s = _splitmix64(np.full(map_count, int(seed) & 0xFFFFFFFFFFFFFFFF, dtype=np.uint64))
        return _splitmix64(s ^ (np.arange(map_count, dtype=np.uint64) * np.uint64(0xD1B54A32D192ED03)))


def _gather_all(idx, *values):
    return [dr.gather(type(v), v, idx) for v in values]


def _emitter_name(emitter) -> str:
    """How to name an emitter in a message: its shape's id or its own id, and its type."""
    shape = emitter.get_shape() if hasattr(emitter, "get_shape") else None
    if shape is not None:
        where = f"on shape {shape.id()!r}" if shape.id() else "on an unnamed shape"
    else:
        where = repr(emitter.id()) if emitter.id() else "(unnamed)"
    return f"{where} ({emitter.class_name()})"


#: Emitters whose ``sample_ray`` power disagrees with what ``sample_direction`` (and so
#: Mitsuba's ``path``) shows when their ``to_world`` has a scale s: the projector returns
#: directions of length s and irradiance s times that of its unscaled ``sample_ray`` power.
#: Scaling the photon's power by the length before normalising makes the two agree.
SCALED_BY_DIRECTION_LENGTH = ("Projector",)


def _emitter_table(scene: mi.Scene):
    """Per emitter registry id: 1 where the photon power scales with |ray.d|."""
    ids = dr.reinterpret_array(mi.UInt32, scene.emitters_dr()).numpy()
    table = np.zeros(int(ids.max()) + 1 if ids.size else 1, dtype=np.uint32)
    for emitter, i in zip(scene.emitters(), ids):
        table[i] = emitter.class_name() in SCALED_BY_DIRECTION_LENGTH
    return mi.UInt32(table)


def emit(scene: mi.Scene, rng, photon_count: int, table):
    """Photon rays leaving the scene's emitters, with unit directions, and their power over
    ``photon_count`` (one emitter chosen per photon by the scene, as ``path`` does)."""
    ray, weight, emitter = scene.sample_emitter_ray(
        mi.Float(0), rng.next_float32(), mi.Point2f(rng.next_float32(), rng.next_float32()),
        mi.Point2f(rng.next_float32(), rng.next_float32()), mi.Bool(True))
    length = dr.norm(ray.d)
    scaled = dr.gather(mi.UInt32, table, dr.reinterpret_array(mi.UInt32, emitter)) == 1
    power = mi.Spectrum(weight) * dr.select(scaled, length, 1.0) / float(photon_count)
    ray.d = ray.d / dr.select(length > 0, length, 1.0)
    return ray, power


def check_emitters(scene: mi.Scene, samples: int = 1024):
    """Refuse emitters whose power is NaN, infinite or negative, before any photon is traced.

    Each emitter emits ``samples`` test rays (stratified samples); Mitsuba accepts such
    values in a scene file, and the tracer would otherwise drop those photons silently.
    """
    check_scene(scene, needs_sensor=False)
    u = (np.arange(samples, dtype=np.float64) + 0.5) / samples
    rng = np.random.default_rng(0)
    s = [mi.Float(np.asarray(a, np.float32)) for a in (u, *rng.random((4, samples)))]
    for emitter in scene.emitters():
        _, weight = emitter.sample_ray(0.0, s[0], mi.Point2f(s[1], s[2]),
                                       mi.Point2f(s[3], s[4]), True)
        w = np.atleast_2d(np.array(mi.Spectrum(weight)))
        name = _emitter_name(emitter)
        if not np.all(np.isfinite(w)):
            raise ValueError(f"emitter {name} emits non-finite power (NaN or inf): its "
                             f"radiance / intensity must be finite and >= 0")
        if np.any(w < 0):
            raise ValueError(f"emitter {name} emits negative power (down to {w.min():.4g}): "
                             f"its radiance / intensity must be finite and >= 0")


def trace_photons(scene: mi.Scene, photon_count: int, map_count: int = 1, seed: int = 0,
                  max_depth: int = -1, rr_depth: int = 5, maps: Optional[Sequence[int]] = None,
                  min_bounce: int = 1,
                  progress: Optional[Callable[[str], None]] = None,
                  batch_size: int = TRACE_BATCH,
                  memory_check: Optional[Callable[[float, int], None]] = None) -> Photons:
    """Trace ``photon_count`` photons split over ``map_count`` maps.

    Parameters
    ----------
    scene : mi.Scene
        Any scene with at least one emitter (area, point, spot, directional, environment...).
    photon_count : int
        N, photons emitted in total over all maps.
    map_count : int
        n; map i emits ``map_sizes(N, n)[i]`` photons from its own stream (seed, i).
    seed : int
        Seed of the photon streams.
    max_depth : int
        Longest photon path in segments from the emitter (-1: unlimited, Russian roulette
        ends the paths).
    rr_depth : int
        Segment count from which Russian roulette may end a path.
    maps : sequence of int, optional
        Trace only these maps (a rank of a distributed job); default all.
    min_bounce : int
        Store photons from this many segments on (2 leaves out direct illumination).
    progress : callable(str), optional
        Receives a line per bounce.
    batch_size : int
        Photon paths traced together at most; more run in batches (same photons).
    memory_check : callable(stored_per_emitted, traced), optional
        Called after each batch but the last with the measured photons stored per photon
        emitted; it may raise to stop before memory runs out.

    Returns
    -------
    Photons
        Stored photons, ``emitted == photon_count`` whichever maps were traced.
    """
    check_emitters(scene)
    sizes = map_sizes(photon_count, map_count)
    maps = np.arange(map_count) if maps is None else np.asarray(list(maps), dtype=np.int64)
    max_depth = segment_limit(max_depth)

    # Lane -> (map, index within the map), for the traced maps only.
    lane_map = np.repeat(maps, sizes[maps]).astype(np.uint32)
    lane_index = (np.arange(lane_map.shape[0]) - np.repeat(
        np.concatenate(([0], np.cumsum(sizes[maps])))[:-1], sizes[maps])).astype(np.uint64)
    n_lanes = int(lane_map.shape[0])
    channels = 3 if mi.is_rgb else 1
    empty = Photons(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32),
                    np.zeros((0, channels), np.float32), np.zeros((0, 3), np.float32),
                    np.zeros(0, np.uint32), np.zeros(0, np.uint16), int(photon_count),
                    int(map_count))
    if n_lanes == 0:
        return empty

    stored = {k: [] for k in ("position", "direction", "power", "normal", "map_id", "bounce")}
    segments = 0
    for first in range(0, n_lanes, batch_size):
        # Batches only bound the memory: every lane's random stream depends on its (map,
        # index in the map) alone, so the photons are the same for any batch size.
        chunk = slice(first, min(first + batch_size, n_lanes))
        segments += _trace_batch(scene, lane_map[chunk], lane_index[chunk], photon_count,
                                 map_count, seed, max_depth, rr_depth, min_bounce, channels,
                                 stored, progress)
        done = chunk.stop
        if memory_check is not None and done < n_lanes:
            ratio = sum(len(m) for m in stored["map_id"]) / done
            memory_check(ratio, done)
        if progress is not None and n_lanes > batch_size:
            progress(f"batch: {done} of {n_lanes} photons traced")

    if not stored["position"]:
        empty.segments = segments
        return empty
    return Photons(*(np.concatenate(stored[k]) for k in stored), int(photon_count),
                   int(map_count), segments)


def _trace_batch(scene, lane_map, lane_index, photon_count, map_count, seed, max_depth,
                 rr_depth, min_bounce, channels, stored, progress) -> int:
    """Trace one batch of photon paths (a wavefront, one kernel per bounce); append the
    stored photons to ``stored`` and return the ray segments traced."""
    n_lanes = int(lane_map.shape[0])
    map_id = mi.UInt32(lane_map)
    rng = mi.PCG32(n_lanes)
    rng.seed(dr.gather(mi.UInt64, mi.UInt64(map_seeds(seed, map_count)), map_id),
             mi.UInt64(lane_index))

    ray, power = emit(scene, rng, photon_count, _emitter_table(scene))
    active = dr.any(power != 0) & dr.all(dr.isfinite(power))
    ctx = mi.BSDFContext(mi.TransportMode.Importance)

    segments = 0
    bounce = 1
    while bounce <= max_depth:
        # Drop the paths that ended; keep the state of the live ones.
        idx = dr.compress(active)
        alive = dr.width(idx)
        if alive == 0:
            break
        if alive != dr.width(map_id):
            ray, power, map_id, state, inc = _gather_all(idx, ray, power, map_id, rng.state,
                                                         rng.inc)
            rng = mi.PCG32(alive)
            rng.state, rng.inc = state, inc
        active = mi.Bool(True)
        segments += alive
        if progress is not None:
            progress(f"bounce {bounce}: {alive} photon paths")

        si = scene.ray_intersect(ray, active)
        active &= si.is_valid()
        bsdf = si.bsdf()
        store = active & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth) & (bounce >= min_bounce)
        normal = si.sh_frame.n
        normal = dr.select(dr.dot(normal, -ray.d) < 0, -normal, normal)
        hit_p, hit_wi, hit_power = si.p, -ray.d, power

        last = bounce == max_depth
        if not last:
            sample1 = rng.next_float32()
            sample2 = mi.Point2f(rng.next_float32(), rng.next_float32())
            bs, bsdf_weight = bsdf.sample(ctx, si, sample1, sample2, active)
            ray = si.spawn_ray(si.to_world(bs.wo))
            power = power * bsdf_weight
            active &= dr.any(power != 0) & dr.all(dr.isfinite(power))
            if bounce >= rr_depth:
                # Russian roulette on the path's throughput (power relative to its emission).
                q = dr.minimum(dr.max(bsdf_weight), 0.95)
                survive = rng.next_float32() < q
                active &= survive
                power = dr.select(survive, power / q, power)
        # One kernel per bounce: the intersection, what to store and the next segment together
        # (evaluating them apart would trace the rays once per output).
        dr.eval(hit_p, hit_wi, hit_power, normal, store, ray, power, active, rng.state, map_id)

        s = dr.compress(store)
        if dr.width(s) > 0:
            pos, wi, pw, nrm = _gather_all(s, hit_p, hit_wi, hit_power, normal)
            stored_map = dr.gather(mi.UInt32, map_id, s)
            dr.eval(pos, wi, pw, nrm, stored_map)
            stored["position"].append(pos.numpy().T)
            stored["direction"].append(wi.numpy().T)
            stored["power"].append(np.atleast_2d(pw.numpy()).reshape(channels, -1).T)
            stored["normal"].append(nrm.numpy().T)
            stored["map_id"].append(stored_map.numpy())
            stored["bounce"].append(np.full(dr.width(s), min(bounce, 65535), np.uint16))
        if last:
            break
        bounce += 1
    return segments

