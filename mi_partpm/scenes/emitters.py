"""A catalogue of Mitsuba's emitter plugins in one small scene: a diffuse floor lit by one
emitter of each kind that Mitsuba 3.9.1 ships for the RGB variants.

The tests render every entry with partpm and with an independent reference (Mitsuba's
``path``, or ``ptracer`` where ``path`` cannot see the light), and ``partpm bench`` times the
photon tracer on every entry. The camera looks down at the middle of a 6 x 6 floor, so the
fixed radius never reaches past the floor's edge inside the picture.
"""
from __future__ import annotations

from pathlib import Path

import mitsuba as mi
import numpy as np

__all__ = ["EMITTER_KINDS", "emitter_scene", "write_textures", "reference_integrator"]

#: Every entry, in the order the tests and the benchmark list them.
EMITTER_KINDS = ("area_rectangle", "area_sphere", "area_mesh", "area_textured", "point",
                 "spot", "spot_textured", "directional", "directionalarea", "projector",
                 "projector_bitmap", "projector_scaled", "constant", "envmap",
                 "envmap_rotated", "sunsky")


def write_textures(directory) -> dict:
    """Write the bitmaps the textured entries use (seeded, values up to 1.5) into
    ``directory``; returns their paths by name."""
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(7)
    paths = {"texture": d / "texture.exr", "envmap": d / "envmap.exr"}
    # A smooth pattern: the fixed radius would blur a per-pixel random one.
    y, x = np.mgrid[0:16, 0:24] / 8.0
    pattern = 0.25 + 0.5 * (0.5 + 0.5 * np.sin(3 * x + 2 * y))[..., None] * rng.random(3)
    mi.Bitmap(pattern.astype(np.float32)).write(str(paths["texture"]))
    theta = np.linspace(0, np.pi, 32)[:, None, None]
    sky = (0.3 + 1.2 * np.cos(theta / 2) ** 2) * np.ones((32, 64, 3)) * rng.uniform(0.6, 1, 3)
    mi.Bitmap(sky.astype(np.float32)).write(str(paths["envmap"]))
    return {k: str(v) for k, v in paths.items()}


def _emitter(kind: str, textures: dict) -> dict:
    T = mi.ScalarTransform4f
    down = T().look_at(origin=[0, 2.5, 0.5], target=[0, 0, 0], up=[0, 0, 1])
    panel = T().translate([0, 2, 0]).rotate([1, 0, 0], 90).scale(0.5)
    bitmap = {"type": "bitmap", "filename": textures.get("texture", "")}
    table = {
        "area_rectangle": {"type": "rectangle", "to_world": panel,
                           "emitter": {"type": "area", "radiance": 5.0}},
        "area_sphere": {"type": "sphere", "center": [0, 1.5, 0], "radius": 0.3,
                        "emitter": {"type": "area", "radiance": 5.0}},
        "area_mesh": {"type": "cube", "to_world": T().translate([0, 1.8, 0]).scale(0.25),
                      "emitter": {"type": "area", "radiance": 3.0}},
        "area_textured": {"type": "rectangle", "to_world": panel,
                          "emitter": {"type": "area", "radiance": bitmap}},
        "point": {"type": "point", "position": [0.3, 1.5, 0.2], "intensity": 5.0},
        "spot": {"type": "spot", "to_world": down, "intensity": 10.0, "cutoff_angle": 30},
        "spot_textured": {"type": "spot", "to_world": down, "intensity": 10.0,
                          "cutoff_angle": 30, "texture": bitmap},
        "directional": {"type": "directional", "direction": [0.3, -1, 0.2], "irradiance": 2.0},
        "directionalarea": {"type": "rectangle", "to_world": panel,
                            "emitter": {"type": "directionalarea", "radiance": 5.0}},
        "projector": {"type": "projector", "fov": 30, "irradiance": 1.0, "to_world": down},
        "projector_bitmap": {"type": "projector", "fov": 30, "irradiance": bitmap,
                             "to_world": down},
        "projector_scaled": {"type": "projector", "fov": 30, "irradiance": 1.0,
                             "to_world": down @ T().scale(2.0)},
        "constant": {"type": "constant", "radiance": 1.0},
        "envmap": {"type": "envmap", "filename": textures.get("envmap", "")},
        # Tilted and turned: the sky's bright pole leans towards the floor's side.
        "envmap_rotated": {"type": "envmap", "filename": textures.get("envmap", ""),
                           "to_world": T().rotate([1, 0, 0], 60) @ T().rotate([0, 1, 0], 70)},
        "sunsky": {"type": "sunsky"},
    }
    return table[kind]


def emitter_scene(kind: str, textures: dict, size: int = 32, spp: int = 4) -> mi.Scene:
    """The floor lit by the emitter ``kind`` (one of :data:`EMITTER_KINDS`); ``textures``
    from :func:`write_textures`."""
    if kind not in EMITTER_KINDS:
        raise ValueError(f"emitter kind must be one of {', '.join(EMITTER_KINDS)}, got "
                         f"{kind!r}")
    T = mi.ScalarTransform4f
    return mi.load_dict({
        "type": "scene",
        "sensor": {"type": "perspective", "fov": 35,
                   "to_world": T().look_at(origin=[0, 3, 2], target=[0, 0, 0], up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": size, "height": size,
                            "rfilter": {"type": "box"}},
                   "sampler": {"type": "independent", "sample_count": spp}},
        "floor": {"type": "rectangle", "bsdf": {"type": "diffuse"},
                  "to_world": T().rotate([1, 0, 0], -90).scale(3)},
        "light": _emitter(kind, textures)})


def reference_integrator(kind: str, max_depth: int = 2) -> dict:
    """The independent reference for ``kind``: Mitsuba's ``path``, except for the
    directional area light, whose radiance leaves along one direction only, so that no
    emitter or BSDF sample of ``path`` can reach it; Mitsuba's light tracer ``ptracer``
    renders it instead."""
    if kind == "directionalarea":
        return {"type": "ptracer", "max_depth": max_depth}
    return {"type": "path", "max_depth": max_depth}
