"""Registration of the integrator plugins with Mitsuba, per variant.

A Python class that subclasses ``mi.SamplingIntegrator`` belongs to the variant that was active
when it was defined. :func:`register` therefore (re)imports the integrator modules under the
active variant - their shared base (``mi_partpm.integrators.common``) first, then each plugin -
and registers their classes; ``import mi_partpm`` calls it and hooks it to every later
``mi.set_variant``.
"""
from __future__ import annotations

import importlib
import re
from pathlib import Path

import mitsuba as mi

__all__ = ["register", "supported_variant", "check_variant", "load_integrator", "PLUGINS"]

#: Plugin name -> (module under mi_partpm.integrators, class name).
PLUGINS = {
    "partpm": ("partpm", "PartPMIntegrator"),
    "pm": ("pm", "PMIntegrator"),
}

#: The modules the plugins' classes derive from, reloaded before the plugins.
BASES = ("common",)


def supported_variant(variant) -> bool:
    """JIT (LLVM or CUDA) variants with RGB or mono colour; not scalar, spectral, polarised."""
    return (variant is not None and variant.split("_")[0] in ("llvm", "cuda")
            and ("_rgb" in variant or "_mono" in variant) and "polarized" not in variant)


def check_variant(variant=None, hint="mi.set_variant('llvm_ad_rgb')"):
    """``variant`` (default: the active one) if the plugins run on it; else a ValueError
    that lists the variants they run on and ends with ``hint``, how to choose one."""
    variant = mi.variant() if variant is None else variant
    if not supported_variant(variant):
        works = [v for v in mi.variants() if supported_variant(v)]
        raise ValueError(f"mi_partpm needs a JIT RGB or mono Mitsuba variant, the active one is "
                         f"{variant!r}; use one of: {', '.join(works)} (e.g. {hint})")
    return variant


def load_integrator(desc: dict):
    """``mi.load_dict(desc)``, where a plugin of this project that refuses a prop (its
    ``ValueError``, which Mitsuba hands on as a RuntimeError holding the traceback's text)
    raises that ValueError, with its message alone; any other error stays as it was (an
    unknown plugin, Mitsuba's own errors)."""
    try:
        return mi.load_dict(desc)
    except RuntimeError as e:
        refused = plugin_refusal(str(e))
        if refused is None:
            raise
        raise ValueError(refused) from None


def plugin_refusal(text: str):
    """The message of the ValueError a plugin of this project raised, from the text of
    Mitsuba's RuntimeError around it (its last line ``ValueError: ...``, its innermost frame
    in this package), or None for any other error."""
    lines = text.strip().splitlines()
    if not lines or not lines[-1].startswith("ValueError: "):
        return None
    frames = re.findall(r'File "([^"]+)"', text)
    integrators = importlib.import_module("mi_partpm.integrators")
    roots = (Path(__file__).resolve().parent, Path(integrators.__file__).resolve().parent)
    if not frames or not any(Path(frames[-1]).resolve().is_relative_to(r) for r in roots):
        return None
    return lines[-1][len("ValueError: "):]


def _unsupported(props):
    check_variant()  # raises: this variant cannot run the plugins


def register():
    """Register every plugin of :data:`PLUGINS` for the active variant."""
    variant = mi.variant()
    if variant is None:
        return
    if not supported_variant(variant):
        for name in PLUGINS:
            mi.register_integrator(name, _unsupported)
        return
    for module_name in BASES:
        _module_for(module_name, variant)
    for name, (module_name, class_name) in PLUGINS.items():
        cls = getattr(_module_for(module_name, variant), class_name)
        mi.register_integrator(name, lambda props, cls=cls: cls(props))


def _module_for(module_name: str, variant: str):
    """``mi_partpm.integrators.<module_name>``, (re)loaded under ``variant``."""
    module = importlib.import_module(f"mi_partpm.integrators.{module_name}")
    if getattr(module, "_variant", None) != variant:
        module = importlib.reload(module)
        module._variant = variant
    return module


def _on_variant_change(old, new):
    register()


_hooked = False


def hook_variant_changes():
    """Re-register the plugins whenever ``mi.set_variant`` changes the variant (once)."""
    global _hooked
    if not _hooked:
        mi.detail.add_variant_callback(_on_variant_change)
        _hooked = True
