"""mi-partpm: partitioned photon maps for Mitsuba 3.

``import mi_partpm`` registers the ``partpm`` integrator plugin for the active Mitsuba variant
(and again whenever the variant changes), so scene files can say
``<integrator type="partpm">``.
"""
from __future__ import annotations

from . import plugins
from .scenes import load_scene, scene_names

__version__ = "0.1.0"
__all__ = ["register", "load_scene", "scene_names", "__version__"]

register = plugins.register

plugins.hook_variant_changes()
register()
