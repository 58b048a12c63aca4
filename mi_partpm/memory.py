"""Memory guard and waves: will a render fit, and how many photon maps are held at once.

A render holds its eye pass (every sample's path state, the visible points and the terms'
per-path sums) for the whole pass, and the photon maps of one *wave* at a time: the maps of
a pass are traced, built and queried a wave after another, and each wave's maps are freed
before the next is traced. Eq. (2) makes this exact: every map's term is added to the eye
paths on its own, so the image does not depend on the waves (up to the order of float
additions). A wave holds as many maps as fit the budget (:func:`plan_waves`): all of them
when they fit, which is the fastest; fewer when they do not, which is how 10^8 photons fit a
machine that could not hold their maps at once.

The estimate counts what grows with the inputs, per stored photon of a wave and per eye
sample; free memory is the kernel's ``MemAvailable`` (Linux), or ``PARTPM_MEMORY_LIMIT``
(bytes) where a test or a user sets it; where neither can be read the guard only reports.
"""
from __future__ import annotations

import os
import resource
import sys
import threading
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Optional, Sequence

__all__ = ["available_bytes", "share_memory", "render_memory", "peak_rss_bytes",
           "MemoryEstimate", "estimate_render", "check_fits", "assumed_stored_per_emitted",
           "plan_waves", "wave_budget", "MemoryGuardError", "WaveOverBudget", "TRACE_BATCH",
           "WAVE_BYTES_PER_STORED", "TRACE_BATCH_BYTES", "BATCH_BYTES_PER_STORED",
           "batch_bytes_per_path", "EYE_BYTES_PER_SAMPLE", "EYE_BYTES_PER_SAMPLE_KEPT",
           "ASSUMED_STORED_PER_EMITTED", "ASSUMED_CAUSTIC_STORED_PER_EMITTED",
           "WAVE_BUDGET_BYTES", "MORE_MAPS", "LOWER_DEPTH", "FOREST_BYTES_PER_STORED"]

#: Photon paths traced together at most (larger counts run in batches of this size).
TRACE_BATCH = 1 << 20
#: Bytes of one trace batch's buffers and state beyond the photons it returns (the stored
#: photons' 32-byte slots, about 3.75 per path, the order that puts them in photon order,
#: and the copy it reads them into), whatever the photon count. Measured: Dr.Jit's peak over
#: a trace of 2^20 paths in the Cornell box less the photons returned, 283 bytes per path
#: when a pilot batch's photons were joined to the full batch's, 198 without that joining
#: (the pilot's photons are now traced again instead, so the estimate keeps the margin).
TRACE_BATCH_BYTES = 300 * TRACE_BATCH
#: The same per stored photon, where paths store more (the slots and their copies grow with
#: them): measured 73 bytes (the Cornell box, 2.98 stored per path) and 110 (a closed room
#: of reflectance 0.99 lit by a point light, 24 per path; 2,649 bytes per path against the
#: 300 above) beyond the photons returned, Dr.Jit's peak over one batch.
BATCH_BYTES_PER_STORED = 110
#: Peak bytes per stored photon of a wave while it is traced, built and queried: the photons
#: as traced (position, direction, power, map, bounce), the tree build's sort orders and
#: partition temporaries, the maps in tree order, and Dr.Jit's rounding of every allocation
#: to a power of two. Measured: 131 bytes (Dr.Jit's peak over the stored photons of one wave
#: of 3 x 10^7 in the Cornell box); 150 leaves room for scenes that store more per path.
WAVE_BYTES_PER_STORED = 150
#: Eye pass bytes per sample of a single-pass render (ray, throughput, sampler, the visible
#: points, the terms' per-path sums and the film). Measured (Dr.Jit's peak over a render of
#: 10^4 photons in 8 maps, per sample): 452 (Cornell box, 480 x 480 x 4), 432 (480 x 480 x
#: 16), 384 (1024 x 1024 x 4), 456 with emitter sampling, 508 with glossy surfaces traced on,
#: 514 in glossy_spheres traced on with emitter sampling, 285 in glossy_spheres.
EYE_BYTES_PER_SAMPLE = 520
#: The same where every eye path keeps its state between passes (progressive) or gathers
#: (final gathering): measured 669 (Cornell box, 2 passes), 701 (final gather of 1 ray),
#: 737 (caustic_glass, 2 passes, caustic maps), 480 x 480 x 4.
EYE_BYTES_PER_SAMPLE_KEPT = 760
#: Photons stored per emitted photon assumed before tracing, when max_depth does not bound it
#: lower (measured: 2.9-3.0 in the Cornell box, 3.4 in glossy_spheres, 4.0 in caustic_glass,
#: 0.5 for the open Buddha scene). After the first
#: wave the measured ratio replaces it.
ASSUMED_STORED_PER_EMITTED = 3.0
#: The most bytes one wave's photon maps may take by default: renders larger than this run in
#: waves even where more memory is free, so that a render's memory stays predictable and about
#: 80 bytes per stored photon or less (maps of about 10^7 stored photons fit one wave; with
#: 2 GiB, 10^7 photons emitted into 8 maps peaked at 83 bytes per stored photon in 3 waves).
#: Waves cost no speed: smaller builds stay in the caches (10^7 photons emitted into 8 maps:
#: 45.6 s in 2 waves, 50.7 s in one).
WAVE_BUDGET_BYTES = 3 << 29

#: Bytes per stored photon of a built forest kept beside the traced photons (calibrate keeps
#: one per leaf size and map count): its records (16), its tree order (4) and its tree (about
#: 2 with leaves of 32 or more photons), doubled for Dr.Jit's rounding of an allocation to a
#: power of two.
FOREST_BYTES_PER_STORED = 44

class MemoryGuardError(MemoryError):
    """The render would need more memory than is free; the message says which prop to lower."""


class WaveOverBudget(MemoryGuardError):
    """A wave of several maps, while it is traced, turns out to store more photons than
    its plan assumed and to need more than a wave may take (:func:`wave_budget`): it is
    planned again in smaller waves (never raised for a wave of one map)."""


def _proc_bytes(path: str, key: str) -> Optional[int]:
    """The ``key:`` line of a /proc file given in kB (``MemAvailable`` of /proc/meminfo,
    ``VmHWM`` of /proc/self/status), in bytes; None where it cannot be read."""
    try:
        with open(path) as f:
            for line in f:
                if line.startswith(key + ":"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return None


#: Processes of one job that share this machine's memory (the MPI ranks on this node:
#: :func:`share_memory`); each plans with its share of the free memory.
_SHARERS = 1


def share_memory(processes: int):
    """Plan every render of this process with 1 / ``processes`` of the machine's free memory
    (the MPI backend: P ranks on one node planned P times what was free before)."""
    global _SHARERS
    _SHARERS = max(1, int(processes))


#: Per thread, this process's resident bytes when the thread's render began
#: (:func:`render_memory`); unset outside a render.
_RENDER_START = threading.local()


@contextmanager
def render_memory():
    """Within it (a render), what the render holds counts as free to it: the guard's checks
    after the eye pass (while a wave is traced, a wave planned again, the next pass's plan)
    compare the whole render's bytes with what is free, and ``MemAvailable`` had already
    lost what the render holds: a 1920 x 1080 x 16 render that fitted its plan was refused
    once its eye pass had run. Per thread; a render made within another (in ``on_pass``)
    counts from its own start, not the outer render's memory, which it cannot use."""
    outer = getattr(_RENDER_START, "bytes", None)
    _RENDER_START.bytes = _proc_bytes("/proc/self/status", "VmRSS")
    try:
        yield
    finally:
        _RENDER_START.bytes = outer


def _held_by_render() -> int:
    """Resident bytes this process gained since this thread's render began (0 outside
    one)."""
    start = getattr(_RENDER_START, "bytes", None)
    if start is None:
        return 0
    now = _proc_bytes("/proc/self/status", "VmRSS")
    return 0 if now is None else max(0, now - start)


def available_bytes() -> Optional[int]:
    """Free memory for this process (``MemAvailable``, divided among the ranks of an MPI job
    on this machine (:func:`share_memory`), plus, within a render, what the render holds
    (:func:`render_memory`); or ``PARTPM_MEMORY_LIMIT`` where it is set, the free memory of
    each process for a whole render: a ValueError where that is not a number >= 1), or None
    where it cannot be read."""
    override = os.environ.get("PARTPM_MEMORY_LIMIT")
    if override:
        try:
            value = float(override)
        except ValueError:
            value = float("nan")
        if not (1 <= value < float("inf")):
            raise ValueError(f"PARTPM_MEMORY_LIMIT (the free memory to assume, in bytes) "
                             f"must be a number >= 1, e.g. 8e9; got {override!r}")
        return int(value)
    free = _proc_bytes("/proc/meminfo", "MemAvailable")
    return None if free is None else free // _SHARERS + _held_by_render()


def peak_rss_bytes() -> int:
    """Peak resident memory of this process so far.

    On Linux this is ``VmHWM`` of ``/proc/self/status``: ``ru_maxrss`` is carried from a
    parent into a child across fork and exec, so a small child of a large process would
    report its parent's peak. Elsewhere it is ``ru_maxrss``."""
    hwm = _proc_bytes("/proc/self/status", "VmHWM")
    if hwm is not None:
        return hwm
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return int(peak if sys.platform == "darwin" else peak * 1024)


@dataclass
class MemoryEstimate:
    """Bytes of a render: its largest wave of photon maps and its eye pass."""

    photons: int          # photons emitted (over the maps of the largest wave)
    stored: float         # photons stored in the largest wave
    waves: int
    photon_maps: int      # peak bytes of the largest wave (trace, build, maps)
    eye: int

    @property
    def total(self) -> int:
        return self.photon_maps + self.eye

    def describe(self) -> str:
        waves = "" if self.waves == 1 else f" in the largest of {self.waves} waves"
        return (f"{size_text(self.total)} (photon maps {size_text(self.photon_maps)} for "
                f"about {self.stored:.3g} stored photons{waves}, eye pass "
                f"{size_text(self.eye)})")


def size_text(nbytes: float) -> str:
    """``nbytes`` for a message: in GB with two decimals from 0.1 GB, in MB or kB below, so
    that a small amount does not read 0.00 GB."""
    if nbytes >= 1e8:
        return f"{nbytes / 1e9:.2f} GB"
    if nbytes >= 1e5:
        return f"{nbytes / 1e6:.1f} MB"
    return f"{nbytes / 1e3:.1f} kB"


#: Photons stored per caustic photon emitted, assumed before tracing: a caustic path stores
#: one photon where it lands after a mirror or glass and ends there, so this is the most it
#: stores (where every path leaves the light through glass); most paths meet no mirror or
#: glass (measured: 0.02 in caustic_glass, 0.05 in glossy_spheres with glossy = trace, 0.07
#: in the Cornell box, the same with final gathering, whose caustic paths go on past their
#: landings). As for the global maps, the measured ratio replaces it once a wave is traced.
ASSUMED_CAUSTIC_STORED_PER_EMITTED = 1.0


def assumed_stored_per_emitted(paths: str, max_depth: int) -> float:
    """Photons stored per photon emitted assumed before a layer's first wave: a caustic
    layer's (``paths`` "caustic") :data:`ASSUMED_CAUSTIC_STORED_PER_EMITTED`, else
    :data:`ASSUMED_STORED_PER_EMITTED`; at most ``max_depth``."""
    ratio = ASSUMED_CAUSTIC_STORED_PER_EMITTED if paths == "caustic" else \
        ASSUMED_STORED_PER_EMITTED
    return min(ratio, float(max_depth)) if max_depth != -1 else ratio


def stored_photons(photon_count: float, max_depth: int,
                   stored_per_emitted: Optional[float] = None) -> float:
    """Photons stored for ``photon_count`` emitted (``max_depth`` -1: unlimited)."""
    ratio = ASSUMED_STORED_PER_EMITTED if stored_per_emitted is None else stored_per_emitted
    if max_depth != -1:
        ratio = min(ratio, float(max_depth))
    return photon_count * ratio


def wave_bytes(emitted: float, max_depth: int, stored_per_emitted=None,
               batch_share: float = 1.0) -> int:
    """Peak bytes of one wave of maps that emit ``emitted`` photons, of which a share
    ``batch_share`` is traced at once (the largest layer's: the global and the caustic maps
    are traced one after the other)."""
    return int(stored_photons(emitted, max_depth, stored_per_emitted) * WAVE_BYTES_PER_STORED
               + min(emitted * batch_share, TRACE_BATCH)
               * batch_bytes_per_path(max_depth, stored_per_emitted))


def batch_bytes_per_path(max_depth: int, stored_per_emitted=None) -> float:
    """Bytes per path of a trace batch beyond the photons it returns:
    :data:`TRACE_BATCH_BYTES` per path, or :data:`BATCH_BYTES_PER_STORED` per photon it
    stores where that is more."""
    return max(TRACE_BATCH_BYTES / TRACE_BATCH,
               BATCH_BYTES_PER_STORED * stored_photons(1.0, max_depth, stored_per_emitted))


def eye_bytes(width: int, height: int, spp: int, kept: bool = False) -> int:
    """Bytes of the eye pass of a film of ``width`` x ``height`` at ``spp``; ``kept``: its
    paths keep their state between passes or gather (:data:`EYE_BYTES_PER_SAMPLE_KEPT`)."""
    return int(width) * int(height) * int(spp) * (EYE_BYTES_PER_SAMPLE_KEPT if kept else
                                                  EYE_BYTES_PER_SAMPLE)


def estimate_render(photon_count: int, max_depth: int, width: int, height: int, spp: int,
                    stored_per_emitted: Optional[float] = None,
                    waves: Sequence[Sequence[int]] = (), map_sizes=None,
                    batch_share: float = 1.0, kept: bool = False) -> MemoryEstimate:
    """The bytes a render with these inputs needs: ``photon_count`` photons emitted over
    the maps of ``map_sizes`` (photons per map; default one map), held in ``waves`` (lists of
    map indices; default all at once)."""
    sizes = [photon_count] if map_sizes is None else list(map_sizes)
    waves = list(waves) or [list(range(len(sizes)))]
    largest = max(waves, key=lambda w: sum(sizes[m] for m in w))
    emitted = sum(sizes[m] for m in largest)
    return MemoryEstimate(photons=int(emitted),
                          stored=stored_photons(emitted, max_depth, stored_per_emitted),
                          waves=len(waves),
                          photon_maps=wave_bytes(emitted, max_depth, stored_per_emitted,
                                                 batch_share),
                          eye=eye_bytes(width, height, spp, kept))


#: The guard's advice beside fewer photons: more maps, or a lower max_depth.
MORE_MAPS = ", raise map_count (smaller maps make smaller waves)"
LOWER_DEPTH = ", or lower max_depth"


def check_fits(estimate: MemoryEstimate, what: str = "this render",
               option: str = "photon_count", more: str = MORE_MAPS + LOWER_DEPTH,
               asked: Optional[int] = None):
    """Raise :class:`MemoryGuardError` when ``estimate`` exceeds the free memory. The
    message says to lower ``option`` (what sets the photons) to a value for it, scaled from
    its value ``asked`` (default the estimate's own photons: the photons of every wave and
    every rank scale with it), or what ``more`` adds, or the eye samples."""
    free = available_bytes()
    if free is None or estimate.total <= free:
        return
    room = free - estimate.eye
    photons_fit = int(estimate.photons * room / max(estimate.photon_maps, 1) * 0.9) \
        if room > 0 else 0
    if photons_fit < 1:
        # The eye pass alone (nearly) fills what is free: fewer photons would not help.
        share = max(free * 0.9 / max(estimate.eye, 1), 0.0)
        raise MemoryGuardError(
            f"the eye pass (the camera's samples) alone needs about "
            f"{size_text(estimate.eye)}, "
            f"{'but only' if room <= 0 else 'which leaves no room for a photon of the'} "
            f"{size_text(free)}{' are' if room <= 0 else ''} free{_share_text()}: lower the "
            f"resolution or spp (to about {share:.2g} of the samples per image here); fewer "
            f"photons would not help (their maps take {size_text(estimate.photon_maps)})")
    target = int((asked or estimate.photons) * photons_fit / max(estimate.photons, 1))
    raise MemoryGuardError(
        f"{what} needs about {estimate.describe()}, but only {size_text(free)} are free"
        f"{_share_text()}: lower {option} (to about {target:,} here){more}, or the "
        f"resolution / spp (the eye pass takes {size_text(estimate.eye)})")


def _share_text() -> str:
    return "" if _SHARERS == 1 or os.environ.get("PARTPM_MEMORY_LIMIT") else \
        f" (this process's share: the machine's free memory over the {_SHARERS} MPI ranks " \
        f"on it)"


def wave_budget(eye: int, limit: Optional[int] = None) -> Optional[int]:
    """The bytes one wave may take: ``limit`` (default :data:`WAVE_BUDGET_BYTES`), and no
    more than what is free beside the eye pass (None where free memory cannot be read and
    no limit is set)."""
    free = available_bytes()
    budget = WAVE_BUDGET_BYTES if limit is None else int(limit)
    if free is not None:
        budget = min(budget, free - eye)
    return budget


def plan_waves(map_sizes: Sequence[int], max_depth: int, budget: Optional[int],
               stored_per_emitted: Optional[float] = None, maps_per_wave: int = 0,
               batch_share: float = 1.0) -> list:
    """The maps (indices into ``map_sizes``, photons emitted per map) of every wave: in map
    order, each wave as many maps as fit ``budget`` bytes (at least one), or exactly
    ``maps_per_wave`` when that is > 0. One wave holds all maps when ``budget`` is None."""
    maps = list(range(len(map_sizes)))
    if maps_per_wave > 0:
        return [maps[i:i + maps_per_wave] for i in range(0, len(maps), maps_per_wave)]
    if budget is None:
        return [maps]
    waves, current, emitted = [], [], 0
    for m in maps:
        if current and wave_bytes(emitted + map_sizes[m], max_depth, stored_per_emitted,
                                  batch_share) > budget:
            waves.append(current)
            current, emitted = [], 0
        current.append(m)
        emitted += map_sizes[m]
    waves.append(current)
    return waves


