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
    direction, power, normal : Dr.Jit arrays
        Photon attributes in the forest's tree order (``mi.Vector3f``, ``mi.Spectrum``,
        ``mi.Vector3f``).
    emitted : int
        N, the photons emitted over all maps (powers are already divided by it).
    """

    forest: Forest
    direction: object
    power: object
    normal: object
    emitted: int

    @property
    def map_count(self) -> int:
        return self.forest.map_count

    @property
    def photon_count(self) -> int:
        """Photons stored over all maps."""
        return int(self.forest.points.shape[0])

    @staticmethod
    def bytes_per_photon() -> int:
        """Bytes of one photon record: position, direction, power, normal (float32)."""
        channels = mi.Spectrum.Size if hasattr(mi.Spectrum, "Size") else 3
        return 4 * (9 + channels)

    @property
    def nbytes_per_photon(self) -> int:
        return self.bytes_per_photon()

    @property
    def nbytes(self) -> int:
        """Bytes of photons (position, direction, power, normal, float32) plus trees."""
        return self.photon_count * self.bytes_per_photon() + self.forest.nbytes


def _vector(a: np.ndarray):
    return mi.Vector3f(a[:, 0], a[:, 1], a[:, 2])


def build_photon_maps(photons: Photons, leaf_size: int = LEAF_SIZE) -> PhotonMaps:
    """Build the kd-tree of every map of ``photons`` and upload the attributes."""
    forest = build_forest(photons.position, photons.map_id.astype(np.int64),
                          photons.map_count, leaf_size)
    order = forest.order
    power = photons.power[order]
    if power.shape[1] == 3:
        spectrum = mi.Spectrum(power[:, 0], power[:, 1], power[:, 2])
    else:
        spectrum = mi.Spectrum(power[:, 0])
    return PhotonMaps(forest=forest, direction=_vector(photons.direction[order]),
                      power=spectrum, normal=_vector(photons.normal[order]),
                      emitted=photons.emitted)


def fixed_radius(scene: mi.Scene, radius, radius_fraction: float) -> float:
    """The fixed radius: ``radius`` if given, else a fraction of the bounding box's longest side."""
    if radius is not None:
        return float(radius)
    extent = scene.bbox().extents()
    longest = float(dr.max(mi.ScalarVector3f(extent)))
    if not longest > 0:
        raise ValueError("the scene's bounding box is empty: give radius explicitly")
    return radius_fraction * longest
