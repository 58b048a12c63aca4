"""Partitioned photon maps: the stored photons of n maps, each map a kd-tree.

:class:`PhotonMaps` joins a :class:`~mi_partpm.kdtree.Forest` (the trees) with the photons'
attributes in tree order, on the device, ready for density estimation. It is the one place that
counts a map's bytes (:meth:`PhotonMaps.map_bytes`, :func:`record_bytes`): the memory guard,
the benchmarks, the workloads that hwsim replays and the statistics all read them here.
"""
from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from .kdtree import LEAF_SIZE, Forest, build_forest, tree_bytes
from .trace import Photons

__all__ = ["PhotonMaps", "build_photon_maps", "fixed_radius", "record_bytes", "map_bytes"]


@dataclass
class PhotonMaps:
    """n partial photon maps, ready to query.

    Attributes
    ----------
    forest : Forest
        One balanced kd-tree per map.
    direction32 : mi.UInt32
        Incident direction of every photon (towards where it came from), in tree order,
        octahedral-encoded in 2 x 16 bits (angular error below 0.04 degrees);
        :meth:`photon_direction` decodes it.
    power : mi.Spectrum
        Every photon's power (float32), in tree order.
    emitted : int
        N, the photons emitted over all maps (powers are already divided by it).
    bounce : mi.UInt32 or None
        Segments from the emitter to each photon, in tree order, kept only when the render
        bounds the light path's length (``max_depth``): an estimate at the end of an eye path
        of e segments may use only photons of at most ``max_depth - e`` segments.

    A photon record on the device is 12 (position, in the forest) + 4 (direction) + 12
    (power, RGB) bytes, and 4 more with ``bounce``; the surface normal stays on the host
    (the estimate does not use it).
    """

    forest: Forest
    direction32: object
    power: object
    emitted: int
    bounce: object = None

    def photon_bounce(self, index, active=True):
        """Segments from the emitter of the photons at tree-order ``index``."""
        return dr.gather(mi.UInt32, self.bounce, index, active)

    def photon_power(self, index, active=True):
        """The power of the photons at tree-order ``index`` as ``mi.Spectrum``."""
        return dr.gather(mi.Spectrum, self.power, index, active)

    def photon_direction(self, index, active=True):
        """The incident direction of the photons at tree-order ``index`` (unit vectors)."""
        return decode_direction(dr.gather(mi.UInt32, self.direction32, index, active))

    @property
    def map_count(self) -> int:
        return self.forest.map_count

    @property
    def photon_count(self) -> int:
        """Photons stored over all maps."""
        return int(self.forest.points.shape[0])

    @property
    def bytes_per_photon(self) -> int:
        """Bytes of one photon record on the device (see :func:`record_bytes`)."""
        return record_bytes(self.bounce is not None)

    @property
    def map_bytes(self):
        """Bytes of each map: its photon records plus its tree."""
        return self.forest.photon_count.astype(np.int64) * self.bytes_per_photon + \
            self.forest.map_nbytes

    @property
    def nbytes(self) -> int:
        """Bytes of the photon records plus the trees, over all maps."""
        return int(self.map_bytes.sum())


def record_bytes(with_bounce: bool = False) -> int:
    """Bytes of one photon record on the device: position and power (float32, one float per
    colour channel of the variant), direction (2 x 16 bits), and the bounce count (uint32)
    when the path length is bounded."""
    channels = mi.Spectrum.Size if hasattr(mi.Spectrum, "Size") else 3
    return 12 + 4 + 4 * channels + (4 if with_bounce else 0)


def map_bytes(photon_counts, leaf_size: int = LEAF_SIZE):
    """Bytes of maps of ``photon_counts`` photons each (records and tree), e.g. to size a
    request before any photon is traced."""
    counts = np.asarray(photon_counts, dtype=np.int64)
    return counts * record_bytes() + tree_bytes(counts, leaf_size)


def encode_direction(d: np.ndarray) -> np.ndarray:
    """Unit vectors (K, 3) -> uint32 octahedral codes (16 bits per coordinate)."""
    d = np.asarray(d, np.float64)
    d = d / np.maximum(np.abs(d).sum(axis=1, keepdims=True), 1e-30)
    u, v, z = d[:, 0], d[:, 1], d[:, 2]
    su, sv = np.where(u >= 0, 1.0, -1.0), np.where(v >= 0, 1.0, -1.0)
    lower = z < 0
    u, v = np.where(lower, (1 - np.abs(v)) * su, u), np.where(lower, (1 - np.abs(u)) * sv, v)
    qu = np.rint((np.clip(u, -1, 1) * 0.5 + 0.5) * 65535).astype(np.uint32)
    qv = np.rint((np.clip(v, -1, 1) * 0.5 + 0.5) * 65535).astype(np.uint32)
    return qu | (qv << 16)


def decode_direction(code):
    """uint32 octahedral codes (Dr.Jit) -> unit ``mi.Vector3f`` (inverse of encode)."""
    u = mi.Float(code & 0xFFFF) * (2.0 / 65535.0) - 1.0
    v = mi.Float(code >> 16) * (2.0 / 65535.0) - 1.0
    z = 1.0 - dr.abs(u) - dr.abs(v)
    t = dr.maximum(-z, 0.0)
    x = u + dr.select(u >= 0, -t, t)
    y = v + dr.select(v >= 0, -t, t)
    return dr.normalize(mi.Vector3f(x, y, z))


def build_photon_maps(photons: Photons, leaf_size: int = LEAF_SIZE,
                      keep_bounce: bool = False) -> PhotonMaps:
    """Build the kd-tree of every map of ``photons`` and upload the attributes (with
    ``keep_bounce``, also each photon's segment count)."""
    forest = build_forest(photons.position, photons.map_id.astype(np.int64),
                          photons.map_count, leaf_size)
    order = forest.order
    power = photons.power[order]
    if power.shape[1] == 3:
        spectrum = mi.Spectrum(power[:, 0], power[:, 1], power[:, 2])
    else:
        spectrum = mi.Spectrum(power[:, 0])
    return PhotonMaps(forest=forest,
                      direction32=mi.UInt32(encode_direction(photons.direction[order])),
                      power=spectrum, emitted=photons.emitted,
                      bounce=mi.UInt32(photons.bounce[order].astype(np.uint32))
                      if keep_bounce else None)


def fixed_radius(scene: mi.Scene, radius, radius_fraction: float) -> float:
    """The fixed radius: ``radius`` if given, else a fraction of the bounding box's longest side."""
    if radius is not None:
        return float(radius)
    extent = scene.bbox().extents()
    longest = float(dr.max(mi.ScalarVector3f(extent)))
    if not longest > 0:
        raise ValueError("the scene's bounding box is empty: give radius explicitly")
    return radius_fraction * longest
