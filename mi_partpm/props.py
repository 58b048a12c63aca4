"""Checking parameters: plugin props, command-line options and experiment settings alike.

The ``check_*`` functions are the one place where a value is validated: each returns the
value (converted) or raises a :class:`ValueError` that names the parameter, the value received
and what is allowed. The ``read_*`` functions take a prop from Mitsuba's ``Properties`` (or a
default) and check it; the command line (:mod:`mi_partpm.cli`) and the experiment settings
call the same checks, so a bad value reads the same everywhere.

``max_depth`` follows Mitsuba: -1 (:data:`UNLIMITED_DEPTH`) means no limit, and
:func:`segment_limit` is the one conversion to a loop bound.
"""
from __future__ import annotations

import math
import numbers
from dataclasses import dataclass
from typing import Optional

__all__ = ["PhotonMapParams", "check_int", "check_float", "check_bool", "check_choice",
           "read_int", "read_float", "read_bool", "read_choice", "read_photon_map_params",
           "DIRECT_MODES", "UNLIMITED_DEPTH", "segment_limit", "RADIUS_FRACTION",
           "PROGRESSIVE_RADIUS_FRACTION", "MAX_RADIUS", "KERNEL_NAMES", "GLOSSY_MODES",
           "MAX_RAYS_PER_POINT", "PARTPM_ONLY", "PM_ONLY", "refuse_props", "QUALITY_PROPS",
           "PARTPM_QUALITY_PROPS"]

#: ``max_depth`` of -1: no limit (Russian roulette ends the paths), as in Mitsuba.
UNLIMITED_DEPTH = -1

#: Default radius over the longest side of the scene: the paper's 1/20.
RADIUS_FRACTION = 0.05
#: The largest radius a prop may give: its square must be a finite float32 (3.4e38).
MAX_RADIUS = 1e18

#: Default initial radius of a progressive render (passes > 1): the radius only shrinks, so a
#: progressive render starts smaller (measured best of 0.05 / 0.025 / 0.0125 at equal time
#: on the Cornell box: 0.025, with 0.0125 close).
PROGRESSIVE_RADIUS_FRACTION = 0.025

#: How direct illumination is computed: from the photon maps, or by emitter and BSDF
#: sampling weighted by MIS (as Mitsuba's path).
DIRECT_MODES = ("photons", "nee")
#: Density kernels (:data:`mi_partpm.estimate.KERNELS`).
KERNEL_NAMES = ("box", "simpson", "epanechnikov", "cone")
#: What eye paths do at surfaces whose lobes are all glossy or delta: estimate from the map
#: there, or trace on by BSDF sampling to the next surface with a diffuse lobe.
GLOSSY_MODES = ("map", "trace")
#: The most rays from one visible point: of a final gather (Jensen's method uses hundreds
#: to a few thousand) or from a first glossy surface. At 480 x 480 and 4 spp, 4096 rays are
#: 3.8 x 10^9 rays a pass.
MAX_RAYS_PER_POINT = 4096


def segment_limit(max_depth: int) -> int:
    """The loop bound of a path of at most ``max_depth`` segments (-1: effectively none)."""
    return INT32_MAX if max_depth == UNLIMITED_DEPTH else int(max_depth)


def _range_text(low, high) -> str:
    if low is not None and high is not None:
        return f"in [{low}, {high}]"
    if low is not None:
        return f">= {low}"
    if high is not None:
        return f"<= {high}"
    return ""


#: The largest value of a 32-bit signed integer prop (a depth), as Mitsuba reads them.
INT32_MAX = 2**31 - 1


def check_int(name: str, value, low: Optional[int] = None, high: Optional[int] = None,
              allowed: str = "") -> int:
    """``value`` (a Python or NumPy integer) as an int in [low, high]; ``allowed`` replaces
    the range in the message."""
    what = allowed or _range_text(low, high)
    if isinstance(value, float) and value.is_integer() and abs(value) >= 2**63:
        # Mitsuba's properties hold an integer beyond 64 bits as a float (its last digits
        # lost): say so, not a float the user did not write.
        raise ValueError(f"{name} must be an integer {what}, got about {value:.4g} (Mitsuba "
                         f"holds an integer beyond 64 bits as a float)")
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        raise ValueError(f"{name} must be an integer {what}, got {value!r}")
    if (low is not None and value < low) or (high is not None and value > high):
        raise ValueError(f"{name} must be an integer {what}, got {value}")
    return int(value)


def check_float(name: str, value, low: Optional[float] = None, high: Optional[float] = None,
                low_open: bool = True, high_open: bool = False) -> float:
    """``value`` as a finite float between ``low`` and ``high`` (open or closed ends)."""
    lo = "(" if low_open else "["
    hi = ")" if high_open or high is None else "]"
    what = f"in {lo}{'-inf' if low is None else low}, {'inf' if high is None else high}{hi}"
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ValueError(f"{name} must be a finite number {what}, got {value!r}")
    value = float(value)
    ok = math.isfinite(value)
    if ok and low is not None:
        ok = value > low if low_open else value >= low
    if ok and high is not None:
        ok = value < high if high_open else value <= high
    if not ok:
        raise ValueError(f"{name} must be a finite number {what}, got {value}")
    return value


def check_bool(name: str, value) -> bool:
    if not isinstance(value, bool):
        # A scene file's <string name=... value="true"/> reads as the string 'true': say
        # which tag gives a boolean.
        hint = f' (a boolean: <boolean name="{name}" value="{value}"/> in a scene file)' \
            if isinstance(value, str) and value.lower() in ("true", "false") else ""
        raise ValueError(f"{name} must be true or false{hint}, got {value!r}")
    return value


def check_choice(name: str, value, choices):
    if value not in choices:
        raise ValueError(f"{name} must be one of {', '.join(repr(c) for c in choices)}, "
                         f"got {value!r}")
    return value


def _get(props, name, default):
    return props.get(name, default) if props is not None else default


def read_int(props, name: str, default, low: Optional[int] = None, high: Optional[int] = None,
             allowed: str = "") -> int:
    return check_int(name, _get(props, name, default), low, high, allowed)


def read_float(props, name: str, default, low: Optional[float] = None,
               high: Optional[float] = None, low_open: bool = True,
               high_open: bool = False) -> float:
    return check_float(name, _get(props, name, default), low, high, low_open, high_open)


def read_bool(props, name: str, default: bool) -> bool:
    return check_bool(name, _get(props, name, default))


def read_choice(props, name: str, default: str, choices) -> str:
    return check_choice(name, _get(props, name, default), choices)


#: partpm's props, which pm refuses by name.
PARTPM_ONLY = ("radius", "radius_fraction", "map_count", "passes", "alpha", "time_limit",
               "caustic_photon_count", "caustic_radius", "caustic_radius_fraction",
               "final_gather", "maps_per_wave", "backend")
#: pm's props, which partpm refuses by name.
PM_ONLY = ("k", "count_kth", "max_radius")

#: The quality props both photon mappers take (the command line's ``--direct``,
#: ``--kernel``, ``--glossy``, ``--glossy-samples``), and those of partpm alone.
QUALITY_PROPS = ("direct", "kernel", "glossy", "glossy_samples")
PARTPM_QUALITY_PROPS = ("caustic_photon_count", "caustic_radius", "caustic_radius_fraction",
                        "final_gather")


def refuse_props(props, names, owner: str, why: str):
    """A ValueError naming the props of ``names`` given in ``props``, which apply to the
    integrator ``owner`` only (Mitsuba's own message says "unreferenced property in unknown
    plugin"), with ``why``."""
    given = [name for name in names if props is not None and name in props]
    if given:
        raise ValueError(f"{', '.join(given)} appl{'ies' if len(given) == 1 else 'y'} to "
                         f"{owner} only: {why}")


@dataclass
class PhotonMapParams:
    """The parameters shared by ``partpm`` and ``pm``."""

    photon_count: int = 100_000
    max_depth: int = UNLIMITED_DEPTH
    rr_depth: int = 5
    seed: int = 0
    direct: str = "photons"
    hide_emitters: bool = False
    radius: Optional[float] = None
    radius_fraction: Optional[float] = None    # None: RADIUS_FRACTION (or PROGRESSIVE_...)
    kernel: str = "box"
    glossy: str = "map"
    glossy_samples: int = 1


def read_photon_map_params(props, fixed_radius: bool = True) -> PhotonMapParams:
    """Read and check the shared props. Raises ValueError naming the bad one.

    ``fixed_radius=False`` (the kNN integrator ``pm``) leaves ``radius`` and
    ``radius_fraction`` unread, so Mitsuba rejects them as unknown props.
    """
    p = PhotonMapParams()
    p.photon_count = read_int(props, "photon_count", p.photon_count, low=1)
    # Depths are 32-bit signed integers, as for Mitsuba's path.
    p.max_depth = read_int(props, "max_depth", UNLIMITED_DEPTH, high=INT32_MAX,
                           allowed=f"= -1 (unlimited) or in [1, {INT32_MAX}]")
    if p.max_depth != UNLIMITED_DEPTH and p.max_depth < 1:
        raise ValueError(f"max_depth must be an integer = -1 (unlimited) or in [1, {INT32_MAX}], "
                         f"got {p.max_depth}")
    p.rr_depth = read_int(props, "rr_depth", p.rr_depth, low=1, high=INT32_MAX)
    p.seed = read_int(props, "seed", p.seed, low=0, high=2**63 - 1)
    p.direct = read_choice(props, "direct", p.direct, DIRECT_MODES)
    p.hide_emitters = read_bool(props, "hide_emitters", p.hide_emitters)
    p.kernel = read_choice(props, "kernel", p.kernel, KERNEL_NAMES)
    p.glossy = read_choice(props, "glossy", p.glossy, GLOSSY_MODES)
    p.glossy_samples = read_int(props, "glossy_samples", p.glossy_samples, low=1,
                                high=MAX_RAYS_PER_POINT)
    if p.glossy_samples > 1 and p.glossy != "trace":
        raise ValueError(f"glossy_samples = {p.glossy_samples} needs glossy = 'trace' (the "
                         f"samples are the rays traced from a glossy surface)")
    if not fixed_radius:
        return p
    has_radius = props is not None and "radius" in props
    has_fraction = props is not None and "radius_fraction" in props
    if has_radius and has_fraction:
        raise ValueError("give either radius or radius_fraction, not both")
    if has_radius:
        from .kdtree.radius import MIN_RADIUS    # the least radius the queries compare
        p.radius = read_float(props, "radius", None, low=MIN_RADIUS, high=MAX_RADIUS,
                              low_open=False)
    else:
        if has_fraction:
            p.radius_fraction = read_float(props, "radius_fraction", None, low=0.0, high=1.0)
    return p
