"""The camera side of a render: the film, the sampler and the eye rays, as Mitsuba does them.

:class:`CameraPass` reproduces what Mitsuba's ``SamplingIntegrator::render`` does around an
integrator's ``sample()`` (JIT variants): the sensor's own sampler set to ``spp`` and seeded
with the render's seed over the whole wavefront, samples of a pixel next to each other, the
pixel position jittered by ``next_2d``, the aperture, time and wavelength samples only where
the sensor needs them, ray differentials scaled by 1/sqrt(spp), the ray weight, and a film
block that receives every sample's colour, alpha and weight at the jittered position (the pixel
itself with a box filter). A progressive render draws a new set of eye rays per pass
(``advance``), as Mitsuba's passes do, and puts one value per sample into the film at the end.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from .scenes import check_sensor

__all__ = ["CameraPass"]


class CameraPass:
    """Film, sampler and eye rays of one ``render()`` call (see the module's text)."""

    def __init__(self, scene: mi.Scene, sensor, seed: int, spp: int, aovs=()):
        self.sensor = scene.sensors()[sensor] if isinstance(sensor, int) else sensor
        check_sensor(self.sensor, spp=spp)
        self.film = self.sensor.film()
        self.sampler = self.sensor.sampler()
        if spp:
            self.sampler.set_sample_count(spp)
        self.spp = int(self.sampler.sample_count())
        film_size = np.array(self.film.crop_size(), dtype=np.int64)
        border = self.film.rfilter().border_size() if self.film.sample_border() else 0
        film_size += 2 * border
        self.width = int(film_size[0] * film_size[1] * self.spp)
        if self.width > 0xFFFFFFFF:
            raise ValueError(f"the film ({film_size[0]} x {film_size[1]}) at spp = {self.spp} "
                             f"has {self.width:,} samples, more than one wavefront of 2^32 "
                             f"holds: lower spp or the resolution")
        self.aovs = list(aovs)
        self.film.prepare(self.aovs)
        self.sampler.set_samples_per_wavefront(self.spp)
        self.sampler.seed(seed, self.width)
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
        self.diff_scale = float(np.float32(1) / np.sqrt(np.float32(self.spp)))
        self.sample_pos = None

    def rays(self):
        """This pass's eye rays: ``(ray, weight)``, one per sample (the sampler's state moves
        on). Call :meth:`advance` before the next pass."""
        crop_size = mi.ScalarVector2f(self.film.crop_size())
        scale = dr.rcp(crop_size)
        offset = -mi.ScalarVector2f(self.film.crop_offset()) * scale
        sampler, sensor = self.sampler, self.sensor
        self.sample_pos = self.pixel + sampler.next_2d()
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
        return ray, weight

    def advance(self):
        """On to the next set of samples (a new pass)."""
        self.sampler.advance()
        self.sampler.schedule_state()

    def develop(self, value, alpha, develop: bool = True):
        """Put one ``value`` (Spectrum) and ``alpha`` per sample into the film at the last
        pass's sample positions; return the developed image (or an empty tensor). The film
        is cleared first, so this can be called after any pass (a checkpoint)."""
        film = self.film
        film.prepare(self.aovs)
        block = film.create_block()
        block.set_offset(film.crop_offset())
        block.set_coalesce(block.coalesce() and self.spp >= 4)
        if mi.is_spectral:
            raise ValueError("spectral variants are not supported")
        rgb = mi.Color3f(value.x) if mi.is_monochromatic else value
        channels = [rgb[0], rgb[1], rgb[2]]
        if mi.has_flag(film.flags(), mi.FilmFlags.Alpha):
            channels.append(mi.Float(alpha))
        channels.append(dr.full(mi.Float, 1.0, self.width))
        box = film.rfilter().is_box_filter()
        block.put(self.pixel if box else self.sample_pos, channels, mi.Bool(True))
        film.put_block(block)
        if develop:
            image = film.develop()
            dr.schedule(image)
            return image
        film.schedule_storage()
        return mi.TensorXf()
