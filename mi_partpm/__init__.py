"""mi-partpm: partitioned photon maps for Mitsuba 3.

``import mi_partpm`` registers the integrator plugins ``partpm`` (partitioned photon maps) and
``pm`` (the conventional k-nearest-neighbour photon mapper) for the active Mitsuba variant, and
again whenever the variant changes, so scene files can say ``<integrator type="partpm">``.
Its warnings and progress lines go to Mitsuba's log and follow ``mi.set_log_level`` (unless
the application set up Python's logging: :mod:`.logs`).

The renderer's core lives in this package's modules, named after the algorithm's phases
(:mod:`.trace`, :mod:`.kdtree`, :mod:`.photonmap`, :mod:`.eyepath`, :mod:`.estimate`,
:mod:`.backends`); the paper's experiments are in :mod:`.experiments`, the command line in
:mod:`.cli`. The README's "How it is built" section maps the whole layout.
"""
from __future__ import annotations

from . import logs, plugins
from .scenes import load_scene, scene_names

__version__ = "0.1.0"
__all__ = ["register", "load_scene", "scene_names", "__version__"]

register = plugins.register

logs.install()
plugins.hook_variant_changes()
register()
