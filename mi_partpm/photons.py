"""Stored photons on the device: what the tracer writes and the photon maps are built from.

A photon is its position, its incident direction (octahedral code, 2 x 16 bits), its power
(already divided by the total emitted count N, so the per-map estimates add up, eq. 2), the
map it belongs to and the number of segments from its emitter. :class:`Photons` keeps them as
Dr.Jit arrays; its NumPy properties copy them to the host for inspection and tests.
"""
from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

__all__ = ["Photons", "encode_direction", "decode_direction", "empty_photons",
           "spectrum_channels", "gather_each"]


def spectrum_channels() -> int:
    """Colour channels of the variant's ``mi.Spectrum`` (1 or 3)."""
    return dr.size_v(mi.Spectrum) if dr.size_v(mi.Spectrum) > 0 else 1


def gather_each(value, index):
    """``value`` (a Dr.Jit array: one component, or several as a ``mi.Spectrum`` or
    ``mi.Point3f``) at ``index``, evaluated one component at a time: on the LLVM backend one
    kernel that gathers three components ran 1.6 to 3 times longer than three kernels that
    gather one each (3 x 10^7 photons put in tree order, three colour channels: 430-1060 ms
    against about 270)."""
    if dr.depth_v(value) > 1:
        parts = []
        for c in range(len(value)):
            part = dr.gather(type(value[c]), value[c], index)
            dr.eval(part)
            parts.append(part)
        return type(value)(*parts)
    out = dr.gather(type(value), value, index)
    dr.eval(out)
    return out


def encode_direction(d):
    """Unit vectors (``mi.Vector3f``) -> ``mi.UInt32`` octahedral codes, 16 bits per
    coordinate (angular error below 0.04 degrees)."""
    d = d / dr.maximum(dr.abs(d.x) + dr.abs(d.y) + dr.abs(d.z), 1e-30)
    su = dr.select(d.x >= 0, 1.0, -1.0)
    sv = dr.select(d.y >= 0, 1.0, -1.0)
    lower = d.z < 0
    u = dr.select(lower, (1 - dr.abs(d.y)) * su, d.x)
    v = dr.select(lower, (1 - dr.abs(d.x)) * sv, d.y)
    qu = mi.UInt32(dr.round((dr.clip(u, -1, 1) * 0.5 + 0.5) * 65535))
    qv = mi.UInt32(dr.round((dr.clip(v, -1, 1) * 0.5 + 0.5) * 65535))
    return qu | (qv << 16)


def decode_direction(code):
    """``mi.UInt32`` octahedral codes -> unit ``mi.Vector3f`` (inverse of
    :func:`encode_direction`)."""
    u = mi.Float(code & 0xFFFF) * (2.0 / 65535.0) - 1.0
    v = mi.Float(code >> 16) * (2.0 / 65535.0) - 1.0
    z = 1.0 - dr.abs(u) - dr.abs(v)
    t = dr.maximum(-z, 0.0)
    x = u + dr.select(u >= 0, -t, t)
    y = v + dr.select(v >= 0, -t, t)
    return dr.normalize(mi.Vector3f(x, y, z))


@dataclass
class Photons:
    """Photons stored on non-delta surfaces, as Dr.Jit arrays of equal width.

    Attributes
    ----------
    points : mi.Point3f
        Where each photon was stored.
    code : mi.UInt32
        Its incident direction (pointing back along the arriving photon), octahedral code.
    flux : mi.Spectrum
        Its power, already divided by N.
    maps : mi.UInt32
        The partial map it belongs to (the map whose emission produced it).
    bounces : mi.UInt32
        Segments from the emitter (1 = direct illumination).
    emitted : int
        N, the photons emitted in total over all maps (also those of maps not traced here).
    map_count : int
        n, the number of partial maps.
    segments : int
        Ray segments traced to make them (one scene intersection each): the tracer's work.
    """

    points: object
    code: object
    flux: object
    maps: object
    bounces: object
    emitted: int
    map_count: int
    segments: int = 0

    def __len__(self) -> int:
        return dr.width(self.maps)

    def take(self, index) -> "Photons":
        """The photons at ``index`` (a ``mi.UInt32`` or an integer / boolean NumPy array)."""
        if not isinstance(index, mi.UInt32):
            index = np.asarray(index)
            if index.dtype == bool:
                index = np.flatnonzero(index)
            index = mi.UInt32(index.astype(np.uint32))
        return Photons(*[dr.gather(type(a), a, index) for a in (
            self.points, self.code, self.flux, self.maps, self.bounces)],
            self.emitted, self.map_count)

    def select(self, mask) -> "Photons":
        """The photons where ``mask`` holds (same N and n)."""
        return self.take(mask)

    def with_maps(self, map_id, map_count: int) -> "Photons":
        """The same photons assigned to other maps (for partition-invariance checks)."""
        if not isinstance(map_id, mi.UInt32):
            map_id = mi.UInt32(np.asarray(map_id).astype(np.uint32))
        return Photons(self.points, self.code, self.flux, map_id, self.bounces, self.emitted,
                       int(map_count), self.segments)

    @property
    def nbytes(self) -> int:
        """Bytes of the arrays on the device."""
        return len(self) * (12 + 4 + 4 * spectrum_channels() + 4 + 4)

    # ---------------------------------------------------------------- host views

    @property
    def position(self) -> np.ndarray:
        """(K, 3) float32 positions."""
        return np.array(self.points, dtype=np.float32).reshape(3, -1).T

    @property
    def direction(self) -> np.ndarray:
        """(K, 3) float32 unit incident directions (decoded)."""
        return np.array(decode_direction(self.code), dtype=np.float32).reshape(3, -1).T

    @property
    def power(self) -> np.ndarray:
        """(K, C) float32 powers."""
        return np.array(self.flux, dtype=np.float32).reshape(spectrum_channels(), -1).T

    @property
    def map_id(self) -> np.ndarray:
        return self.maps.numpy()

    @property
    def bounce(self) -> np.ndarray:
        return self.bounces.numpy()


def empty_photons(emitted: int, map_count: int, segments: int = 0) -> Photons:
    """No photon (a scene where nothing stores them, or no map traced here)."""
    return Photons(dr.zeros(mi.Point3f, 0), dr.zeros(mi.UInt32, 0), dr.zeros(mi.Spectrum, 0),
                   dr.zeros(mi.UInt32, 0), dr.zeros(mi.UInt32, 0), int(emitted),
                   int(map_count), int(segments))
