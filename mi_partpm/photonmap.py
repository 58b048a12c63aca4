"""Partitioned photon maps: the stored photons of n maps, each map a kd-tree.

:class:`PhotonMaps` joins a :class:`~mi_partpm.kdtree.Forest` (the trees) with the photons'
attributes in tree order, on the device, ready for density estimation.
"""
from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from .kdtree import LEAF_SIZE, Forest, build_forest
from .photons import Photons

__all__ = ["PhotonMaps", "build_photon_maps", "fixed_radius"]


@dataclass
class PhotonMaps:
    """n partial photon maps, ready to query.

    Attributes
    ----------
    forest : Forest
        One balanced kd-tree per map.
    direction : mi.Vector3f
        Incident direction of every photon (towards where it came from), in tree order.
    power16 : half-precision colour array
        Every photon's power divided by ``power_scale``, as float16 (6 bytes in RGB): in
        [0, 1], so no photon overflows and only those below 6e-8 of the brightest underflow.
        :meth:`photon_power` gives it back as ``mi.Spectrum``.
    power_scale : float
        The largest power component of any photon.
    emitted : int
        N, the photons emitted over all maps (powers are already divided by it).

    A photon record on the device is 12 (position, in the forest) + 12 (direction) + 6
    (power) bytes; the surface normal stays on the host (the estimate does not use it).
    """

    forest: Forest
    direction: object
    power16: object
    power_scale: float
    emitted: int

    def photon_power(self, index, active=True):
        """The power of the photons at tree-order ``index`` as ``mi.Spectrum``."""
        value = dr.gather(type(self.power16), self.power16, index, active)
        return mi.Spectrum(value) * dr.opaque(mi.Float, self.power_scale)

    @property
    def map_count(self) -> int:
        return self.forest.map_count

    @property
    def photon_count(self) -> int:
        """Photons stored over all maps."""
        return int(self.forest.points.shape[0])

    @staticmethod
    def bytes_per_photon() -> int:
        """Bytes of one photon record: position and direction (float32), power (float16)."""
        channels = mi.Spectrum.Size if hasattr(mi.Spectrum, "Size") else 3
        return 4 * 6 + 2 * channels

    @property
    def nbytes_per_photon(self) -> int:
        return self.bytes_per_photon()

    @property
    def nbytes(self) -> int:
        """Bytes of the photon records plus the trees."""
        return self.photon_count * self.bytes_per_photon() + self.forest.nbytes


def _vector(a: np.ndarray):
    return mi.Vector3f(a[:, 0], a[:, 1], a[:, 2])


def build_photon_maps(photons: Photons, leaf_size: int = LEAF_SIZE) -> PhotonMaps:
    """Build the kd-tree of every map of ``photons`` and upload the attributes."""
    forest = build_forest(photons.position, photons.map_id.astype(np.int64),
                          photons.map_count, leaf_size)
    order = forest.order
    power = photons.power[order].astype(np.float64)
    scale = float(power.max()) if power.size and power.max() > 0 else 1.0
    half = (power / scale).astype(np.float16)
    if half.shape[1] == 3:
        power16 = mi.Array3f16(half[:, 0], half[:, 1], half[:, 2])
    else:
        power16 = mi.Array1f16(half[:, 0])
    return PhotonMaps(forest=forest, direction=_vector(photons.direction[order]),
                      power16=power16, power_scale=scale, emitted=photons.emitted)


def fixed_radius(scene: mi.Scene, radius, radius_fraction: float) -> float:
    """The fixed radius: ``radius`` if given, else a fraction of the bounding box's longest side."""
    if radius is not None:
        return float(radius)
    extent = scene.bbox().extents()
    longest = float(dr.max(mi.ScalarVector3f(extent)))
    if not longest > 0:
        raise ValueError("the scene's bounding box is empty: give radius explicitly")
    return radius_fraction * longest
