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

from .kdtree import LEAF_SIZE, RECORD_FLOATS, Forest, build_forest, tree_bytes
from .kdtree.radius import MIN_RADIUS, below_min_radius, photon_payload
from .photons import Photons, decode_direction, gather_each, spectrum_channels

__all__ = ["PhotonMaps", "build_photon_maps", "fixed_radius", "record_bytes", "map_bytes",
           "power_floats", "POWER_FLOATS"]


@dataclass
class PhotonMaps:
    """n partial photon maps, ready to query.

    Attributes
    ----------
    forest : Forest
        The maps' balanced kd-trees (one per map, or shared by groups of maps: see
        :func:`build_photon_maps`); each photon's record there holds its position and, as
        payload, its incident direction (octahedral code, 2 x 16 bits): one 16-byte load.
    power : mi.Float
        Every photon's power (float32), in tree order: with three colour channels packed as
        :data:`POWER_FLOATS` floats per photon (one 16-byte load, :meth:`photon_power`),
        with one channel one float per photon.
    emitted : int
        N, the photons emitted over all maps (powers are already divided by it).
    bounce : mi.UInt32 or None
        Segments from the emitter to each photon, in tree order, kept only when the render
        bounds the light path's length (``max_depth``): an estimate at the end of an eye path
        of e segments may use only photons of at most ``max_depth - e`` segments.

    A photon on the device is 16 bytes of record (position, direction) + 16 (power, RGB
    and one unused float), and 4 more with ``bounce``.
    """

    forest: Forest
    power: object
    emitted: int
    bounce: object = None

    def photon_power(self, index, active=True):
        """The power of the photons at tree-order ``index`` as ``mi.Spectrum``."""
        if power_floats() == 1:
            return mi.Spectrum(dr.gather(mi.Float, self.power, index, active))
        packed = dr.gather(mi.Vector4f, self.power, index, active)
        return mi.Spectrum(packed.x, packed.y, packed.z)

    def photon_direction(self, index, active=True, code=None):
        """The incident direction of the photons at tree-order ``index`` (unit vectors);
        ``code``: their records' payload, where the caller has read it already."""
        if code is None:
            code = photon_payload(self.forest, index, active)
        return decode_direction(code)

    def photon_bounce(self, index, active=True):
        """Segments from the emitter of the photons at tree-order ``index``."""
        return dr.gather(mi.UInt32, self.bounce, index, active)

    @property
    def map_count(self) -> int:
        return self.forest.map_count

    @property
    def photon_count(self) -> int:
        """Photons stored over all maps."""
        return self.forest.size

    @property
    def bytes_per_photon(self) -> int:
        """Bytes of one photon on the device (see :func:`record_bytes`)."""
        return record_bytes(self.bounce is not None)

    @property
    def map_bytes(self):
        """Bytes of each map: its photon records plus its tree."""
        return self.forest.photon_count.astype(np.int64) * self.bytes_per_photon + \
            self.forest.map_nbytes

    @property
    def nbytes(self) -> int:
        """Bytes of the photon records plus the trees, over all maps."""
        return self.photon_count * self.bytes_per_photon + self.forest.nbytes


#: Floats per photon of the packed power of three colour channels (RGB and one unused): one
#: 16-byte load per photon found. Three arrays of one channel took three gathers: the
#: integrator's estimate at 480 x 480 visible points of the Cornell box (3 x 10^5 photons,
#: r = 1/20) ran in 0.326 s instead of 0.387 (AVX-512), for 4 more bytes per photon.
POWER_FLOATS = 4


def power_floats() -> int:
    """Floats of a photon's power in :attr:`PhotonMaps.power`: :data:`POWER_FLOATS` with
    colour, 1 for a monochrome variant."""
    return POWER_FLOATS if spectrum_channels() > 1 else 1


def pack_power(flux, order):
    """Photon power ``flux`` (``mi.Spectrum``) at ``order``, as :attr:`PhotonMaps.power`
    holds it: RGB and one unused float per photon, or the one channel of a monochrome
    variant. A channel per kernel (one random read each, see
    :func:`~mi_partpm.photons.gather_each`), each written into its place of the packed array.
    :func:`~mi_partpm.kdtree.rows_in_order` would be faster (3.7 x 10^6 photons: 17 against
    39 ms with this function's zero-filled output) but its packed copy of the power lies at
    the render's peak: 10^7 photons emitted peaked at 1.22 against 1.09 GB of Dr.Jit's
    buffers with it."""
    channels = spectrum_channels()
    if channels == 1:
        return gather_each(mi.Float(flux[0] if dr.depth_v(flux) > 1 else flux), order)
    n = dr.width(order)
    out = dr.zeros(mi.Float, POWER_FLOATS * n)
    if n == 0:
        return out
    slot = POWER_FLOATS * dr.arange(mi.UInt32, n)
    for c in range(channels):
        dr.scatter(out, dr.gather(mi.Float, flux[c], order), slot + c)
        dr.eval(out)
    return out


def record_bytes(with_bounce: bool = False) -> int:
    """Bytes of one photon on the device: its record in the forest (position float32 and
    direction code: 16) and its power (:func:`power_floats` float32: 16 bytes with colour),
    and the bounce count (uint32) when the path length is bounded."""
    return 4 * RECORD_FLOATS + 4 * power_floats() + (4 if with_bounce else 0)


def map_bytes(photon_counts, leaf_size: int = LEAF_SIZE):
    """Bytes of maps of ``photon_counts`` photons each (records and tree), e.g. to size a
    request before any photon is traced."""
    counts = np.asarray(photon_counts, dtype=np.int64)
    return counts * record_bytes() + tree_bytes(counts, leaf_size)


def build_photon_maps(photons: Photons, leaf_size: int = LEAF_SIZE,
                      keep_bounce: bool = False, layout: str = "shared") -> PhotonMaps:
    """Build the kd-trees of the maps of ``photons`` and put the attributes in tree order
    (with ``keep_bounce``, also each photon's segment count). Everything stays on the
    device.

    ``layout`` (:data:`~mi_partpm.kdtree.LAYOUTS`): "shared" (default), the maps of one
    process share split planes in groups, so an estimate over all of them descends once per
    group, and each map's photons and estimate stay its own; "separate", every map's tree is
    built from its photons alone, as the paper's processing elements build theirs (what the
    speedup experiment and hwsim's workloads measure)."""
    forest = build_forest(photons.points, photons.maps, photons.map_count, leaf_size,
                          payload=photons.code, layout=layout)
    order = forest.tree_order
    power = pack_power(photons.flux, order)
    bounce = gather_each(photons.bounces, order) if keep_bounce else None
    return PhotonMaps(forest=forest, power=power, emitted=photons.emitted, bounce=bounce)


def fixed_radius(scene: mi.Scene, radius, radius_fraction: float,
                 names=("radius", "radius_fraction"), source: str = None) -> float:
    """The fixed radius: ``radius`` if given, else a fraction of the longest side of the
    shapes' bounding box (:func:`~mi_partpm.scenes.scene_bounds`). ``names``, the props of
    the radius and of the fraction, and ``source``, where the fraction came from (default:
    the fraction prop), name them in the message that refuses a radius below the least. A
    scene without a shape stores no photon, and any radius renders it the same: there the
    fraction itself is returned."""
    from .scenes import scene_size
    if radius is not None:
        return float(radius)
    if not scene.shapes():        # no photon is ever stored: any radius renders the same
        return float(radius_fraction)
    longest = scene_size(scene)
    if not longest > 0:
        raise ValueError("the scene's bounding box is empty: give radius explicitly")
    if radius_fraction * longest < MIN_RADIUS:
        source = source or f"{names[1]} = {radius_fraction:g}"
        subject = {"caustic_radius": "caustic maps' radius"}.get(names[0], names[0])
        raise ValueError(f"the {subject}, {source} of the scene's size {longest:g}, is "
                         f"{radius_fraction * longest:.3g}: {below_min_radius()} (raise "
                         f"{names[1]} or give {names[0]})")
    return radius_fraction * longest
