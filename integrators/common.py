"""What ``partpm`` and ``pm`` share: the photon-mapping integrator base, :class:`PhotonMapper`.

A render is a fixed sequence of phases, repeated once per pass (the paper's figure 4 is one
pass):

1. trace: the photons of the maps this process owns, from the streams of (seed, render seed,
   pass, map) (:mod:`mi_partpm.trace`);
2. build: the maps' kd-trees, groups of maps sharing split planes
   (:mod:`mi_partpm.photonmap`);
3. eye: one eye path per pixel sample, through delta bounces to its visible points
   (:mod:`mi_partpm.eyepath`, the camera of :mod:`mi_partpm.camera`);
4. estimate: the density estimate at every visible point, in Morton order
   (:mod:`mi_partpm.estimate`), summed onto its eye path;
5. gather: the backend sums the paths' flux and photon counts over the processes
   (:mod:`mi_partpm.backends`), and every path's statistics are updated
   (:mod:`mi_partpm.progressive`).

After the last pass each path's radiance goes into the film, as Mitsuba's own render loop
puts its samples. A subclass says which photon maps a pass builds (:class:`Layer`: the global
map, a caustic map) and which terms make up a path's radiance (:class:`Term`: an estimate at
the visible points, a final gather, each with what it accumulates over the passes), and reads
its own props (:meth:`PhotonMapper.read_estimator_props`). Where the maps run is the backend
object chosen once in the constructor; the phases never ask which one it is.
"""
from __future__ import annotations

import hashlib
import logging
import re
import threading
import time
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Callable

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_partpm import memory
from mi_partpm.backends import LocalBackend
from mi_partpm.camera import CameraPass, scene_sensor
from mi_partpm.estimate import bent_table, note_bent_bsdfs
from mi_partpm.eyepath import eye_paths
from mi_partpm.logs import follow_mitsuba_level
from mi_partpm.photonmap import build_photon_maps
from mi_partpm.props import UNLIMITED_DEPTH, read_bool, read_int, read_photon_map_params
from mi_partpm.timing import Heartbeat, Stopwatch
from mi_partpm.trace import check_emitters, map_sizes, stream_seed, trace_photons

log = logging.getLogger("mi_partpm")

#: A wave of several maps is planned again while it is traced once it needs more than this
#: share of the bytes its plan held it to (:meth:`PhotonMapper._tracing_guard`).
BUDGET_TOLERANCE = 1.05

#: ``passes`` of a render that runs passes until its ``time_limit``, given without ``passes``.
UNTIL_TIME_LIMIT = 2**31 - 1

__all__ = ["PhotonMapper", "Layer", "Term"]


#: The fewest eye samples of a set where a render splits its samples by itself to fit
#: (:meth:`PhotonMapper._fitting_split`): a set's kernels and its estimate cost the same
#: launches however few samples it has.
MIN_SET_SAMPLES = 1 << 16


def _scene_digest(scene) -> str:
    """A digest of what Mitsuba says of the scene's emitters and shapes (their radiance,
    transforms, BSDFs and sizes), for the processes of a render to compare: ranks that had
    loaded another copy of a scene file, with its light 4 times brighter, gave an image
    between the two in silence. Folders in file names and object addresses are left out:
    the same files may lie in other folders on other machines."""
    def clean(text: str) -> str:
        return re.sub(r"0x[0-9a-fA-F]+", "", re.sub(r"[^\s\"'\[\],=]*[/\\]", "", text))
    # Sorted: Mitsuba 3.9 lists a scene's shapes and emitters in another order from one load
    # of the same file to the next (4 orders of the Cornell box in 40 loads).
    text = "\n".join(sorted(clean(str(o)) for o in
                            list(scene.emitters()) + list(scene.shapes())))
    return hashlib.sha1(text.encode()).hexdigest()[:16]


def _radiance(terms):
    """The photon maps' radiance of every eye path: the sum of the terms'."""
    total = terms[0].state.radiance()
    for term in terms[1:]:
        total = total + term.state.radiance()
    return total


def _as_int(seed) -> int:
    """``render()``'s seed as a Python int (Mitsuba may pass a 1-wide ``UInt32``)."""
    return seed if isinstance(seed, int) else int(dr.ravel(mi.UInt32(seed))[0])


def _wait_for_background_tasks():
    """Let the tasks Mitsuba still runs in the background (an image that
    mi.util.write_bitmap writes asynchronously) end first: a Dr.Jit call of our Python code
    that waits for the thread pool holds the interpreter lock, which such a task may need,
    and the two would wait for each other for ever."""
    mi.Thread.wait_for_tasks()


@dataclass
class Layer:
    """A set of n partitioned photon maps rebuilt every pass: the global maps or the
    caustic maps. ``paths`` says which photons they keep (:data:`mi_partpm.trace.PATHS`);
    ``salt`` keeps their streams apart from other layers'."""

    name: str
    photon_count: int
    paths: str = "all"
    salt: int = 0
    maps: object = None
    stored: int = 0


@dataclass
class Term:
    """A part of every eye path's radiance: ``compute(points, width)`` returns this pass's
    (flux, photons found) per path, summed over the maps of this process; the backend sums
    them over the processes and ``state`` (:mod:`mi_partpm.progressive`) accumulates them."""

    name: str
    state: object
    compute: Callable


def _maps_text(wave) -> str:
    """A wave's maps for a progress line: one map, a range, or a rank's every P-th."""
    if len(wave) == 1:
        return f"map {wave[0]}"
    if wave[-1] - wave[0] == len(wave) - 1:
        return f"maps {wave[0]}-{wave[-1]}"
    return f"{len(wave)} maps of {wave[0]}-{wave[-1]}"


def _small_scene_hint(scene) -> str:
    """Where a scene is tiny (under 0.01 across), the likelier cause of photons that land
    nowhere: Mitsuba offsets rays by an epsilon that is not small against a scene 10^-4
    across (its own light tracer finds no surface there either)."""
    from mi_partpm.scenes import scene_size
    longest = scene_size(scene)
    if not 0 < longest < 1e-2:
        return ""
    return (f", or it is too small ({longest:.2g} across) for Mitsuba's ray offsets, which "
            f"then step over its surfaces (scale it up with a to_world scale)")


class PhotonMapper(mi.SamplingIntegrator):
    """Base of the photon-mapping integrators (see the module's text)."""

    #: Whether the plugin takes ``radius`` / ``radius_fraction`` (a fixed search radius).
    fixed_radius = True
    #: Whether the plugin takes ``passes`` and ``time_limit`` (progressive photon mapping).
    progressive = True

    def __init__(self, props=None):
        if props is not None and "hide_emitters" in props:
            # Mitsuba's base class reads it first, with a message that gives no value.
            read_bool(props, "hide_emitters", False)
        super().__init__(props if props is not None else mi.Properties())
        self.radius = None
        self._layers = []
        self._stored_per_emitted = {}
        self.maps_per_wave, self.wave_bytes, self.wave_index = 0, None, 0
        self._pass_seed = 0
        self.stats = {}
        self.passes, self.alpha, self.time_limit = 1, 0.7, 0.0
        self.on_pass = None
        #: Called after every pass of a progressive render: True stops it there, as the time
        #: limit does (the command line's first Ctrl-C); the image has the passes so far.
        self.stop_requested = None
        self._cancelled = False
        self._lit = True           # whether the last render's emitters give light
        self._planned_budget = None  # the bytes plan_waves held a wave to
        # (scene, seed) of the last render(), for the sample() calls that Mitsuba's aov
        # makes right after it (see :meth:`sample`)
        self._last_render = None
        # The maps, radius and statistics of a render are the integrator's: a render (or a
        # wrapper's sample()) from a second thread waits for the one in progress to end.
        self._busy = threading.RLock()
        self.params = read_photon_map_params(props, fixed_radius=self.fixed_radius)
        self.map_count = 1
        self.backend = LocalBackend()
        self.read_estimator_props(props)
        #: Eye samples per pixel traced at once by a render of one pass (0: all of them):
        #: Mitsuba's ``samples_per_pass``, which splits path's samples into passes.
        self.samples_per_pass = 0
        if props is not None and "samples_per_pass" in props:
            self.samples_per_pass = read_int(props, "samples_per_pass", 0, low=1)
            if self.passes > 1:
                log.warning("samples_per_pass = %d is not used: %s with passes > 1 traces "
                            "every sample of a pass at once (its passes are photon passes, "
                            "each with spp samples per pixel: lower spp to trace fewer at "
                            "once)", self.samples_per_pass, type(self).__name__)

    # ------------------------------------------------------------------ for subclasses

    def read_estimator_props(self, props):
        """Read and check the props of this estimator (may set ``map_count``, ``backend``,
        ``passes``, ``alpha``, ``time_limit``)."""

    def search_radius(self, scene: mi.Scene):
        """The (initial) search radius of the estimate (None: chosen per query)."""
        return None

    def layers(self) -> list:
        """The photon maps every pass builds (:class:`Layer`); by default the global maps."""
        return [Layer("global", self.params.photon_count)]

    def terms(self, layers: list, width: int, scene: mi.Scene) -> list:
        """The parts of an eye path's radiance (:class:`Term`) for a wavefront of
        ``width`` paths, made once per render."""
        raise NotImplementedError

    def before_estimate(self):
        """Called once the first maps are built, before the first estimate."""

    def after_estimate(self):
        """Called after the last pass: read statistics gathered during the estimates."""

    # ------------------------------------------------------------------ phases

    def build_maps(self, scene: mi.Scene, layer: Layer = None, sensor=0, spp: int = 0,
                   render_seed: int = 0, pass_index: int = 0, maps=None, budget=None):
        """Phases 1 and 2 for one layer (default: the first, the global maps): trace the
        photons of ``maps`` (default: every map this process owns) and build their kd-trees;
        ``layer.maps`` holds them until the next wave, and they are returned.

        ``sensor`` and ``spp`` (0: the sensor's sampler's) size the eye pass for the memory
        guard; ``render_seed`` and ``pass_index`` select the photon streams with the ``seed``
        prop (:func:`~mi_partpm.trace.stream_seed`); ``budget``: the bytes a wave of several
        maps is held to while it is traced (:class:`~mi_partpm.memory.WaveOverBudget`
        otherwise; default none, only the free memory).
        """
        p = self.params
        if layer is None:
            if self.radius is None:
                self.radius = self.search_radius(scene)
            self._layers = self.layers()
            layer = self._layers[0]
        owned = self.backend.owned_maps(self.map_count)
        maps = owned if maps is None else np.asarray(maps, dtype=np.int64)
        traced_here = int(map_sizes(layer.photon_count, self.map_count)[maps].sum())
        bounded = p.max_depth != UNLIMITED_DEPTH
        guard = self._tracing_guard(scene, sensor, spp, maps, layer, budget)
        beat = Heartbeat()

        def traced(line):               # a line of the trace's batches, every 10 s at info
            elapsed = beat.due()
            if elapsed is None:
                log.debug("trace: %s", line)
            else:
                log.info("trace: %s, %.0f s", line, elapsed)
        clock = Stopwatch()
        layer.maps = None           # the last wave's maps are freed before the next are traced
        photons = trace_photons(scene, layer.photon_count, self.map_count,
                                stream_seed(p.seed ^ layer.salt, render_seed, pass_index),
                                self._photon_depth(layer), p.rr_depth, maps=maps,
                                min_bounce=self.min_bounce(), paths=layer.paths,
                                caustic_through=self.caustic_through(),
                                caustic_past_landings=self.caustic_past_landings(),
                                store_on=self.store_on(), bent_bsdfs=bent_table(),
                                progress=traced,
                                memory_check=guard)
        # The wave's maps become this process's maps 0 .. len(maps)-1.
        local_of = np.searchsorted(maps, np.arange(self.map_count)).astype(np.uint32)
        photons = photons.with_maps(dr.gather(mi.UInt32, mi.UInt32(local_of), photons.maps),
                                    len(maps))
        t_trace = clock.lap()
        cpu_trace = clock.cpu
        layer.maps = build_photon_maps(photons, keep_bounce=bounded)
        layer.stored, segments = len(photons), photons.segments
        del photons
        t_build = clock.lap()
        cpu_build = clock.cpu
        if traced_here:
            self._stored_per_emitted[layer.name] = layer.stored / traced_here
        prefix = "" if layer.name == "global" else f"{layer.name}_"
        self._add_stats(time_trace=t_trace, time_build=t_build, cpu_trace=cpu_trace,
                        cpu_build=cpu_build, segments=segments,
                        **{f"{prefix}photons_stored": layer.stored,
                           f"{prefix}photons_traced": traced_here})
        self.stats.update(map_bytes=max(self.stats.get("map_bytes", 0), layer.maps.nbytes),
                          maps_owned=owned.tolist())
        return layer.maps

    def _photon_depth(self, layer=None) -> int:
        """The longest photon path of ``layer``'s maps (of any layer's when None):
        ``max_depth`` - 1, which leaves one segment at least for the eye path."""
        d = self.params.max_depth
        return d - 1 if d != UNLIMITED_DEPTH else UNLIMITED_DEPTH

    def _eye_segments(self) -> str:
        """What takes the segments of ``max_depth`` that photons do not have, for messages."""
        return "the camera's takes the only one"

    def caustic_through(self) -> str:
        """What a caustic path bounces on (:data:`~mi_partpm.trace.CAUSTIC_THROUGH`): glossy
        lobes too where eye paths trace glossy surfaces on, so that the caustic and the
        global maps split the paths where the eye paths do."""
        return "glossy" if self.params.glossy == "trace" else "delta"

    def store_on(self) -> str:
        """Where photons are stored (:data:`~mi_partpm.trace.STORE_ON`): with glossy = trace
        only on surfaces with a diffuse lobe, the only ones the estimates read."""
        return "diffuse" if self.params.glossy == "trace" else "smooth"

    def caustic_past_landings(self) -> bool:
        """Whether caustic paths go on past surfaces they left by a delta lobe (see
        :func:`~mi_partpm.trace.trace_photons`): where final gathering reads the maps."""
        return False

    def min_bounce(self) -> int:
        """The fewest segments a stored photon has: 2 when direct light is sampled."""
        return 2 if self.params.direct == "nee" else 1

    def _eye_size(self, scene, sensor, spp):
        """(width, height, samples per pixel) of the eye pass for the memory guard; with
        ``sensor`` None (``sample()``, which traces the rays it is given), ``spp`` rays."""
        if sensor is None:
            return 1, 1, int(spp)
        sensor = scene_sensor(scene, sensor)
        film = sensor.film().crop_size()
        return int(film[0]), int(film[1]), int(spp) or sensor.sampler().sample_count()

    def _emitted_per_map(self, layers=None) -> np.ndarray:
        """Photons emitted per map, over every layer (the global and caustic maps of one
        index are traced in the same wave)."""
        layers = self._layers if layers is None else layers
        return sum(map_sizes(l.photon_count, self.map_count) for l in layers)

    def _stored_ratio(self, maps):
        """Photons stored per photon emitted over the layers of ``maps``, each layer's
        emitted photons weighted by its own ratio: measured (in an earlier wave, or so far
        in the one being traced), else assumed
        (:func:`~mi_partpm.memory.assumed_stored_per_emitted`: a caustic path stores one
        photon where it lands, a global one about three)."""
        emitted = stored = 0.0
        for layer in self._layers:
            e = float(map_sizes(layer.photon_count, self.map_count)[maps].sum())
            ratio = self._stored_per_emitted.get(layer.name)
            if ratio is None:
                ratio = memory.assumed_stored_per_emitted(layer.paths,
                                                          self._photon_depth(layer))
            emitted, stored = emitted + e, stored + e * ratio
        return stored / emitted if emitted else None

    def plan_waves(self, scene, sensor=0, spp: int = 0, maps=None) -> list:
        """The waves of this process's maps (default; or of ``maps``) as lists of map
        indices, for the next pass: the memory guard. Raises
        :class:`~mi_partpm.memory.MemoryGuardError` before any photon is traced when even
        one map per wave would not fit."""
        owned = self.backend.owned_maps(self.map_count) if maps is None else \
            np.asarray(maps, dtype=np.int64)
        if not self._layers:
            self._layers = self.layers()
        sizes = self._emitted_per_map()[owned]
        depth, ratio = self._photon_depth(), self._stored_ratio(owned)
        width, height, samples = self._eye_size(scene, sensor, spp)
        kept = self._eye_kept()
        budget = memory.wave_budget(memory.eye_bytes(width, height, samples, kept),
                                    self.wave_bytes)
        # What a wave of several maps is held to while it is traced (build_maps), as planned
        # here, before the eye pass took its memory.
        self._planned_budget = budget if self.maps_per_wave == 0 else None
        share = self._batch_share()
        waves = memory.plan_waves(sizes, depth, budget, ratio, self.maps_per_wave, share)
        estimate = memory.estimate_render(int(sizes.sum()), depth, width, height, samples,
                                          ratio, waves, sizes, share, kept)
        what = self._photons_text()
        if maps is None and len(owned) < self.map_count:      # an MPI rank's share
            what += f" (this process's {len(owned)} of the {self.map_count} maps)"
        memory.check_fits(estimate, what, option=self._photons_option(),
                          asked=self._photons_asked())
        return [[int(owned[i]) for i in wave] for wave in waves]

    def _eye_kept(self) -> bool:
        """Whether the eye paths keep their state between passes (more bytes per sample for
        the memory guard; partpm's final gathering keeps it too)."""
        return self.passes > 1

    def _batch_share(self) -> float:
        """The share of a wave's photons traced at once: the largest layer's (the layers
        are traced one after the other)."""
        counts = [l.photon_count for l in self._layers]
        return max(counts) / sum(counts) if sum(counts) else 1.0

    def _count_props(self) -> list:
        """(prop, value) of each layer's photon count, for the memory guard's messages:
        photon_count, and caustic_photon_count with caustic maps."""
        return [("photon_count" if l.name == "global" else f"{l.name}_photon_count",
                 l.photon_count) for l in self._layers]

    def _photons_text(self) -> str:
        """The props that set the photons and their values."""
        return ", ".join(f"{prop} = {value}" for prop, value in self._count_props())

    def _photons_asked(self) -> int:
        """The value of what :meth:`_photons_option` names: the photons of every layer."""
        return sum(value for _, value in self._count_props())

    def _photons_option(self) -> str:
        """What to lower: photon_count, or its sum with the caustic maps' photons."""
        return " + ".join(prop for prop, _ in self._count_props())

    def _tracing_guard(self, scene, sensor, spp, maps, layer, budget=None):
        """The check repeated while ``layer``'s wave is traced, with its measured photons
        stored per photon emitted: does the wave still fit? With ``budget`` (the one its
        plan held it to) a wave of several maps is held to it too: where its paths store
        more than planned it is planned again (a closed white room stored 24 photons per
        photon emitted, planned as 3, and took 3 GB in one wave)."""
        width, height, samples = self._eye_size(scene, sensor, spp)
        emitted = int(self._emitted_per_map()[maps].sum())
        depth, share = self._photon_depth(), self._batch_share()
        kept = self._eye_kept()
        budget = budget if len(maps) > 1 else None

        def check_during(ratio, done):
            # What this wave measured so far: a wave planned again plans with it.
            self._stored_per_emitted[layer.name] = ratio
            measured = self._stored_ratio(maps)
            estimate = memory.estimate_render(emitted, depth, width, height, samples,
                                              measured, batch_share=share, kept=kept)
            memory.check_fits(estimate, f"{self._photons_text()} (projected from the first "
                                        f"{done:,} photons traced)",
                              option=self._photons_option(), asked=self._photons_asked())
            need = memory.wave_bytes(emitted, depth, measured, share)
            # (a tolerance for the pilot's noise: a wave packed to its budget at the last
            # pass's ratio is not split for a percent more)
            if budget is not None and need > BUDGET_TOLERANCE * budget:
                raise memory.WaveOverBudget(
                    f"the wave of {len(maps)} maps needs about {memory.size_text(need)}, "
                    f"more than a wave's {memory.size_text(budget)}")
        return check_during

    def _add_stats(self, **values):
        for key, value in values.items():
            self.stats[key] = self.stats.get(key, 0) + value

    def _start_stats(self, render_seed: int):
        p = self.params
        self._stored_per_emitted = {}
        self.stats = {"photons_emitted": p.photon_count, "map_count": self.map_count,
                      "radius": self.radius,
                      "render_seed": render_seed, "passes": 0,
                      "passes_asked": self.passes if self.passes < UNTIL_TIME_LIMIT else None,
                      "photons_stored": 0,
                      "photons_traced": 0, "segments": 0, "time_trace": 0.0,
                      "time_build": 0.0, "time_eye": 0.0, "time_estimate": 0.0,
                      "cpu_trace": 0.0, "cpu_build": 0.0, "cpu_eye": 0.0,
                      "cpu_estimate": 0.0,
                      "time_reduce": 0.0, "reduce_bytes": 0}

    def cancel(self):
        """Mitsuba's request to stop a render, made from Python (another thread, or
        ``on_pass``): a progressive render ends after the pass in progress, with the image
        of the passes so far, as after ``stop_requested``; the next render starts afresh."""
        self._cancelled = True
        super().cancel()

    def should_stop(self) -> bool:
        """Whether a render was asked to stop with :meth:`cancel`, until the next render (or
        the ``sample()`` calls of a wrapper's render) starts or ends; Mitsuba's own flag is
        cleared only by its own render loop, which this one replaces, and stayed set. (A
        ``stop_requested`` that says stop is not a cancel: it ends the render it asks.)"""
        return self._cancelled

    def render(self, scene, sensor=0, seed=0, spp=0, develop=True, evaluate=True):
        """Render: for every pass trace and build the maps, follow the eye paths, estimate at
        their visible points and gather; then develop the film. With ``backend="mpi"`` rank 0
        returns the image (its ``stats["ranks"]`` lists every rank's figures); the other
        ranks return an image without emission and direct light."""
        _wait_for_background_tasks()
        with self._busy:
            # (not cleared when it ends: inside aov Mitsuba calls render() and then sample(),
            # and a cancel() during the one must end the other too)
            self._cancelled = False
            self._last_render = None
            with dr.suspend_grad(), follow_mitsuba_level(), self._freeing_maps(), \
                    memory.render_memory():
                image = self._render(scene, sensor, seed, spp, develop, evaluate)
            self._last_render = (id(scene), _as_int(seed))
            return image

    @contextmanager
    def _freeing_maps(self):
        """The last wave's maps are of no use once a render ends, however it ends: an
        integrator kept in a notebook held them (about 150 MB per 10^6 photons emitted) until
        its next render."""
        try:
            yield
        finally:
            for layer in self._layers:
                layer.maps = None

    def _not_differentiable(self):
        raise NotImplementedError(
            f"{type(self).__name__} is not differentiable: photon tracing, the kd-trees and "
            f"the density estimate have no derivatives; use Mitsuba's prb (or another "
            f"differentiable integrator) for gradients, and {type(self).__name__} for the "
            f"image")

    def render_forward(self, *args, **kwargs):
        self._not_differentiable()

    def render_backward(self, *args, **kwargs):
        self._not_differentiable()

    def _render(self, scene, sensor, seed, spp, develop, evaluate):
        if not develop and self.backend.name != "local":
            raise ValueError(f"develop=False is not supported with backend={self.backend.name!r}"
                             f": render with develop=True")
        with self.backend.running():
            self.backend.start()
            self._lit = check_emitters(scene)   # before any work: a scene it cannot render
            note_bent_bsdfs(scene)
            seed = _as_int(seed)
            self.radius = self.search_radius(scene)
            self._start_stats(seed)
            camera = CameraPass(scene, sensor, seed, spp, self.aov_names(), self.passes > 1)
            split = self._split_spp(scene, camera.sensor, camera.spp)
            if split:
                camera.split(split)
            self.backend.check_same(self._settings(scene, camera, seed))
            image = self._split_pass(scene, camera, seed, develop) if split else \
                camera.develop(*self._passes(scene, camera, seed), develop)
            if evaluate:
                dr.eval(image)
            self.stats["peak_memory_bytes"] = memory.peak_rss_bytes()
            self.backend.collect(self.stats)
            return image

    def _settings(self, scene, camera: CameraPass, seed: int) -> dict:
        """What every process of a render must share for their partial images to add up:
        the eye paths (film, crop, samples, seed), the integrator's props and the scene as
        far as its size and counts tell it apart."""
        film = camera.film
        box = scene.bbox()
        return {"seed": seed, "spp": camera.spp, "film size": tuple(film.size()),
                "crop": (tuple(film.crop_size()), tuple(film.crop_offset())),
                "integrator": str(self), "radius": self.radius,
                "scene": (len(scene.shapes()), len(scene.emitters()),
                          tuple(float(box.min[a]) for a in range(3)),
                          tuple(float(box.max[a]) for a in range(3))),
                "scene content": _scene_digest(scene)}

    def _passes(self, scene, camera: CameraPass, seed: int):
        """The passes of a render: per eye path, the mean light not from the maps and the
        terms' states; returns (radiance, alpha) per sample."""
        p = self.params
        self._layers = self.layers()
        terms = self.terms(self._layers, camera.width, scene)
        emitted = dr.zeros(mi.Spectrum, camera.width)
        valid = dr.zeros(mi.Float, camera.width)
        start, self._paused = time.perf_counter(), 0.0
        for pass_index in range(self.passes):
            waves, eye, weight, clock = self._next_eye_pass(scene, camera, seed, pass_index)
            emitted += eye.emitted * weight
            valid += dr.select(eye.valid, camera.sign, 0.0)    # the filter's sign
            self._add_stats(time_eye=clock.lap(emitted, valid), cpu_eye=clock.cpu, passes=1)
            self._photon_pass(scene, terms, eye.points, camera.width, camera.sensor,
                              camera.spp, seed, pass_index, waves)

            def image(done=pass_index + 1):
                """The image after this pass (developed into the film), while it is the
                last pass done: a later pass adds to the sums it reads."""
                now = getattr(terms[0].state, "passes", done)
                if now != done:
                    raise RuntimeError(
                        f"info['image']() develops the image after pass {done} only until "
                        f"the next pass runs (pass {now} has): call it in on_pass and keep "
                        f"the image it returns")
                # The pass count is opaque: one kernel serves every checkpoint.
                scale = dr.rcp(dr.opaque(mi.Float, done))
                return camera.develop(emitted * scale + _radiance(terms), valid * scale)
            if self._after_pass(pass_index, terms, start, image):
                break
        self._finish(terms)
        done = max(terms[0].state.passes, 1)
        scale = dr.rcp(dr.opaque(mi.Float, done))
        return emitted * scale + _radiance(terms), valid * scale

    def _next_eye_pass(self, scene, camera: CameraPass, seed: int, index: int):
        """The eye paths of set ``index`` of a render's eye rays (a pass, or a set of a
        split pass; the camera moves on to new rays after the first), with the memory
        guard's waves planned before the eye pass allocates anything. Returns (waves, the
        eye paths, the rays' weights, the clock started before the eye pass)."""
        if index:
            camera.advance()
        waves = self.plan_waves(scene, camera.sensor, camera.spp)
        clock = Stopwatch()
        self._pass_seed = stream_seed(self.params.seed, seed, index) & 0x7FFFFFFF
        ray, weight = camera.rays()
        eye = self.eye_pass(scene, camera.sampler, ray, weight, True,
                            self.backend.emission_weight)
        return waves, eye, weight, clock

    def _split_spp(self, scene, sensor, total: int) -> int:
        """The samples per pixel of each set of eye samples traced at once where a render of
        one pass at ``total`` spp (its sampler's) splits them, else 0: ``samples_per_pass``,
        or where that is not given, the most that fit beside the maps
        (:meth:`_fitting_split`). A ValueError, before any work, where ``samples_per_pass``
        does not divide spp (as for Mitsuba's path)."""
        if self.passes > 1:
            return 0
        split = self.samples_per_pass
        if not split:
            return self._fitting_split(scene, sensor, total)
        if split >= total:
            return 0
        if total % split:
            raise ValueError(f"spp = {total} must be a multiple of samples_per_pass = {split} "
                             f"(the render traces its eye samples in passes of "
                             f"samples_per_pass per pixel), as for Mitsuba's path")
        return split

    def _fitting_split(self, scene, sensor, total: int) -> int:
        """Where the eye pass of ``total`` samples per pixel would not fit in the free memory
        beside the maps (their largest wave as planned: ``maps_per_wave`` maps, or all of
        them within the wave budget, ``wave_bytes`` or WAVE_BUDGET_BYTES), the most samples
        per pixel, a divisor of ``total``, whose eye pass does (as Mitsuba's path splits its
        samples into the passes it needs); 0 where all fit, where free memory cannot be
        read, where not even one per pixel fits or the sets would hold fewer than
        :data:`MIN_SET_SAMPLES` samples each (the memory guard then says what to lower: a
        tiny film at a huge spp split into 10^5 sets of 64 samples would run for hours)
        and under MPI (the processes of a render must split alike)."""
        free = memory.available_bytes()
        if free is None or self.backend.name != "local":
            return 0
        self._layers = self.layers()
        owned = self.backend.owned_maps(self.map_count)
        sizes = self._emitted_per_map()[owned]
        depth, ratio, share = self._photon_depth(), self._stored_ratio(owned), \
            self._batch_share()
        # The maps' waves as plan_waves would plan them with the whole wave budget.
        budget = memory.WAVE_BUDGET_BYTES if self.wave_bytes is None else self.wave_bytes
        waves = memory.plan_waves(sizes, depth, budget, ratio, self.maps_per_wave, share)
        maps = memory.estimate_render(int(sizes.sum()), depth, 0, 0, 0, ratio, waves, sizes,
                                      share).photon_maps
        width, height, _ = self._eye_size(scene, sensor, total)
        kept = self._eye_kept()
        per_spp = max(memory.eye_bytes(width, height, 1, kept), 1)
        # The most samples per pixel whose eye pass fits beside the maps (eye bytes grow
        # with spp; counted from there, not from spp: a 1 x 1 film at 10^9 spp).
        most = (free - maps) // per_spp
        if total <= most:
            return 0
        for split in range(int(most), 0, -1):
            if width * height * split < MIN_SET_SAMPLES:
                break
            if total % split == 0:
                log.info("the eye pass of %d x %d at spp = %d (about %s) does not fit beside "
                         "the maps in the %s free: its samples are traced in %d sets of %d "
                         "per pixel (samples_per_pass sets them)", width, height, total,
                         memory.size_text(memory.eye_bytes(width, height, total, kept)),
                         memory.size_text(free), total // split, split)
                return split
        return 0

    def _split_pass(self, scene, camera: CameraPass, seed: int, develop: bool):
        """A render of one pass whose eye samples are traced in the camera's sets
        (:meth:`CameraPass.split`: ``samples_per_pass``, or the sets that fit): the maps
        are traced and built once and every set's eye paths are estimated against them, so
        the eye pass holds one set at a time. Where the maps are held in several waves,
        each set traces them again (the same photons: the streams do not depend on the
        set). Each set is added to the film, which divides by the samples; returns the
        developed image (with ``cancel()``, the image of the sets done)."""
        parts = camera.sets
        self._layers = self.layers()
        block = camera.block()
        start, self._paused = time.perf_counter(), 0.0
        beat = Heartbeat()
        for part in range(parts):
            terms = None                # the last set's per-sample sums, added to the film
            waves, eye, weight, clock = self._next_eye_pass(scene, camera, seed, part)
            emitted = eye.emitted * weight
            valid = dr.select(eye.valid, camera.sign, 0.0)
            self._add_stats(time_eye=clock.lap(emitted, valid), cpu_eye=clock.cpu)
            terms = self.terms(self._layers, camera.width, scene)
            before = dict(self.stats)
            self._photon_pass(scene, terms, eye.points, camera.width, camera.sensor,
                              camera.spp, seed, 0, waves, part)
            if part:
                # The same photons again: counted once.
                for key, value in before.items():
                    if key.endswith(("photons_stored", "photons_traced")) or \
                            key == "segments":
                        self.stats[key] = value
            camera.put(block, emitted + _radiance(terms), valid)
            dr.eval(block.tensor())
            del eye, weight, emitted, valid
            elapsed = beat.due()
            if elapsed is not None or part + 1 == parts:
                log.info("eye samples: %d of %d sets of %d per pixel done, %.1f s", part + 1,
                         parts, camera.spp, time.perf_counter() - start)
            if part + 1 < parts and self.backend.agree(
                    self._cancelled or (self.stop_requested is not None and
                                        bool(self.stop_requested()))):
                self._stopped_by(False, True)
                log.info("eye samples: stopped as asked after %d of %d sets", part + 1,
                         parts)
                break
        self._add_stats(passes=1)
        self._after_pass(0, terms, start, lambda: camera.finish(block))
        self._finish(terms)
        return camera.finish(block, develop)

    def eye_pass(self, scene, sampler, ray, weight, active, emission):
        """Phase 3: the eye paths of ``ray`` (throughput starting at ``weight``) to their
        visible points."""
        p = self.params
        eye = eye_paths(scene, sampler, ray, p.max_depth, p.rr_depth, p.direct == "nee",
                        p.hide_emitters, active, emission, p.glossy, p.glossy_samples,
                        seed=self._pass_seed)
        if weight is not None:
            eye.points.beta = eye.points.beta * dr.gather(mi.Spectrum, weight,
                                                          eye.points.lane)
        return eye

    def _warn_if_empty(self, scene):
        """Warn when no map of the render (of any process) holds a photon, saying why."""
        stored = self.backend.total(sum(v for k, v in self.stats.items()
                                        if k.endswith("photons_stored")))
        # (a collective: every process asks, not only the one that reports)
        traced = self.backend.total(int(self.stats.get("photons_traced", 0)))
        if stored == 0 and self.backend.reports:
            depth = self._photon_depth(self._layers[0] if self._layers else None)
            # (direct light is sampled from an eye path's first surface: a second segment)
            shown = "emitted and sampled direct" if self.params.direct == "nee" and \
                self.params.max_depth != 1 else "emitted"
            if not self._lit:
                log.warning("no photon was stored: every emitter's power is 0 (its radiance "
                            "or intensity); the image holds no light")
            elif depth != UNLIMITED_DEPTH and depth < self.min_bounce():
                log.warning("no photon was stored: max_depth = %d %s", self.params.max_depth,
                            f"leaves photons no segment ({self._eye_segments()}); only "
                            f"{shown} light will show" if depth < 1 else
                            "leaves photons only direct light, which direct = 'nee' samples "
                            "instead; the maps add nothing")
            elif self.min_bounce() > 1:
                log.warning("no photon was stored: direct = '%s' stores only light that "
                            "bounced at least once, and none reached a surface with %s "
                            "(direct light is sampled instead)", self.params.direct,
                            self._stored_where())
            else:
                log.warning("no photon was stored of the %d traced: the scene has no surface "
                            "with %s lit by its emitters%s, or too few photons were traced "
                            "to reach one (raise photon_count); only emitted light will show",
                            traced, self._stored_where(), _small_scene_hint(scene))

    def _stored_where(self) -> str:
        """The surfaces photons are stored on, for messages (:meth:`store_on`)."""
        return "a diffuse lobe (glossy = trace stores photons only there)" \
            if self.store_on() == "diffuse" else "a non-delta BSDF"

    def _photon_pass(self, scene, terms, points, width: int, sensor=0, spp: int = 0,
                     render_seed: int = 0, pass_index: int = 0, waves=None, part: int = 0):
        """Phases 1, 2, 4 and 5 of one pass: wave after wave, trace and build the wave's maps
        of every layer and add every term's estimate over them; then one gather of all terms
        and every term's update. A term's sums over the waves are its sums over all maps
        (eq. 2), so the waves change nothing but the memory held at once. ``part`` > 0: a
        later set of eye samples of the pass (:meth:`_split_pass`), estimated against the
        maps its first set built where they are still held (one wave)."""
        if waves is None:
            waves = self.plan_waves(scene, sensor, spp)
        sums = None
        queue, wave_index = list(waves), -1
        while queue:
            wave = queue.pop(0)
            wave_index += 1
            self.wave_index = wave_index
            count = wave_index + 1 + len(queue)
            if count > 1:
                log.info("wave %d of %d: %s of %d", wave_index + 1, count,
                         _maps_text(wave), self.map_count)
            before = dict(self.stats)
            # (one wave: the maps of the pass's first set are all its maps, still held)
            held = part > 0 and len(waves) == 1 and \
                all(layer.maps is not None for layer in self._layers)
            try:
                for layer in [] if held else self._layers:
                    self.build_maps(scene, layer, sensor, spp, render_seed, pass_index, wave,
                                    self._planned_budget)
            except memory.MemoryGuardError:
                if len(wave) == 1:
                    raise
                queue[:0] = self._split_wave(scene, sensor, spp, wave, before)
                wave_index -= 1
                continue
            first = pass_index == 0 and part == 0
            if first and wave_index == 0:
                self.before_estimate()
            clock = Stopwatch()
            arrays = []
            for term in terms:
                arrays += list(term.compute(points, width))
            self._add_stats(time_estimate=clock.lap(*arrays), cpu_estimate=clock.cpu)
            sums = arrays if sums is None else [a + b for a, b in zip(sums, arrays)]
            if queue or wave_index:
                dr.eval(sums)
                for layer in self._layers:
                    layer.maps = None
        if first:
            self._warn_if_empty(scene)
        self.stats["waves"] = wave_index + 1
        arrays = self.backend.allreduce(sums, self.stats)
        if first:
            self._warn_if_none_found(terms, arrays, len(points))
        for j, term in enumerate(terms):
            term.state.update(arrays[2 * j], arrays[2 * j + 1])

    def _split_wave(self, scene, sensor, spp, wave, before) -> list:
        """The smaller waves of a ``wave`` of several maps whose paths store more photons
        than its plan assumed, so that it would not fit: planned with what it measured (the
        streams are the same, so are the photons). Its maps are freed and the stats put back
        as they were ``before`` it (a layer done before the one that stopped is traced
        again and counted once; the times spent stay counted)."""
        for key in [k for k in self.stats if not k.startswith(("time_", "cpu_"))]:
            if key in before:
                self.stats[key] = before[key]
            else:
                del self.stats[key]
        for layer in self._layers:
            layer.maps = None
        smaller = self.plan_waves(scene, sensor, spp, wave)
        if max(len(w) for w in smaller) >= len(wave):
            # The plan would keep it whole (maps_per_wave, or more memory free once its maps
            # are freed): halve it, or it would stop again where it did.
            half = (len(wave) + 1) // 2
            smaller = [wave[:half], wave[half:]]
        log.info("the wave of %s stores more photons per photon emitted than planned: "
                 "traced again in %d smaller waves", _maps_text(wave), len(smaller))
        return smaller

    def _warn_if_none_found(self, terms, arrays, visible: int):
        """Per term, warn when its maps hold photons and visible points exist but no
        estimate found a photon (a radius far below the photons' spacing), or when a term's
        own maps (the caustic ones) hold none: the term then adds nothing."""
        prefixes = ["" if term.name == "global" else f"{term.name}_" for term in terms]
        # The maps of every process: the photons stored in all of them (the sums in
        # ``arrays`` are every process's already). Asked before anything returns: every
        # process makes the same collective calls.
        every = [self.backend.total(int(self.stats.get(f"{prefix}photons_stored", 0)))
                 for prefix in prefixes]
        traced = [self.backend.total(int(self.stats.get(f"{prefix}photons_traced", 0)))
                  for prefix in prefixes]
        if visible == 0 or not self.backend.reports:
            return
        # Said after the first pass: of a render of several, of that pass.
        first, add = (" in the first pass", "added nothing to it") if self.passes > 1 else \
            ("", "add nothing")
        for j, (term, prefix, stored) in enumerate(zip(terms, prefixes, every)):
            if stored == 0:
                if prefix:
                    log.warning("no %s photon was stored of the %d traced%s: the scene has no "
                                "such light path (for caustics: emitter, mirror or glass, "
                                "then a diffuse surface), or too few photons were traced to "
                                "find one (raise %sphoton_count); the %s maps %s",
                                term.name, traced[j], first, prefix, term.name, add)
                continue
            if float(dr.sum(arrays[2 * j + 1])[0]) == 0:
                r = self.radius if not prefix else self.stats.get(f"{prefix}radius")
                radius = "" if r is None else f" (radius {r:.4g})"
                where, why = self.none_found_text(term.name)
                log.warning("no photon was found at any %s by the %s estimate%s%s, though %d "
                            "were stored: %s, and those maps %s", where, term.name, radius,
                            first, stored, why, add)

    def _finish(self, terms):
        self.after_estimate()
        # The radii a next pass would search with (a render of one pass searched with the
        # fixed radius alone, and its stats say so: no final radius).
        for term in terms:
            if hasattr(term.state, "r2") and getattr(term.state, "passes", 0) > 1:
                key = "mean_final_radius" if term.name == "global" else \
                    f"{term.name}_mean_final_radius"
                self.stats[key] = float(dr.mean(dr.sqrt(term.state.r2))[0])
        done = self.stats.get("passes", 0)
        scheduled = self.scheduled_radius(done) if done > 1 else None
        if "mean_final_radius" not in self.stats and scheduled is not None:
            self.stats["mean_final_radius"] = scheduled

    def _after_pass(self, pass_index: int, terms, start: float, image) -> bool:
        """Progress after a pass (``on_pass`` receives it, with ``image()`` to develop the
        image so far); True when the time limit says to stop. Time spent in ``on_pass`` is
        not counted."""
        elapsed = time.perf_counter() - start - self._paused
        done = pass_index + 1
        state = terms[0].state
        info = {"pass": done, "passes": self.passes if self.passes < UNTIL_TIME_LIMIT else None,
                "elapsed": elapsed, "image": image,
                "photons": done * self.params.photon_count,
                "eta": self._remaining(elapsed, done),
                "mean_radius": float(dr.mean(dr.sqrt(state.r2))[0])
                if hasattr(state, "r2") else self.scheduled_radius(done)}
        timed_out = self.time_limit > 0 and elapsed >= self.time_limit
        if self.passes > 1:
            # Every process by the root's clock: its on_pass time is left out, and the
            # others, which waited for it, counted it and stopped the job early.
            timed_out = self.backend.root_says(timed_out)
        asked = self._cancelled or \
            (self.stop_requested is not None and bool(self.stop_requested()))
        ended = self.cannot_run_pass(done) if done < self.passes else None
        stop = (timed_out or asked or ended is not None) and done < self.passes
        if self.passes > 1:
            # Every process of the render stops after the same pass (the first whose clock
            # or request says so on any process), or one would wait in the next pass's
            # gather for ever: asked after every pass, so every process asks as often
            # whatever it was told.
            stop = self.backend.agree(stop)
        info["last"] = stop or done == self.passes
        if info["last"]:
            info["eta"] = 0.0
        if stop:
            self._stopped_by(timed_out, asked, ended, done)
        if self.passes > 1:
            radius = "" if info["mean_radius"] is None else \
                f", mean radius {info['mean_radius']:.4g}"
            of = f"{self.passes}" if not self.time_limit else \
                f"at most {self.passes} in {self.time_limit:g} s" \
                if self.passes < UNTIL_TIME_LIMIT else f"as many as fit in {self.time_limit:g} s"
            ending = (", stopped as asked" if asked else ", time limit reached" if timed_out
                      else ", no further pass can run" if ended
                      else ", stopped with another process") if stop \
                else f", about {info['eta']:.0f} s left"
            log.info("pass %d of %s: %d photons so far%s, %.1f s elapsed%s", done, of,
                     info["photons"], radius, elapsed, ending)
        if self.on_pass is not None:
            t0 = time.perf_counter()
            self.on_pass(info)
            self._paused += time.perf_counter() - t0
        if self.passes > 1 and not stop and done < self.passes:
            # cancel() from on_pass: this pass was the last (on_pass was told it was not),
            # on every process (one more agreement: a process whose on_pass cancelled asks
            # the others, who ask as often whatever their on_pass did).
            if self.backend.agree(self._cancelled):
                stop = True
                self._stopped_by(False, True)
                log.info("pass %d: stopped as asked", done)
        return stop

    def _stopped_by(self, timed_out: bool, asked: bool, ended=None, done: int = 0):
        """Why the render has fewer passes than it was given, in its stats: its time limit,
        a request (Ctrl-C, cancel()), a next pass that cannot run (``ended``, why, from
        :meth:`cannot_run_pass`, which is said after pass ``done``) or another process of
        the render that stopped."""
        self.stats["stopped_by"] = "time_limit" if timed_out else \
            "request" if asked else "radius" if ended else "another_process"
        if self.stats["stopped_by"] == "radius":
            log.warning("pass %d: %s, so the render ends here, before its time limit", done,
                        ended)

    def none_found_text(self, term: str) -> tuple:
        """Where the ``term`` estimate searches, and why it may find nothing there."""
        return "visible point", ("the search is far smaller than the photons' spacing, or "
                                 "the photons lie only where the camera sees no surface read "
                                 "from the maps (on an emitter hide_emitters hides, say)")

    def scheduled_radius(self, passes_done: int):
        """The radius a next pass would search with where it follows a schedule rather than
        each eye path's photons (a final gather's), or None."""
        return None

    def cannot_run_pass(self, pass_index: int):
        """Why pass ``pass_index`` (0 first) cannot run, or None. A render of a given number
        of passes is refused before its first where one could not; one of passes until its
        time limit ends after the last that can. None here."""
        return None

    def _remaining(self, elapsed: float, done: int) -> float:
        """Seconds left: the passes to go at the mean pass time so far, or less where the
        time limit ends the render first (it stops after the pass that reaches it)."""
        left = elapsed / done * (self.passes - done)
        if self.time_limit > 0:
            left = min(left, max(self.time_limit - elapsed, 0.0) + elapsed / done)
        return left

    # ------------------------------------------------------------------ per sample

    def sample(self, scene, sampler, ray, medium=None, active=True):
        """The radiance along ``ray`` for another integrator that wraps this one (moment,
        aov): maps are traced for this call with the ``seed`` prop's streams, and the passes
        refine the estimate at these rays' visible points (progressive photon mapping).

        Mitsuba's ``aov`` renders its nested integrator alone (``render()``: the image
        ``mi.render`` returns) and then once more through ``sample()`` (the film's channels):
        ``sample()`` takes the seed of this integrator's last ``render()`` of the same scene
        too, so that the two use the same photons. A wrapper that does not call ``render()``
        (``moment``) is not told ``mi.render``'s seed: its photons come from the ``seed`` prop
        alone (and the seed of an earlier ``render()`` of the scene, if any)."""
        if self.backend.name != "local":
            raise ValueError(f"{type(self).__name__} with backend={self.backend.name!r} "
                             f"must be the scene's top-level integrator (its ranks gather "
                             f"whole images); use backend='local' inside moment or aov")
        _wait_for_background_tasks()
        with self._busy, follow_mitsuba_level(), self._freeing_maps(), \
                memory.render_memory():
            last = self._last_render
            render_seed = last[1] if last is not None and last[0] == id(scene) else 0
            try:
                return self._sample(scene, sampler, ray, active, render_seed)
            finally:
                # A cancel() during the wrapper's render (before this call too: the wrapper
                # loads and compiles first) ends this one; the next starts afresh.
                self._cancelled = False

    def _sample(self, scene, sampler, ray, active, render_seed: int):
        self._lit = check_emitters(scene)
        note_bent_bsdfs(scene)
        width = dr.width(ray.o)
        self.radius = self.search_radius(scene)
        self._start_stats(render_seed)
        self._pass_seed = stream_seed(self.params.seed, render_seed, 0) & 0x7FFFFFFF
        eye = self.eye_pass(scene, sampler, ray, None, active, 1.0)
        self._layers = self.layers()
        terms = self.terms(self._layers, width, scene)
        start = time.perf_counter()
        for pass_index in range(self.passes):
            self._photon_pass(scene, terms, eye.points, width, None, width,
                              render_seed=render_seed, pass_index=pass_index)
            self._add_stats(passes=1)
            timed_out = 0 < self.time_limit <= time.perf_counter() - start
            asked = self._cancelled or \
                (self.stop_requested is not None and bool(self.stop_requested()))
            ended = self.cannot_run_pass(pass_index + 1) if pass_index + 1 < self.passes \
                else None
            if timed_out or asked or ended:
                if pass_index + 1 < self.passes:
                    self._stopped_by(timed_out, asked, ended, pass_index + 1)
                break
        self._finish(terms)
        return eye.emitted + _radiance(terms), eye.valid, []

    def aov_names(self):
        return []

    def common_props_text(self) -> str:
        """The shared props as ``key = value`` pairs for :meth:`to_string`."""
        p = self.params
        return (f"max_depth = {p.max_depth}, rr_depth = {p.rr_depth}, seed = {p.seed}, "
                f"direct = {p.direct}, hide_emitters = {p.hide_emitters}, kernel = "
                f"{p.kernel}, glossy = {p.glossy}, glossy_samples = {p.glossy_samples}"
                + (f", samples_per_pass = {self.samples_per_pass}" if self.samples_per_pass
                   else ""))
