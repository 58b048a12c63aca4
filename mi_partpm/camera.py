"""The camera side of a render: the film, the sampler and the eye rays, as Mitsuba does them.

:class:`CameraPass` reproduces what Mitsuba's ``SamplingIntegrator::render`` does around an
integrator's ``sample()`` (JIT variants): the sensor's own sampler set to ``spp`` and seeded
with the render's seed over the whole wavefront, samples of a pixel next to each other, the
pixel position jittered by ``next_2d``, the aperture, time and wavelength samples only where
the sensor needs them, ray differentials scaled by 1/sqrt(spp), the ray weight, and a film
block that receives every sample's colour, alpha and weight at the jittered position (the pixel
itself with a box filter). A progressive render draws a new set of eye rays per pass
(``advance``), as Mitsuba's passes do, and puts one value per sample into the film at the end.

That one value mixes the passes' visible points, which lie at a new position in the pixel each
pass, so a progressive render cannot weigh them by the reconstruction filter at their own
positions: with a filter other than the box it draws each pass's position from the filter
instead (filter importance sampling, as pbrt does) and puts the samples into their own pixel.
A filter with negative lobes (Lanczos, Mitchell, Catmull-Rom) gives the samples drawn there a
weight of -1, carried by the eye ray's weight and the film's weight channel, and one outside
the crop window (unless the film samples its border) a weight of 0, as Mitsuba samples none
there. The image converges to the same filtered image as Mitsuba's, whose samples are uniform
in the pixel and splatted with the filter's weights.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from .scenes import check_sensor

__all__ = ["CameraPass", "MAX_WAVEFRONT", "scene_sensor"]

#: The most camera samples of one render: a wavefront's lanes are indexed with 32 bits.
MAX_WAVEFRONT = 0xFFFFFFFF


def scene_sensor(scene: mi.Scene, sensor):
    """``sensor``: an ``mi.Sensor``, or the index of one of the scene's (a numpy integer
    too, as Mitsuba's ``render`` takes it); anything else a TypeError."""
    if isinstance(sensor, mi.Sensor):
        return sensor
    if isinstance(sensor, (int, np.integer)) and not isinstance(sensor, bool):
        return scene.sensors()[int(sensor)]
    raise TypeError(f"sensor must be an mi.Sensor or the index of one of the scene's "
                    f"sensors, got {sensor!r}")


class CameraPass:
    """Film, sampler and eye rays of one ``render()`` call (see the module's text)."""

    def __init__(self, scene: mi.Scene, sensor, seed: int, spp: int, aovs=(),
                 progressive: bool = False):
        self.sensor = scene_sensor(scene, sensor)
        check_sensor(self.sensor, spp=spp)
        self.film = self.sensor.film()
        self.sampler = self.sensor.sampler()
        if spp:
            self.sampler.set_sample_count(spp)
        self.spp = int(self.sampler.sample_count())
        rfilter = self.film.rfilter()
        # Filter importance sampling: the offsets' distribution (|filter|, per axis), and
        # the box filter that puts each sample into its own pixel.
        self.offsets = _filter_offsets(rfilter) if progressive and \
            not rfilter.is_box_filter() else None
        self.pixel_filter = mi.load_dict({"type": "box"}) if self.offsets is not None \
            else None
        film_size = np.array(self.film.crop_size(), dtype=np.int64)
        border = rfilter.border_size() if self.film.sample_border() and \
            self.offsets is None else 0
        film_size += 2 * border
        self._film_size, self._border = film_size, border
        self.width = int(film_size[0] * film_size[1] * self.spp)
        if self.width > MAX_WAVEFRONT:
            raise ValueError(f"the film ({film_size[0]} x {film_size[1]}) at spp = {self.spp} "
                             f"has {self.width:,} samples, more than one wavefront of 2^32 "
                             f"holds: lower spp or the resolution")
        self.aovs = list(aovs)
        self.film.prepare(self.aovs)
        self.seed = int(seed)
        #: Sets of eye samples the render traces one after the other (:meth:`split`).
        self.sets = 1
        self.diff_scale = float(np.float32(1) / np.sqrt(np.float32(self.spp)))
        self._wavefront()
        self.sample_pos = None
        self.sign = mi.Float(1.0)          # this pass's sample weights (filter signs)
        self.sign_sum = mi.Float(0.0)      # their sum over the passes drawn so far
        self.drawn = 0

    def _wavefront(self):
        """Seed the sampler for a wavefront of ``spp`` samples per pixel and find each
        sample's pixel (samples of a pixel next to each other)."""
        film_size, border = self._film_size, self._border
        self.width = int(film_size[0] * film_size[1] * self.spp)
        self.sampler.set_samples_per_wavefront(self.spp)
        self.sampler.seed(self.seed, self.width)
        idx = dr.arange(mi.UInt32, self.width)
        log_spp = int(np.log2(self.spp)) if self.spp > 0 else 0
        if (1 << log_spp) == self.spp:
            idx >>= dr.opaque(mi.UInt32, log_spp)
        else:
            idx //= dr.opaque(mi.UInt32, self.spp)
        pos = mi.Vector2i(0)
        pos.y = mi.Int32(idx // int(film_size[0]))
        pos.x = mi.Int32(idx - mi.UInt32(pos.y) * int(film_size[0]))
        if border:
            pos -= border
        pos += mi.Vector2i(self.film.crop_offset())
        self.pixel = mi.Vector2f(pos)

    def split(self, per_set: int):
        """Trace the samples in sets of ``per_set`` per pixel (a divisor of spp), as
        Mitsuba's render does with ``samples_per_pass``: the sampler keeps the render's
        sample count (a stratified one spans all of it), each set is a wavefront of its own
        and :meth:`advance` moves the sampler on to the next set's samples. ``spp`` is then
        the samples per pixel of one set; ray differentials stay scaled for the render's."""
        self.sets = self.spp // per_set
        self.spp = per_set
        self._wavefront()

    def rays(self):
        """This pass's eye rays: ``(ray, weight)``, one per sample (the sampler's state moves
        on). Call :meth:`advance` before the next pass."""
        crop_size = mi.ScalarVector2f(self.film.crop_size())
        scale = dr.rcp(crop_size)
        offset = -mi.ScalarVector2f(self.film.crop_offset()) * scale
        sampler, sensor = self.sampler, self.sensor
        if self.offsets is None:
            self.sample_pos = self.pixel + sampler.next_2d()
        else:
            u, rfilter = sampler.next_2d(), self.film.rfilter()
            centre = self.pixel + 0.5
            if not self.film.sample_border():
                # Mitsuba samples the crop window only: each axis's offset is drawn from the
                # part of the filter that keeps the position inside it (a sample drawn
                # outside weighed 0, and a border pixel whose samples all fell there was
                # black, alpha 0).
                low = mi.Vector2f(self.film.crop_offset()) - centre
                high = low + mi.Vector2f(self.film.crop_size())
                u = mi.Vector2f([self._within(u[a], low[a], high[a]) for a in range(2)])
            shift = mi.Vector2f(self.offsets.sample(u.x), self.offsets.sample(u.y))
            self.sample_pos = centre + shift
            self.sign = dr.sign(rfilter.eval(shift.x)) * dr.sign(rfilter.eval(shift.y))
            self.sign_sum = self.sign_sum + self.sign
            dr.schedule(self.sign_sum)
        self.drawn += 1
        adjusted = dr.fma(self.sample_pos, scale, offset)
        aperture = sampler.next_2d() if sensor.needs_aperture_sample() else mi.Point2f(0.5)
        time = mi.Float(sensor.shutter_open())
        if sensor.shutter_open_time() > 0:
            time += sampler.next_1d() * sensor.shutter_open_time()
        wavelength = sampler.next_1d() if mi.is_spectral else mi.Float(0.0)
        ray, weight = sensor.sample_ray_differential(time, wavelength, adjusted, aperture)
        if dr.width(ray.o) < self.width:
            # A sensor whose ray is the same for every sample (a radiancemeter): one ray per
            # sample all the same, or the eye pass would follow one path for all of them.
            zero = dr.zeros(mi.Float, self.width)
            ray.o, ray.d, ray.time = ray.o + zero, ray.d + zero, ray.time + zero
        if ray.has_differentials:
            ray.scale_differential(self.diff_scale)
        if self.offsets is not None:
            weight = weight * self.sign
        return ray, weight

    def _within(self, u, low, high):
        """``u`` in [0, 1) moved into the share of the offsets' distribution that lies in
        [``low``, ``high``) (offsets from the pixel's centre)."""
        r = float(self.film.rfilter().radius())
        a = self.offsets.eval_cdf_normalized(dr.clip(low, -r, r))
        b = self.offsets.eval_cdf_normalized(dr.clip(high, -r, r))
        return dr.minimum(dr.fma(u, b - a, a), dr.one_minus_epsilon(mi.Float))

    def advance(self):
        """On to the next set of samples (a new pass): the sampler seeded anew from the
        render's seed and the pass. Advancing it past its sample count hung Mitsuba's
        stratified and multijitter samplers (at a count that is not a power of two). The
        sets of a :meth:`split` render lie within it: the sampler advances, as in Mitsuba's
        render."""
        if self.sets > 1:
            self.sampler.advance()
            self.sampler.schedule_state()
            return
        seed = (self.seed * 0x9E3779B1 + self.drawn * 0x85EBCA77) & 0xFFFFFFFF
        self.sampler.seed(seed, self.width)
        self.sampler.schedule_state()

    def develop(self, value, alpha, develop: bool = True):
        """Put one ``value`` (Spectrum) and ``alpha`` per sample into the film at the last
        pass's sample positions (into the sample's pixel where the positions were drawn from
        the filter; ``value`` and ``alpha`` then carry the filter signs, and the weight is
        their mean); return the developed image (or an empty tensor). The film is cleared
        first, so this can be called after any pass (a checkpoint)."""
        block = self.block()
        self.put(block, value, alpha)
        return self.finish(block, develop)

    def block(self):
        """An empty image block of the film, for :meth:`put` (the film is cleared)."""
        film = self.film
        film.prepare(self.aovs)
        block = film.create_block()
        if self.offsets is not None:
            block = mi.ImageBlock(block.size(), film.crop_offset(), block.channel_count(),
                                  rfilter=self.pixel_filter)
        block.set_offset(film.crop_offset())
        block.set_coalesce(block.coalesce() and self.spp >= 4)
        return block

    def put(self, block, value, alpha):
        """Add one ``value`` and ``alpha`` per sample of the last set of rays to ``block``
        (blocks of several sets of rays, each drawn after :meth:`advance`, add up: the
        film divides by the weights)."""
        film = self.film
        if mi.is_spectral:
            raise ValueError("spectral variants are not supported")
        rgb = mi.Color3f(value.x) if mi.is_monochromatic else value
        channels = [rgb[0], rgb[1], rgb[2]]
        if mi.has_flag(film.flags(), mi.FilmFlags.Alpha):
            channels.append(mi.Float(alpha))
        if self.offsets is None:
            channels.append(dr.full(mi.Float, 1.0, self.width))
        else:
            channels.append(self.sign_sum * dr.rcp(dr.opaque(mi.Float, max(self.drawn, 1))))
        box = film.rfilter().is_box_filter() or self.offsets is not None
        block.put(self.pixel if box else self.sample_pos, channels, mi.Bool(True))

    def finish(self, block, develop: bool = True):
        """The film holding ``block`` alone (it is cleared first, so this may be called more
        than once), developed (or an empty tensor)."""
        film = self.film
        film.prepare(self.aovs)
        film.put_block(block)
        if develop:
            image = film.develop()
            dr.schedule(image)
            return image
        film.schedule_storage()
        return mi.TensorXf()


_RESOLUTION = 1024         # points of the tabulated filter per axis


def _filter_offsets(rfilter):
    """A distribution of pixel offsets following |filter| on [-radius, radius] (one axis; the
    filters are separable)."""
    r = float(rfilter.radius())
    x = dr.linspace(mi.Float, -r, r, _RESOLUTION)
    return mi.ContinuousDistribution(mi.ScalarVector2f(-r, r), dr.abs(rfilter.eval(x)))
