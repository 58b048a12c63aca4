"""Memory guard: will a render fit, before it starts and while photons are traced.

The estimate counts what grows with the inputs: the tracer's per-path state for one batch,
the stored photons on the host (as traced) and on the device (as maps), the tree build's
temporaries, and the eye pass's per-sample state and image. Free memory is the kernel's
``MemAvailable`` (Linux); where it cannot be read the guard only reports.
"""
from __future__ import annotations

import os
import resource
import sys
from dataclasses import dataclass
from typing import Optional

__all__ = ["available_bytes", "peak_rss_bytes", "MemoryEstimate", "estimate_render",
           "check_fits", "MemoryGuardError", "TRACE_BATCH", "HOST_BYTES_PER_STORED",
           "DEVICE_BYTES_PER_STORED", "BUILD_BYTES_PER_STORED", "TRACER_BYTES_PER_PATH"]

#: Photon paths traced together at most (larger counts run in batches of this size).
TRACE_BATCH = 1 << 22
#: Host bytes of one stored photon as traced (position, direction, power, normal: float32;
#: map id: uint32; bounce: uint16).
HOST_BYTES_PER_STORED = 4 * 12 + 4 + 2
#: Device bytes of one stored photon in the maps (record 28 + tree, rounded up).
DEVICE_BYTES_PER_STORED = 30
#: Peak temporaries of the tree build per photon (three sort orders and their float64 keys,
#: the partition's prefix sums, Dr.Jit's allocation cache). Calibrated on the largest run
#: measured: 10^7 photons emitted into the Cornell box, 29.8 million stored, peak resident
#: memory 10.0 GB, i.e. 337 bytes per stored photon in all.
BUILD_BYTES_PER_STORED = 260
#: Tracer state per live path (ray, power, random state, surface interaction temporaries).
TRACER_BYTES_PER_PATH = 400
#: Eye pass state per sample (ray, throughput, sampler, film accumulation).
EYE_BYTES_PER_SAMPLE = 200
#: Photons stored per emitted photon assumed before tracing, when max_depth does not bound it
#: lower (measured: 3.0 in the Cornell box, 0.5 for the open Buddha scene). The projection
#: during tracing replaces it with the measured ratio.
ASSUMED_STORED_PER_EMITTED = 3.0


class MemoryGuardError(MemoryError):
    """The render would need more memory than is free; the message says which prop to lower."""


def available_bytes() -> Optional[int]:
    """Free memory (``MemAvailable``), or None where it cannot be read."""
    override = os.environ.get("PARTPM_MEMORY_LIMIT")
    if override:
        return int(float(override))
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return None


def peak_rss_bytes() -> int:
    """Peak resident memory of this process so far."""
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return int(peak if sys.platform == "darwin" else peak * 1024)


@dataclass
class MemoryEstimate:
    photons: int
    stored: float
    tracer: int
    photon_maps: int
    build: int
    eye: int

    @property
    def total(self) -> int:
        # The tracer's state is freed before the build; the host copy lives through the build.
        host = int(self.stored * HOST_BYTES_PER_STORED)
        return max(self.tracer + host, host + self.build + self.photon_maps) + self.eye

    def describe(self) -> str:
        gb = 1e9
        return (f"{self.total / gb:.2f} GB (photon maps {self.photon_maps / gb:.2f} GB for "
                f"about {self.stored:.3g} stored photons, tree build {self.build / gb:.2f} GB, "
                f"tracer {self.tracer / gb:.2f} GB, eye pass {self.eye / gb:.2f} GB)")


def estimate_render(photon_count: int, max_depth: int, width: int, height: int, spp: int,
                    stored_per_emitted: Optional[float] = None) -> MemoryEstimate:
    """The bytes a render with these inputs needs (``max_depth`` -1: unlimited)."""
    ratio = ASSUMED_STORED_PER_EMITTED if stored_per_emitted is None else stored_per_emitted
    if max_depth != -1:
        ratio = min(ratio, float(max_depth))
    stored = photon_count * ratio
    return MemoryEstimate(
        photons=photon_count, stored=stored,
        tracer=min(photon_count, TRACE_BATCH) * TRACER_BYTES_PER_PATH,
        photon_maps=int(stored * DEVICE_BYTES_PER_STORED),
        build=int(stored * BUILD_BYTES_PER_STORED),
        eye=width * height * spp * EYE_BYTES_PER_SAMPLE)


def check_fits(estimate: MemoryEstimate, what: str = "this render"):
    """Raise :class:`MemoryGuardError` when ``estimate`` exceeds the free memory."""
    free = available_bytes()
    if free is None or estimate.total <= free:
        return
    fraction = free / estimate.total
    raise MemoryGuardError(
        f"{what} needs about {estimate.describe()}, but only {free / 1e9:.2f} GB are free: "
        f"lower photon_count (to about {int(estimate.photons * fraction * 0.9):,} here) or "
        f"max_depth, or the resolution / spp if the eye pass dominates")
