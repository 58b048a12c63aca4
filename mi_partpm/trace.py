"""Photon tracing: emit photons from a Mitsuba scene's emitters and store them on surfaces.

Step 1 of the paper's algorithm (figure 4): every map i of n traces its own share of the N
photons from its own random stream, so the n partial maps are independent and, together, are
the full photon map. Photon power is normalised by the TOTAL photon count N, so the per-map
density estimates add up to the full estimate with no rescaling (eq. 2).

Tracing is one Dr.Jit kernel per batch of photon paths: a symbolic loop over the bounces in
which every photon stored on a surface with a non-delta lobe (or a diffuse one,
``store_on``) takes a slot of a preallocated buffer and is written there: one
record of :data:`SLOT_FLOATS` floats (position, direction code, power, photon index),
which Dr.Jit writes as two packet stores instead of a scattered
store per value (the stores cost a third of the kernel before), and its bounce count and
rank among its path's stored photons beside it. A lane whose path has ended (absorbed,
escaped, or ended by Russian roulette) takes the batch's next photon and starts it from that
photon's own stream, so a SIMD packet does not idle until its longest path ends (1.4x faster
kernels on the Cornell box than one lane per path, the same photons). On the LLVM backend
the first packet a thread runs keeps taking photons until none is left, so a batch is in
effect one packet of paths per core. Lanes claim photons and slots with ``dr.scatter_inc``,
in runs on the LLVM backend (:func:`claim_runs`): a claim per bounce on one counter, and two
threads writing beside each other, cost a fifth of the kernel on 2 cores.

Nothing goes to the host during a batch. The slots are claimed in whatever order the
threads run; each path's count of stored photons, its prefix sum and each photon's rank put
them back in the order of the photons without a sort, so every run gives the same arrays.
A pilot of a few thousand paths measures the photons stored per path first (its photons
are traced again by the first batch), and the batches size their buffers from it, with
room for a part-full run of slots per lane at work; a batch whose lanes claim more slots
than its buffer holds is traced again with a buffer that holds them (the streams are
deterministic, so the photons are the same). Each photon's map and its index in the map,
which seed its stream, come from its index in the run on the device. The result is
:class:`~mi_partpm.photons.Photons`, on the device.
"""
from __future__ import annotations

import logging
import sys
from typing import Callable, Optional, Sequence

import drjit as dr
import mitsuba as mi
import numpy as np

from .eyepath import lands_on, passes_through, registry_flag
from .memory import TRACE_BATCH
from .photons import Photons, empty_photons, encode_direction, spectrum_channels
from .props import segment_limit
from .scenes import check_scene, infinite_sphere, linear_part

log = logging.getLogger("mi_partpm")

__all__ = ["map_sizes", "map_seeds", "stream_seed", "trace_photons", "check_emitters", "emit",
           "Photons", "PATHS", "CAUSTIC_THROUGH", "STORE_ON"]

#: Which photons a tracing run stores: all of them, only caustic ones (L S+ D), or the rest.
PATHS = ("all", "caustic", "global")
#: Which bounces a caustic path makes before the surface it is stored on: "delta" (L S+ D,
#: S a mirror or glass, D the first non-delta surface) or "glossy" (S a delta or glossy lobe,
#: D the first surface with a diffuse lobe; for eye paths that trace glossy surfaces on).
CAUSTIC_THROUGH = ("delta", "glossy")
#: Where photons are stored (``store_on`` of :func:`trace_photons`): every surface with a
#: non-delta lobe, or only those with a diffuse lobe.
STORE_ON = ("smooth", "diffuse")


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

#: The share of Mitsuba's offset kept between a surface emitter and its photons' origin.
#: Mitsuba's area light starts its ray (1 + max|p|) 8.94 x 10^-5 off the surface along the
#: normal, as every spawned ray, about 1500 float32 steps of |p| where |p| is about 1: in a
#: scene 2 units wide at x = 1000 its photons left 9 cm below a light 1 cm under the ceiling,
#: and the walls next to the light were 0.15-0.45 of `path` (which samples points on the
#: light itself); in a scene of 2 mm, 0.75. A sixteenth keeps about 90 float32 steps:
#: rays from flat, box, cylinder and mesh lights found no hit on their own surface.
EMISSION_OFFSET_SHARE = 1 / 16

#: The most photon paths of one tracing run (their indices are 32-bit).
MAX_RUN = 0xFFFFFFFF

#: :func:`_emitter_table`'s kinds: power scaled by the direction's length, a rotated
#: environment map, a surface (area) emitter.
SCALED, ROTATED_ENVMAP, SURFACE = 1, 2, 3


def _emitter_table(scene: mi.Scene):
    """What :func:`emit` corrects per emitter: a UInt32 per emitter registry id, ``SCALED``
    where the photon power scales with |ray.d| (:data:`SCALED_BY_DIRECTION_LENGTH`),
    ``ROTATED_ENVMAP`` for a rotated environment map (:func:`_rotated_envmap`), ``SURFACE``
    for an emitter on a shape (:data:`EMISSION_OFFSET_SHARE`), 0 otherwise; that map's frame
    and sphere, or None; and whether any emitter is on a shape."""
    ids = dr.reinterpret_array(mi.UInt32, scene.emitters_dr()).numpy()
    table = np.zeros(int(ids.max()) + 1 if ids.size else 1, dtype=np.uint32)
    envmap = None
    for emitter, i in zip(scene.emitters(), ids):
        if emitter.class_name() in SCALED_BY_DIRECTION_LENGTH:
            table[i] = SCALED
        elif _on_surface(emitter):
            table[i] = SURFACE
        to_world = _envmap_turn(emitter)
        if to_world is not None:
            if not np.allclose(to_world, np.eye(3), atol=1e-7):
                table[i] = ROTATED_ENVMAP
                centre, radius = infinite_sphere(scene)
                envmap = (np.linalg.inv(to_world), [float(c) for c in centre], radius)
    return mi.UInt32(table), envmap, bool(np.any(table == SURFACE))


def _on_surface(emitter) -> bool:
    """Whether ``emitter`` lies on a shape (an area light): its photons leave from a point
    :func:`emit` samples again."""
    return mi.has_flag(emitter.flags(), mi.EmitterFlags.Surface)


def _envmap_turn(emitter):
    """An environment map's ``to_world`` without its translation (3 x 3, float64); None for
    any other emitter."""
    if emitter.class_name() != "EnvironmentMapEmitter":
        return None
    return linear_part(emitter.world_transform())


def _warn_if_scaled_envmap(emitter):
    """A warning where an environment map's ``to_world`` is more than a rotation."""
    to_world = _envmap_turn(emitter)
    if to_world is None or np.allclose(to_world @ to_world.T, np.eye(3), atol=1e-5):
        return
    log.warning("environment map %s has a to_world that is not a rotation (a scale): "
                "Mitsuba 3.9.1 then disagrees with itself (path's emitter samples grow "
                "brighter with the scale, its BSDF samples do not); the photons carry the "
                "unscaled map's light, so give the map a rotation only", _emitter_name(emitter))


def _rotated_envmap(ray, envmap):
    """Mitsuba 3.9's ``envmap`` emits a photon of direction d = M (-d_l) (M its ``to_world``)
    from a point of the disc perpendicular to d_l, not to d: where M turns d_l, the rays
    cross the scene's sphere through a disc tilted against them, whose shadow is smaller than
    the pi R^2 their power assumes (a rotated map lit the scene 1.4-4 times too brightly).
    The photon keeps its direction and its point's coordinates on the disc, and leaves from
    the disc perpendicular to d, as Mitsuba's unrotated map does (the same point then)."""
    inverse, centre, radius = envmap
    m = mi.Matrix3f(inverse.astype(np.float32).tolist())
    d_global = ray.d                  # M (-d_l), as Mitsuba made it (of M's scale's length)
    d = dr.normalize(d_global)
    local = dr.normalize(-(m @ d_global))
    rel = (ray.o - mi.Point3f(centre)) / radius + d_global
    frame = mi.Frame3f(local)
    offset = frame.to_local(rel)
    proper = mi.Frame3f(-d).to_world(mi.Vector3f(offset.x, offset.y, 0.0))
    return mi.Point3f(centre) + (proper - d) * radius


def emit(scene: mi.Scene, rng, photon_count: int, table, active=True):
    """Photon rays leaving the scene's emitters, with unit directions, and their power over
    ``photon_count`` (one emitter chosen per photon by the scene, as ``path`` does);
    ``table`` is :func:`_emitter_table`'s."""
    active = mi.Bool(active)
    pick = rng.next_float32()
    at = mi.Point2f(rng.next_float32(), rng.next_float32())     # the point on the emitter
    ray, weight, emitter = scene.sample_emitter_ray(
        mi.Float(0), pick, at, mi.Point2f(rng.next_float32(), rng.next_float32()), active)
    table, envmap, surfaces = table
    length = dr.norm(ray.d)
    kind = dr.gather(mi.UInt32, table, dr.reinterpret_array(mi.UInt32, emitter), active)
    power = mi.Spectrum(weight) * dr.select(kind == SCALED, length, 1.0) / \
        dr.opaque(mi.Float, float(photon_count))
    if envmap is not None:
        ray.o = dr.select(kind == ROTATED_ENVMAP, _rotated_envmap(ray, envmap), ray.o)
    if surfaces:
        # The scene hands the emitter its point sample unchanged: the same point again, from
        # which the origin keeps a share of Mitsuba's offset along the normal.
        surface = active & (kind == SURFACE)
        p = emitter.sample_position(0.0, at, surface)[0].p
        ray.o = dr.select(surface, dr.fma(ray.o - p, EMISSION_OFFSET_SHARE, p), ray.o)
    ray.d = ray.d / dr.select(length > 0, length, 1.0)
    return ray, power


def check_emitters(scene: mi.Scene, samples: int = 1024):
    """Refuse emitters whose power is NaN, infinite or negative, or that give light but are
    never sampled (``sampling_weight`` 0), before any photon is traced. Returns whether any
    emitter gives light (False: every test ray's power is 0).

    Each emitter emits ``samples`` test rays (stratified samples); Mitsuba accepts such
    values in a scene file, and the tracer would otherwise drop those photons silently.
    """
    check_scene(scene, needs_sensor=False)
    u = (np.arange(samples, dtype=np.float64) + 0.5) / samples
    rng = np.random.default_rng(0)
    s = [mi.Float(np.asarray(a, np.float32)) for a in (u, *rng.random((4, samples)))]
    lit = False
    for emitter in scene.emitters():
        name = _emitter_name(emitter)
        _warn_if_scaled_envmap(emitter)
        try:
            _, weight = emitter.sample_ray(0.0, s[0], mi.Point2f(s[1], s[2]),
                                           mi.Point2f(s[3], s[4]), True)
            w = np.atleast_2d(np.array(mi.Spectrum(weight)))
            if _on_surface(emitter):
                # emit() finds a surface emitter's point again (EMISSION_OFFSET_SHARE)
                emitter.sample_position(0.0, mi.Point2f(s[1], s[2]), True)
        except RuntimeError as e:
            reason = " ".join(str(e).split())
            hint = ("its radiance is a texture Mitsuba can evaluate but not sample emission "
                    "from (a procedural one, such as checkerboard): give it a bitmap texture"
                    if "not implemented" in reason else "photon mapping needs sample_ray")
            raise ValueError(f"emitter {name} cannot emit photons (Mitsuba: {reason}); "
                             f"{hint}") from None
        if not np.all(np.isfinite(w)):
            raise ValueError(f"emitter {name} emits non-finite power (NaN or inf): its "
                             f"radiance / intensity must be finite and >= 0")
        if np.any(w < 0):
            raise ValueError(f"emitter {name} emits negative power (down to {w.min():.4g}): "
                             f"its radiance / intensity must be finite and >= 0")
        if float(emitter.sampling_weight()) <= 0 and np.any(w > 0):
            raise ValueError(f"emitter {name} has sampling_weight = "
                             f"{float(emitter.sampling_weight()):g}: photons leave only from "
                             f"emitters the scene samples, so its light would be missing from "
                             f"the image; give it a sampling_weight > 0 (a weight changes only "
                             f"how many photons it emits, not its brightness)")
        lit = lit or bool(np.any(w > 0))
    return lit


def trace_photons(scene: mi.Scene, photon_count: int, map_count: int = 1, seed: int = 0,
                  max_depth: int = -1, rr_depth: int = 5, maps: Optional[Sequence[int]] = None,
                  min_bounce: int = 1, paths: str = "all", caustic_through: str = "delta",
                  progress: Optional[Callable[[str], None]] = None,
                  batch_size: int = TRACE_BATCH,
                  memory_check: Optional[Callable[[float, int], None]] = None,
                  caustic_past_landings: bool = False, store_on: str = "smooth",
                  bent_bsdfs="find") -> Photons:
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
        ends the paths; 0: no photon).
    rr_depth : int
        Segment count from which Russian roulette may end a path.
    maps : sequence of int, optional
        Trace only these maps (a rank of a distributed job); default all.
    min_bounce : int
        Store photons from this many segments on (2 leaves out direct illumination).
    paths : str
        Which photons to store (:data:`PATHS`): "all"; "caustic", only the photons that
        reached their first non-delta surface through one or more delta bounces (L S+ D;
        the path ends there); "global", all the others, so that a global and a caustic map
        together hold every photon once.
    caustic_through : str
        What a caustic path bounces on (:data:`CAUSTIC_THROUGH`): "delta" (the above) or
        "glossy": delta or glossy lobes, up to the first surface with a diffuse lobe (L
        {S|G}+ D), the caustics of eye paths that trace their glossy surfaces on.
    progress : callable(str), optional
        Receives a line per batch.
    batch_size : int
        Photon paths traced together at most; more run in batches (same photons). A run
        of more than ``batch_size // 16`` paths (at least 1024) traces a pilot of at most
        8192 of them first, which measures how many photons a path stores, so that the
        batches size their buffers; the first batch traces the pilot's paths again and
        keeps them.
    memory_check : callable(stored_per_emitted, traced), optional
        Called after the pilot and after each batch but the last with the measured photons
        stored per photon emitted and the photons traced for it; it may raise to stop
        before memory runs out.
    caustic_past_landings : bool
        A path that leaves a surface it could be stored on (one with a non-delta lobe) by a
        delta lobe (a mask's pass-through, plastic's coat) stays a caustic one. Final
        gathering needs it: its rays go on through such lobes and its visible points read
        no global map. Otherwise such light stays in the global maps, denser than the
        caustic ones.
    store_on : str
        Where photons are stored (:data:`STORE_ON`): on every surface with a non-delta lobe
        ("smooth"), or only on those with a diffuse lobe ("diffuse": where eye paths trace
        glossy surfaces on, no estimate reads a photon on one, and within the radius of a
        surface it touches it was counted there: rough glass resting on a floor made the
        floor 1.6 times too bright around the contact).
    bent_bsdfs : mi.UInt32 or None or "find"
        The scene's BSDFs that look plain diffuse but bend their normal inside (``normalmap``,
        ``bumpmap``), as :func:`~mi_partpm.estimate.note_bent_bsdfs` finds them (its device
        table, :func:`~mi_partpm.estimate.bent_table`; None: none is); "find" (default):
        found here, with ``note_bent_bsdfs``, which also sets the table the estimate reads
        (for this scene). A photon that bounces off one is corrected for the normal it bends
        to (:func:`bent_normal`).

    Returns
    -------
    Photons
        Stored photons on the device, ``emitted == photon_count`` whichever maps were traced.
    """
    check_emitters(scene)
    if paths not in PATHS:
        raise ValueError(f"paths must be one of {', '.join(PATHS)}, got {paths!r}")
    if caustic_through not in CAUSTIC_THROUGH:
        raise ValueError(f"caustic_through must be one of {', '.join(CAUSTIC_THROUGH)}, got "
                         f"{caustic_through!r}")
    if store_on not in STORE_ON:
        raise ValueError(f"store_on must be one of {', '.join(STORE_ON)}, got {store_on!r}")
    sizes = map_sizes(photon_count, map_count)
    maps = np.arange(map_count) if maps is None else np.asarray(list(maps), dtype=np.int64)
    max_depth = segment_limit(max_depth)
    n_lanes = int(sizes[maps].sum())
    if n_lanes == 0 or max_depth < 1 or not scene.shapes():    # (no shape: every photon escapes)
        return empty_photons(photon_count, map_count)
    if n_lanes > MAX_RUN:
        raise ValueError(f"a tracing run has at most 2^32 - 1 photons, got {n_lanes} (trace "
                         f"the maps in several runs: maps=...)")
    if isinstance(bent_bsdfs, str) and bent_bsdfs == "find":
        # Here, not at the top: the estimate's module needs a variant set when imported,
        # and the command line imports this one before it sets one.
        from .estimate import bent_table, note_bent_bsdfs
        note_bent_bsdfs(scene)
        bent_bsdfs = bent_table()
    run = _Run(scene, photon_count, map_seeds(seed, map_count), max_depth, rr_depth,
               min_bounce, PATHS.index(paths), caustic_through == "glossy",
               caustic_past_landings, maps, sizes[maps], store_on == "diffuse", bent_bsdfs)
    # A run of up to ``batch_size // PILOT_SHARE`` paths is one batch with room for
    # PILOT_GUESS photons per path. A longer run traces a pilot of a few thousand paths
    # first, which measures the photons stored per path before the batches size their
    # buffers: a buffer too small for a batch means tracing that batch again (a scene of
    # white walls stores 7 photons per path, the Cornell box 3). The pilot's photons are
    # traced again by the first batch, so that a run of one batch hands its photons over as
    # they come, with no copy into a run of several batches.
    direct = min(batch_size, max(PILOT_MIN, batch_size // PILOT_SHARE))
    pilot = min(direct, PILOT_MAX)
    per_lane = float(min(max_depth, PILOT_GUESS))
    if n_lanes > direct:
        stored, _ = run.batch(0, pilot, per_lane, keep=False)
        per_lane = max(stored / pilot, 0.05)
        if memory_check is not None:
            memory_check(stored / pilot, pilot)
    batches, segments, stored = [], 0, 0
    for first in range(0, n_lanes, batch_size):
        # Batches only bound the memory: every lane's random stream depends on its (map,
        # index in the map) alone, so the photons are the same for any batch size.
        done = min(first + batch_size, n_lanes)
        photons, traced = run.batch(first, done - first, per_lane)
        batches.append(photons)
        segments += traced
        stored += len(photons)
        per_lane = max(stored / done, 0.05)
        if memory_check is not None and done < n_lanes:
            memory_check(stored / done, done)
        if progress is not None and n_lanes > batch_size:
            progress(f"batch: {done} of {n_lanes} photons traced, {stored} stored")
    photons = _concat(batches, photon_count, map_count)
    photons.segments = segments
    return photons


#: A run of at most ``batch_size // PILOT_SHARE`` paths (at least ``PILOT_MIN``) is traced
#: in one batch with room for ``PILOT_GUESS`` stored photons per path (47 MB of slots and
#: bounce words for the 2^16 paths of the default batch size); a longer one measures a pilot
#: of at most ``PILOT_MAX`` of its paths first (6 MB for 2^13).
PILOT_SHARE, PILOT_MIN, PILOT_MAX, PILOT_GUESS = 16, 1024, 1 << 13, 16


class _Run:
    """What every batch of one tracing run shares."""

    def __init__(self, scene, photon_count, seeds, max_depth, rr_depth, min_bounce, paths,
                 through_glossy=False, past_landings=False, maps=(0,), sizes=None,
                 store_diffuse=False, bent=None):
        self.scene, self.photon_count = scene, photon_count
        self.bent = bent                          # device table by registry id, or None
        self.seeds = mi.UInt64(seeds)
        self.max_depth, self.rr_depth, self.min_bounce = max_depth, rr_depth, min_bounce
        self.paths, self.through_glossy = paths, through_glossy
        self.store_diffuse = store_diffuse
        self.past_landings = past_landings
        self.table = _emitter_table(scene)
        # The run's paths, the traced maps' photons one map after another: path l is photon
        # l - starts[k] of map maps[k], for the k with starts[k] <= l < ends[k].
        maps = np.asarray(maps, dtype=np.int64)
        sizes = np.ones_like(maps) if sizes is None else np.asarray(sizes, dtype=np.int64)
        ends = np.cumsum(sizes)
        self.map_total = int(maps.shape[0])
        self.maps = mi.UInt32(maps.astype(np.uint32))
        self.ends = mi.UInt32(ends.astype(np.uint32))
        self.starts = mi.UInt32((ends - sizes).astype(np.uint32))

    def map_and_index(self, path, active=True):
        """The map of each of the run's ``path`` indices and its photon's index in that map
        (on the device: a branch-free binary search over the traced maps' ends)."""
        k = dr.zeros(mi.UInt32, dr.width(path))
        count = self.map_total
        while count > 1:                          # the first k with ends[k] > path
            half = count // 2
            k = dr.select(dr.gather(mi.UInt32, self.ends, k + (half - 1), active) <= path,
                          k + half, k)
            count -= half
        if self.map_total > 1:
            k += dr.select(dr.gather(mi.UInt32, self.ends, k, active) <= path, 1, 0)
        return (dr.gather(mi.UInt32, self.maps, k, active),
                path - dr.gather(mi.UInt32, self.starts, k, active))

    def batch(self, start: int, photons: int, per_lane: float, keep: bool = True):
        """Trace the run's paths ``start .. start + photons - 1``; returns (photons, ray
        segments traced), or with ``keep`` False (a pilot) (photons stored, segments)."""
        slot_run = claim_runs()[1]
        capacity = _round_up(max(1024, int(photons * per_lane * 1.25))
                             + run_slack(lane_count(photons), slot_run), slot_run)
        ranked = True
        while True:
            out, counts, too_deep, runs, segments = self._kernel(start, photons, capacity,
                                                                 ranked)
            used = int(runs[0]) * slot_run        # slots in the runs the lanes claimed
            if ranked and int(too_deep[0]) > 0:
                ranked = False                    # a bounce count did not fit beside a rank
            elif used <= capacity:
                break
            # Trace again with room for every run claimed (how many runs end part full
            # depends on how the threads ran: with runs, a tenth more).
            capacity = max(capacity, _round_up(used + (used // 10 if slot_run > 1 else 0),
                                               slot_run))
        if not keep:
            fill = out[2]
            stored = used if slot_run == 1 or used == 0 else int(dr.sum(dr.gather(
                mi.UInt32, fill, dr.arange(mi.UInt32, used // slot_run)))[0])
            return stored, int(segments[0])
        if used == 0:
            return empty_photons(self.photon_count, 0), int(segments[0])
        # The slots were claimed in whatever order the threads ran: put the photons in the
        # order of the batch's photons, and a photon's in bounce order, so that every run
        # hands the same arrays to the build. A photon's first slot in that order is the
        # prefix sum of the photons stored per photon before it, and each stored photon
        # carries its rank among its photon's: one scatter gives the order, no sort.
        # Each buffer is freed once read: the batch's peak is its slots and the photons in
        # photon order (one packet gather cannot read half a slot).
        slots, bounces, fill = out
        out.clear()
        # The slots written: each run's first ``fill`` (every run full with runs of one).
        index = dr.arange(mi.UInt32, used)
        if slot_run > 1:
            index = dr.compress(index % slot_run < dr.gather(mi.UInt32, fill, index // slot_run))
        del fill
        stored = dr.width(index)
        photon_of = dr.reinterpret_array(mi.UInt32, dr.gather(
            mi.Float, slots, SLOT_FLOATS * index + SLOT_FLOATS - 1))
        if ranked:
            if int(dr.sum(counts)[0]) != stored:     # every slot has a place of its own
                raise RuntimeError(f"tracer: {int(dr.sum(counts)[0])} photons counted per "
                                   f"path but {stored} stored")
            first = dr.prefix_sum(counts)             # exclusive
            del counts
            place = dr.gather(mi.UInt32, first, photon_of) + (
                dr.gather(mi.UInt32, bounces, index) >> RANK_SHIFT)
            keep = dr.empty(mi.UInt32, stored)
            dr.scatter(keep, index, place)
            del first, place
        else:
            # Stable, and a lane's runs are claimed in order: a photon's slots in bounce order.
            keep = dr.gather(mi.UInt32, index, dr.argsort(photon_of))
        del photon_of, index
        bounce = dr.gather(mi.UInt32, bounces, keep)
        if ranked:
            bounce &= (1 << RANK_SHIFT) - 1
        dr.eval(bounce)
        del bounces
        rec = dr.gather(_array_xf(), slots, keep, shape=(SLOT_FLOATS, stored))
        dr.eval(rec)
        del slots, keep
        channels = spectrum_channels()
        flux = mi.Spectrum(*[rec[4 + c] for c in range(channels)])
        photon = dr.reinterpret_array(mi.UInt32, rec[SLOT_FLOATS - 1])
        maps = self.map_and_index(photon + dr.opaque(mi.UInt32, start))[0]
        photons = Photons(mi.Point3f(rec[0], rec[1], rec[2]),
                          dr.reinterpret_array(mi.UInt32, rec[3]), flux, maps, bounce,
                          emitted=self.photon_count, map_count=0)
        dr.eval(photons.points, photons.code, photons.flux, photons.maps, photons.bounces)
        return photons, int(segments[0])

    def _kernel(self, start, photons, capacity, ranked):
        # Uninitialised: only the slots the kernel writes are read. Every run of slots is
        # full but a lane's last, whose fill the lane writes when it is done.
        slot_run = claim_runs()[1]
        out = [dr.empty(mi.Float, SLOT_FLOATS * capacity), dr.empty(mi.UInt32, capacity),
               dr.full(mi.UInt32, slot_run, capacity // slot_run) if slot_run > 1 else None]
        counts = dr.zeros(mi.UInt32, photons) if ranked else None
        runs = dr.zeros(mi.UInt32, 1)              # runs of slots claimed
        # Stored photons whose bounce count does not fit beside their rank.
        too_deep = dr.zeros(mi.UInt32, 1) if ranked else None
        # Recording the loop once instead of twice (the loop optimisation's second recording)
        # saves about 0.2 s a call; the kernel is the same.
        with dr.scoped_set_flag(dr.JitFlag.OptimizeLoops, False):
            segments = _trace_paths(self, start, photons, out, runs, capacity,
                                    lane_count(photons), counts, too_deep)
        total = dr.sum(segments)
        dr.eval([a for a in out if a is not None], counts, too_deep, runs, total)
        return out, counts, too_deep, runs, total


#: A stored photon's bounce count and its rank among its photon's stored photons share one
#: 32-bit word: the bounce count in the low RANK_SHIFT bits. A batch that stores a photon
#: after 2^RANK_SHIFT bounces or more (Russian roulette makes that all but impossible) is
#: traced again without ranks and sorted instead.
RANK_SHIFT = 16

#: Floats of a stored photon's slot in the tracer's buffer: x, y, z, direction code, power
#: (3 channels, or 1 and 2 unused), the photon's index in its batch (as float bits).
SLOT_FLOATS = 8


def _array_xf():
    """The variant's dynamic-size float array type (of its backend: LLVM or CUDA)."""
    return getattr(sys.modules[mi.Float.__module__], "ArrayXf")


def _slot(position, code, flux, photon):
    """A stored photon's slot as two 4-float packets (see :data:`SLOT_FLOATS`)."""
    f = [flux[c] for c in range(spectrum_channels())]
    f += [dr.zeros(mi.Float, dr.width(f[0]))] * (3 - len(f))
    return (mi.Vector4f(position.x, position.y, position.z,
                        dr.reinterpret_array(mi.Float, code)),
            mi.Vector4f(f[0], f[1], f[2], dr.reinterpret_array(mi.Float, photon)))


#: Photon paths per tracer lane, on average: a lane whose path ends takes the next photon of
#: the batch, so SIMD lanes stay busy while Russian roulette ends paths at different depths.
PHOTONS_PER_LANE = 4


#: Claims per lane on the LLVM backend: photons in runs of 16 (64 bytes of the per-photon
#: counts) and stored-photon slots in runs of 64, so that the two threads of a 2-core machine
#: neither contend for the claim counters at every bounce nor write to the same cache lines
#: (the Cornell box's kernel on 2 threads against 1: 1.6x faster with a claim per photon and
#: per stored photon, 1.95x with runs; 227 against 283 ms for 10^6 photons). On CUDA every
#: lane of thousands runs at once and claims one of each (the runs would leave a part-full
#: run of slots per lane).
PHOTON_RUN, SLOT_RUN = 16, 64


def claim_runs() -> tuple:
    """(photons, slots) a tracer lane claims at once on the variant's backend."""
    if dr.backend_v(mi.Float) == dr.JitBackend.CUDA:
        return 1, 1
    return PHOTON_RUN, SLOT_RUN


def _next_in_run(counter, take, next_, end, run: int):
    """Where ``take``, each lane takes the next index of its run ``[next_, end)``, claiming
    the next run of ``run`` indices from ``counter`` (``dr.scatter_inc``) once its run is
    used up. Returns (the index taken, the new next, the new end)."""
    refill = take & (next_ >= end)
    start = dr.scatter_inc(counter, mi.UInt32(0), refill) * run
    index = dr.select(refill, start, next_)
    return index, index + dr.select(take, 1, 0), dr.select(refill, start + run, end)


def _round_up(x: int, step: int) -> int:
    return -(-int(x) // step) * step


#: Lanes that may be at work at once in a batch, at most, for the room of their part-full
#: runs of slots: on the LLVM backend a packet per thread (16 lanes on AVX-512), so 1024
#: covers 64 threads; beyond, a batch is traced again at worst.
WORKING_LANES = 1024


def run_slack(lanes: int, slot_run: int) -> int:
    """Slots a batch's buffer holds beyond its stored photons: the unused end of the last
    run of each lane at work (none with runs of one slot)."""
    return 0 if slot_run == 1 else min(int(lanes), WORKING_LANES) * (slot_run - 1)


def lane_count(photons: int) -> int:
    """Lanes that trace a batch of ``photons`` paths (each lane takes photons in turn)."""
    return max(1, -(-int(photons) // PHOTONS_PER_LANE))


def shading_correction(si, wi):
    """The adjoint BSDF's correction for shading normals at a stored photon (Veach 1997,
    as Mitsuba 0.6 applies it at the last bounce): |wi . n_s| / |wi . n_g|. Exactly 1 where
    the shading normal is the geometric one; 1 where the photon grazes the geometry
    (|wi . n_g| < 1e-3), which the correction would blow up."""
    cos_g = dr.abs(dr.dot(wi, si.n))
    cos_s = dr.abs(dr.dot(wi, si.sh_frame.n))
    return dr.select(cos_g > 1e-3, cos_s / dr.select(cos_g > 1e-3, cos_g, 1.0), 1.0)


def adjoint_correction(si, wi, wo, n_s=None):
    """The adjoint BSDF's correction for shading normals at a photon's bounce (Veach 1997,
    section 5.3; as Mitsuba's light tracer ``ptracer`` applies it): |wi . n_s| |wo . n_g| /
    (|wi . n_g| |wo . n_s|), with ``wi`` towards the light and ``wo`` the sampled direction,
    and 0 where either lies on different sides of the geometric and the shading surface (a
    light leak). Exactly 1 where the shading normal is the geometric one. Without it, on a
    box with smooth vertex normals the light that bounced off it came out up to 1.18 of
    path's (a box of six faces in a scene written elsewhere); Mitsuba gives smooth normals
    to every OBJ and PLY mesh without normals of its own unless ``face_normals`` is set.
    The geometric normal is turned to the shading normal's side first: its way is the
    triangles' winding, which a mirroring ``to_world`` or a mesh wound the other way turns
    against its vertex normals, and then every direction lay on "different sides" (a room
    with a box mirrored by its transform stored 0.74 of the photons and 0.89 of the power it
    stored with the box unmirrored). ``n_s``: the shading normal, where the BSDF shades
    with another than Mitsuba's (:func:`bent_normal`)."""
    n_s = si.sh_frame.n if n_s is None else n_s
    n_g = si.n * dr.select(dr.dot(si.n, n_s) < 0, -1.0, 1.0)
    wi_g, wo_g = dr.dot(wi, n_g), dr.dot(wo, n_g)
    wi_s, wo_s = dr.dot(wi, n_s), dr.dot(wo, n_s)
    factor = dr.abs(wi_s * wo_g) / dr.abs(wi_g * wo_s)
    leak = (wi_g * wi_s <= 0) | (wo_g * wo_s <= 0)
    return dr.select(leak | ~dr.isfinite(factor), 0.0, factor)


#: The directions :func:`bent_normal` evaluates a BSDF in lean this far from Mitsuba's
#: shading normal (radians): it finds normals bent by up to 90 degrees less this.
PROBE_LEAN = 0.5


def bent_normal(si, bsdf, active):
    """The normal a Lambertian BSDF that bends it inside (``normalmap`` or ``bumpmap`` around
    ``diffuse``) shades with at ``si``, in world space, found from three evaluations: for
    directions d_k leaning :data:`PROBE_LEAN` from the shading normal (on ``si.wi``'s side:
    ``twosided`` turns a hit from behind to its front) at azimuths t_k = 0, 120 and 240
    degrees, the BSDF gives k max(0, d_k . n), and where all three are positive, their sums
    weighted by cos t_k, by sin t_k and by 1 give n's three components up to k. Here k is
    albedo / pi summed over the channels, times Mitsuba 3.9's shadowing term for bent
    normals (Estevez et al. 2019), which depends on a direction's angle to the shading
    normal alone: the probes share that angle, so they share the term. Mitsuba's shading
    normal where they are not all positive (a normal bent further than 90 degrees less the
    lean, or an albedo of 0). The plugins keep the normal to themselves; without it a
    photon that bounced off a constant 37-degree normal map was corrected for the wrong
    normal. Exact for any Lambertian BSDF (its own shading normal), so a plain one taken as
    bent costs the three evaluations and changes nothing."""
    ctx = mi.BSDFContext()
    s, c = float(np.sin(PROBE_LEAN)), float(np.cos(PROBE_LEAN))
    side = dr.select(mi.Frame3f.cos_theta(si.wi) < 0, -1.0, 1.0)
    cos_t = [float(np.cos(2.0 * np.pi * k / 3.0)) for k in range(3)]
    sin_t = [float(np.sin(2.0 * np.pi * k / 3.0)) for k in range(3)]
    v = [dr.sum(mi.Spectrum(bsdf.eval(ctx, si, mi.Vector3f(s * ck, s * sk, side * c), active)))
         for ck, sk in zip(cos_t, sin_t)]
    # sum_k v_k cos t_k = 3/2 k s n_x, the same with sines for n_y; sum_k v_k = 3 k c |n_z|.
    local = dr.normalize(mi.Vector3f(2.0 * sum(vk * ck for vk, ck in zip(v, cos_t)) / s,
                                     2.0 * sum(vk * sk for vk, sk in zip(v, sin_t)) / s,
                                     side * (v[0] + v[1] + v[2]) / c))
    found = (v[0] > 0) & (v[1] > 0) & (v[2] > 0)
    return dr.select(found, si.to_world(local), si.sh_frame.n)


@dr.syntax
def _trace_paths(run, first, photon_total, out, runs, capacity, width, counts=None,
                 too_deep=None):
    """The bounce loop of one batch (one kernel): take a photon, store, scatter, roulette.

    ``width`` lanes share the batch's photons (the run's paths ``first`` and on): a
    lane whose path has ended takes the next photon of its run (claiming a run with
    ``dr.scatter_inc`` when its run is used up) and starts it from its own random stream
    (map, index), so a photon is the same whichever lane traces it, and a SIMD packet does
    not wait for its longest path. A stored photon takes the next slot of its lane's run of
    slots the same way; ``runs`` counts the runs claimed and ``out`` holds the slots, the
    bounce words and, with runs longer than one, each run's fill. With ``counts`` (one per
    photon), each photon's count of stored photons goes there once its path has ended, and
    each stored photon's rank among them goes beside its bounce count (:data:`RANK_SHIFT`);
    ``too_deep`` counts the stored photons whose bounce count does not fit there.
    Returns the segments each lane traced."""
    scene = run.scene
    slots, bounces, fill = out
    ctx = mi.BSDFContext(mi.TransportMode.Importance)
    photons = dr.opaque(mi.UInt32, photon_total)
    path_base = dr.opaque(mi.UInt32, first)
    queue = dr.zeros(mi.UInt32, 1)
    rng = mi.PCG32(width)
    ray = dr.zeros(mi.Ray3f, width)
    power = dr.zeros(mi.Spectrum, width)
    photon = dr.zeros(mi.UInt32, width)          # the batch index of the lane's photon
    rank = dr.zeros(mi.UInt32, width)            # photons the lane's photon stored so far
    ranked = counts is not None
    active = dr.full(mi.Bool, False, width)      # the lane's photon is still travelling
    finished = dr.full(mi.Bool, False, width)    # no photon left for the lane
    bounce = dr.zeros(mi.UInt32, width) + 1
    segments = dr.zeros(mi.UInt32, width)
    depth_limit = dr.opaque(mi.UInt32, run.max_depth)
    rr_from = dr.opaque(mi.UInt32, run.rr_depth)
    store_from = dr.opaque(mi.UInt32, run.min_bounce)
    room = dr.opaque(mi.UInt32, capacity)       # a multiple of the run of slots
    paths, through_glossy, store_diffuse = run.paths, run.through_glossy, run.store_diffuse
    past_landings = bool(run.past_landings)
    delta_only = dr.full(mi.Bool, True, width)   # every bounce so far was delta (or glossy)
    photon_run, slot_run = claim_runs()
    photon_next = dr.zeros(mi.UInt32, width)     # the lane's run of photons: next, end
    photon_end = dr.zeros(mi.UInt32, width)
    slot_next = dr.zeros(mi.UInt32, width)       # the lane's run of slots: next, end
    slot_end = dr.zeros(mi.UInt32, width)
    while dr.hint(~finished, label="partpm_trace"):
        # Lanes without a photon take the next one of their run of photons, and a lane whose
        # run is used up claims the next run; none left: the lane is done.
        need = ~active & ~finished
        if dr.hint(ranked, mode="scalar"):
            dr.scatter(counts, rank, photon, need & (rank > 0))   # the photon that ended
        claim, photon_next, photon_end = _next_in_run(queue, need, photon_next, photon_end,
                                                      photon_run)
        fresh = need & (claim < photons)
        done = need & ~fresh
        finished |= done
        # A lane that is done leaves its last run of slots part full: say how full.
        if dr.hint(slot_run > 1, mode="scalar"):
            dr.scatter(fill, slot_next - (slot_end - slot_run), slot_end // slot_run - 1,
                       done & (slot_end > 0) & (slot_end <= room))
        if fresh:
            start = mi.PCG32(width)
            map_id, index = run.map_and_index(claim + path_base, fresh)
            start.seed(dr.gather(mi.UInt64, run.seeds, map_id, fresh), mi.UInt64(index))
            new_ray, new_power = emit(scene, start, run.photon_count, run.table, fresh)
            rng = dr.select(fresh, start, rng)
            ray = dr.select(fresh, new_ray, ray)
            power = dr.select(fresh, new_power, power)
            photon = dr.select(fresh, claim, photon)
            bounce = dr.select(fresh, 1, bounce)
            rank = dr.select(fresh, 0, rank)
            delta_only |= fresh
            active = fresh & dr.any(power != 0) & dr.all(dr.isfinite(power))

        si = scene.ray_intersect(ray, active)
        segments += dr.select(active, 1, 0)
        active &= si.is_valid()
        bsdf = si.bsdf()
        flags = bsdf.flags()
        # Where a caustic path ends: its first non-delta surface, or with glossy bounces its
        # first surface with a diffuse lobe.
        lands = active & lands_on(flags, through_glossy)
        caustic = delta_only & (bounce >= 2) & lands    # L S+ D (or L {S|G}+ D)
        store = active & lands_on(flags, store_diffuse) & (bounce >= store_from)
        if dr.hint(paths == 1, mode="scalar"):
            store &= caustic
        elif dr.hint(paths == 2, mode="scalar"):
            store &= ~caustic
        # A stored photon takes the next slot of its lane's run of slots; a lane whose run is
        # full claims the next run.
        slot, slot_next, slot_end = _next_in_run(runs, store, slot_next, slot_end, slot_run)
        write = store & (slot < room)
        head, tail = _slot(si.p, encode_direction(-ray.d),
                           power * shading_correction(si, -ray.d), photon)
        dr.scatter(slots, head, 2 * slot, write)          # packet stores (dr.JitFlag.PacketOps)
        dr.scatter(slots, tail, 2 * slot + 1, write)
        if dr.hint(ranked, mode="scalar"):
            dr.scatter(bounces, bounce | (rank << RANK_SHIFT), slot, write)
            rank += dr.select(store, 1, 0)
            dr.scatter_inc(too_deep, mi.UInt32(0), store & (bounce >= 1 << RANK_SHIFT))
        else:
            dr.scatter(bounces, bounce, slot, write)

        # The next segment: BSDF sampling, then Russian roulette on the throughput.
        active &= bounce < depth_limit
        bs, bsdf_weight = bsdf.sample(ctx, si, rng.next_float32(active),
                                      mi.Point2f(rng.next_float32(active),
                                                 rng.next_float32(active)), active)
        wo = si.to_world(bs.wo)
        n_s = si.sh_frame.n
        if dr.hint(run.bent is not None, mode="scalar"):
            bent = registry_flag(run.bent, bsdf, active)
            n_s = dr.select(bent, bent_normal(si, bsdf, bent), n_s)
        power *= bsdf_weight * adjoint_correction(si, -ray.d, wo, n_s)
        ray = si.spawn_ray(wo)
        # The lobes a caustic path may bounce on before the surface it is stored on; the path
        # is no caustic one after that surface, whichever of its lobes it left by (a plastic's
        # coat), since its caustic photon was stored there; with ``past_landings`` it stays
        # one where it left by a delta lobe (a mask's pass-through, the coat), for final
        # gathering: its rays go on through those lobes to the light only as caustics do.
        passed = lands & mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta) & past_landings
        delta_only &= passes_through(bs.sampled_type, through_glossy) & (~lands | passed)
        if dr.hint(paths == 1, mode="scalar"):
            active &= ~lands | passed                   # no caustic photon after this one
        active &= dr.any(power != 0) & dr.all(dr.isfinite(power))
        if bounce >= rr_from:
            q = dr.minimum(dr.max(bsdf_weight), 0.95)
            survive = rng.next_float32(active) < q
            active &= survive
            power = dr.select(survive, power / q, power)
        bounce += 1
    return segments


#: The per-photon fields of :class:`Photons`, in constructor order.
_FIELDS = ("points", "code", "flux", "maps", "bounces")


def _concat(batches, photon_count, map_count) -> Photons:
    """One :class:`Photons` of every batch's photons, in batch order."""
    batches = [b for b in batches if len(b)]
    if not batches:
        return empty_photons(photon_count, map_count)
    if len(batches) == 1:
        b = batches[0]
        return Photons(b.points, b.code, b.flux, b.maps, b.bounces, photon_count, map_count)
    sizes = [len(b) for b in batches]
    total = sum(sizes)
    # Field by field, each batch's copy dropped once moved: at most one field is held twice.
    merged = []
    for name in _FIELDS:
        target = dr.empty(type(getattr(batches[0], name)), total)    # every entry written
        offset = 0
        for b, size in zip(batches, sizes):
            slot = dr.arange(mi.UInt32, size) + dr.opaque(mi.UInt32, offset)
            dr.scatter(target, getattr(b, name), slot)
            dr.eval(target)
            offset += size
            setattr(b, name, None)
        merged.append(target)
    return Photons(*merged, emitted=photon_count, map_count=map_count)
