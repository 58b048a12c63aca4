"""Every emitter plugin Mitsuba 3.9.1 ships for the RGB variants traces photons with the right
power: partpm at max_depth 2 (direct light only) against an independent reference on a
diffuse floor (mi_partpm.scenes.emitters)."""
import gc

import numpy as np
import pytest

import mitsuba as mi

from conftest import render, save_failure
from mi_partpm.scenes.emitters import (EMITTER_KINDS, emitter_scene, reference_integrator,
                                       write_textures)
from test_render import small_scene


@pytest.fixture(scope="module")
def textures(tmp_path_factory):
    return write_textures(tmp_path_factory.mktemp("emitter_textures"))


def block_rel_mse(img, ref, block=4):
    """Relative MSE of the images averaged over block x block tiles: the photon and eye
    noise of single pixels averages out, a wrong distribution of light does not. The
    epsilon that keeps dark tiles from dividing by ~0 is 1% of the reference's mean squared,
    so the measure does not depend on how bright the emitter is."""
    h, w = ref.shape[:2]

    def tiles(a):
        return a.reshape(h // block, block, w // block, block, -1).mean(axis=(1, 3))
    a, b = tiles(img), tiles(ref)
    return float(np.mean((a - b) ** 2 / (b ** 2 + 1e-2 * ref.mean() ** 2)))


# Measured with 400k photons, r = 0.05 (half a pixel), 16 spp against 1024 spp, emitters
# hidden: mean ratios 0.989 (rotated envmap) to 1.001, block relMSE 0.00015 (spot) to 0.0051
# (constant sky: its photons are the sparsest). The 3% bound on the mean is the one asked
# for, and with the emitters hidden it is 3% of the photons' light: photons 5% too bright
# read 1.042-1.046 on the sphere and mesh lights (with the emitters in view, 10% too bright
# passed on the sphere, 1.021). 0.02 on the block relMSE is 4x the worst seen, and a black
# image scores about 1. Before directions were normalised,
# the scaled projector's mean ratio was 0.50. (At r = 0.1 the disc blurs the hard edges of
# the projector's and the directional area light's patches over whole tiles: 0.026-0.079.)
# The rotated environment map measured 0.989 (relMSE 0.0046); where its photons left from
# Mitsuba's tilted disc (its sample_ray) the ratio was 2.70 (relMSE 4.1).
@pytest.mark.parametrize("kind", EMITTER_KINDS)
def test_emitter_power_matches_the_reference(kind, textures):
    scene = emitter_scene(kind, textures)
    # Emitters hidden in both: the pixels that see one (up to 77% of the image's light, for
    # the visible sphere) render alike either way and would dilute an error of the photons.
    ref = render(scene, mi.load_dict({**reference_integrator(kind), "hide_emitters": True}),
                 seed=1, spp=1024)
    integrator = mi.load_dict({"type": "partpm", "photon_count": 400_000, "max_depth": 2,
                               "radius": 0.05, "hide_emitters": True})
    img = render(scene, integrator, spp=16)
    ratio, err = img.mean() / ref.mean(), block_rel_mse(img, ref)
    print(f"{kind}: mean ratio {ratio:.4f}, block relMSE {err:.5f}")
    if not (abs(ratio - 1) < 0.03 and err < 0.02):
        where = save_failure(f"emitter_{kind}", partpm=img, reference=ref)
        pytest.fail(f"{kind}: mean ratio {ratio:.4f} (bound 1 +- 0.03), block relMSE "
                    f"{err:.5f} (bound 0.02); images in {where}")
    assert block_rel_mse(np.zeros_like(ref), ref) > 10 * 0.02


def test_an_emitter_with_negative_power_is_named_with_its_type():
    """Mitsuba 3.9.1's timed_sunsky returns negative sample_ray weights (its own path
    integrator fails on it too): the error names the emitter and its type. While a scene
    with a timed_sunsky lives, Mitsuba 3.9.1 cannot render any other scene ("not
    permitted": a symbolic variable evaluated), so the test lets it go before it ends."""
    scene = small_scene([0, 2, 3], [0, 0, 0], size=8,
                        floor={"type": "rectangle", "bsdf": {"type": "diffuse"}},
                        sky={"type": "timed_sunsky"})
    with pytest.raises(Exception) as e:
        render(scene, mi.load_dict({"type": "partpm", "photon_count": 1000}))
    cause = e.value
    while cause.__cause__ is not None:
        cause = cause.__cause__
    message = str(cause)
    del scene, e, cause
    gc.collect()
    assert "emitter 'sky' (TimedSunskyEmitter) emits negative power" in message


def _two_lights(weight):
    return small_scene([0, 2, 3], [0, 0, 0], size=16,
                       floor={"type": "rectangle", "to_world": mi.ScalarTransform4f().rotate(
                           [1, 0, 0], -90).scale(2),
                              "bsdf": {"type": "diffuse"}},
                       panel={"type": "rectangle", "to_world": mi.ScalarTransform4f().translate(
                           [0, 1, 0]).rotate([1, 0, 0], 90).scale(0.3),
                              "emitter": {"type": "area", "radiance": 10.0,
                                          "sampling_weight": weight}},
                       bulb={"type": "point", "position": [0.8, 1.0, 0.3], "intensity": 1.0})


def test_a_sampling_weight_changes_how_many_photons_an_emitter_emits_not_its_light():
    """Mitsuba's sampling_weight picks the emitters in proportion and divides by the choice's
    probability: with the panel's weight at 0.2 the floor is as bright as path's (measured
    1.005 of path at 100k photons, 16 spp; bound 3%, as for every emitter). At 0 the panel
    would emit no photon and its light would be lost without a word (0.507 of path in the
    scene this was found in): refused, naming the emitter and the range."""
    scene = _two_lights(0.2)
    ref = render(scene, mi.load_dict({"type": "path", "hide_emitters": True}), seed=1,
                 spp=1024)
    img = render(scene, mi.load_dict({"type": "partpm", "photon_count": 100_000,
                                      "hide_emitters": True}), spp=16)
    print(f"sampling_weight 0.2: mean ratio {img.mean() / ref.mean():.4f}")
    assert abs(img.mean() / ref.mean() - 1) < 0.03
    with pytest.raises(Exception) as e:
        render(_two_lights(0.0), mi.load_dict({"type": "partpm", "photon_count": 1000}))
    cause = e.value
    while cause.__cause__ is not None:
        cause = cause.__cause__
    assert "emitter on shape 'panel' (AreaLight) has sampling_weight = 0" in str(cause)
    assert "give it a sampling_weight > 0" in str(cause)


def test_an_emitter_whose_texture_cannot_be_sampled_is_named():
    """Mitsuba 3.9.1 evaluates a checkerboard radiance (path renders it) but cannot sample
    emission from it: the error names the emitter and suggests a bitmap."""
    scene = small_scene([0, 2, 3], [0, 0, 0], size=8,
                        floor={"type": "rectangle", "bsdf": {"type": "diffuse"}},
                        panel={"type": "rectangle", "to_world": mi.ScalarTransform4f().translate(
                            [0, 1, 0]).rotate([1, 0, 0], 90),
                               "emitter": {"type": "area", "radiance": {"type": "checkerboard"}}})
    with pytest.raises(Exception) as e:
        render(scene, mi.load_dict({"type": "partpm", "photon_count": 1000}))
    cause = e.value
    while cause.__cause__ is not None:
        cause = cause.__cause__
    assert "emitter on shape 'panel' (AreaLight) cannot emit photons" in str(cause)
    assert "give it a bitmap texture" in str(cause)


def test_a_scaled_environment_map_is_warned_about(textures, caplog):
    """Mitsuba 3.9.1's envmap under a scaled to_world disagrees with itself (path's emitter
    samples brighten with the scale, its BSDF samples do not), so no photon power can match
    both: a warning says so and names the map."""
    scene = small_scene([0, 2, 3], [0, 0, 0], size=8,
                        floor={"type": "rectangle", "bsdf": {"type": "diffuse"}},
                        sky={"type": "envmap", "filename": textures["envmap"],
                             "to_world": mi.ScalarTransform4f().scale(2.0)})
    with caplog.at_level("WARNING", logger="mi_partpm"):
        render(scene, mi.load_dict({"type": "partpm", "photon_count": 1000}))
    assert "environment map 'sky' (EnvironmentMapEmitter) has a to_world that is not a " \
           "rotation" in caplog.text


def _box_far_away(offset, scale):
    """A closed grey box 2 units wide, its light 0.01 under the ceiling, facing down, and the
    camera inside it: everything moved to x = ``offset`` and scaled by ``scale``."""
    T = mi.ScalarTransform4f
    place = T().translate([offset, 0, 0]).scale(scale)

    def wall(to_world):
        return {"type": "rectangle", "to_world": place @ to_world,
                "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.6}}}
    return mi.load_dict({
        "type": "scene",
        "sensor": {"type": "perspective", "fov": 60, "near_clip": 0.01 * scale,
                   "to_world": T().look_at(origin=[offset, 0, 0.95 * scale],
                                           target=[offset, 0, 0], up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 32, "height": 32},
                   "sampler": {"type": "independent", "sample_count": 4}},
        "floor": wall(T().translate([0, -1, 0]).rotate([1, 0, 0], -90)),
        "ceiling": wall(T().translate([0, 1, 0]).rotate([1, 0, 0], 90)),
        "back": wall(T().translate([0, 0, -1])),
        "front": wall(T().translate([0, 0, 1]).rotate([0, 1, 0], 180)),
        "left": wall(T().translate([-1, 0, 0]).rotate([0, 1, 0], 90)),
        "right": wall(T().translate([1, 0, 0]).rotate([0, 1, 0], -90)),
        "light": {"type": "rectangle",
                  "to_world": place @ T().translate([0, 0.99, 0]).rotate([1, 0, 0], 90)
                  .scale(0.3),
                  "emitter": {"type": "area", "radiance": {"type": "rgb", "value": 15}}}})


@pytest.mark.parametrize("offset, scale", [(1000.0, 1.0), (0.0, 1e-3)])
def test_photons_leave_from_the_light_far_from_the_origin_and_in_a_small_scene(offset, scale):
    """Mitsuba's area light starts its rays (1 + max|p|) 8.94e-5 off its surface: 9 cm at
    x = 1000 and as much as 4.5% of a 2 mm box, both more than the 1 cm between the light
    and the ceiling. Photons left from there, and the top of the box, beside the light, was
    0.15-0.45 of path's at x = 1000 and 0.75 in the small box. Direct light only (max_depth
    2), so the top of the image is the light's alone; path samples points on the light
    itself. Both scenes put the offset at 4.5% of the box: before, the top quarter of the
    image was 0.68 of path's in both. Measured now (64 spp against 256, 2 x 10^5 photons,
    r = 1/40 of the box, seeds 0 and 1): top quarter 0.98-0.99 and whole image 1.00-1.01,
    as in the same box at the origin (1.00-1.02, 1.00-1.01). 10% and 5% leave room for the
    noise and the radius's blur at the ceiling's edges."""
    scene = _box_far_away(offset, scale)
    ref = render(scene, mi.load_dict({"type": "path", "max_depth": 2}), spp=256)
    img = render(scene, mi.load_dict({"type": "partpm", "photon_count": 200_000,
                                      "map_count": 4, "radius_fraction": 0.025,
                                      "max_depth": 2}), spp=64)
    top = img[:8].mean() / ref[:8].mean()
    whole = img.mean() / ref.mean()
    if not (abs(top - 1) < 0.1 and abs(whole - 1) < 0.05):
        where = save_failure(f"far_from_origin_{offset:g}_{scale:g}", partpm=img, path=ref)
        pytest.fail(f"top quarter {top:.3f}, whole image {whole:.3f} of path; images in {where}")
