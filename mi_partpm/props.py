"""Reading and validating integrator parameters (scene-file props or Python keyword arguments).

Every reader takes the value once, checks it on the spot and raises a :class:`ValueError`
that names the parameter, the value received and what is allowed, before any work starts.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

__all__ = ["PhotonMapParams", "read_int", "read_float", "read_bool", "read_choice",
           "read_photon_map_params", "DIRECT_MODES", "UNLIMITED"]

#: ``max_depth`` of -1 (Mitsuba's convention for "no limit") is stored as this.
UNLIMITED = 0xFFFFFFFF

#: How direct illumination is computed (DESIGN.md).
DIRECT_MODES = ("photons", "nee")

def _get(props, name, default):
    return props.get(name, default) if props is not None else default


def read_int(props, name: str, default, low: Optional[int] = None, high: Optional[int] = None,
             allowed: str = "") -> int:
    value = _get(props, name, default)
    what = allowed or _range_text(low, high)
    if isinstance(value, bool) or not isinstance(value, int):
        raise ValueError(f"{name} must be an integer {what}, got {value!r}")
    if (low is not None and value < low) or (high is not None and value > high):
        raise ValueError(f"{name} must be an integer {what}, got {value}")
    return int(value)


def read_float(props, name: str, default, low: Optional[float] = None,
               high: Optional[float] = None, low_open: bool = True,
               high_open: bool = False) -> float:
    value = _get(props, name, default)
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


def read_bool(props, name: str, default: bool) -> bool:
    value = _get(props, name, default)
    if not isinstance(value, bool):
        raise ValueError(f"{name} must be true or false, got {value!r}")
    return value


def read_choice(props, name: str, default: str, choices) -> str:
    value = _get(props, name, default)
    if value not in choices:
        raise ValueError(f"{name} must be one of {', '.join(repr(c) for c in choices)}, "
                         f"got {value!r}")
    return value


def _range_text(low, high) -> str:
    if low is not None and high is not None:
        return f"in [{low}, {high}]"
    if low is not None:
        return f">= {low}"
    if high is not None:
        return f"<= {high}"
    return ""


@dataclass
class PhotonMapParams:
    """The parameters shared by ``partpm`` and ``pm`` (DESIGN.md)."""

    photon_count: int = 100_000
    max_depth: int = UNLIMITED
    rr_depth: int = 5
    seed: int = 0
    direct: str = "photons"
    hide_emitters: bool = False
    radius: Optional[float] = None
    radius_fraction: float = 0.05

    @property
    def photon_depth(self) -> int:
        """max_depth in the photon tracer's terms (-1 for unlimited)."""
        return -1 if self.max_depth == UNLIMITED else self.max_depth


def read_photon_map_params(props, fixed_radius: bool = True) -> PhotonMapParams:
    """Read and check the shared props. Raises ValueError naming the bad one.

    ``fixed_radius=False`` (the kNN integrator ``pm``) leaves ``radius`` and
    ``radius_fraction`` unread, so Mitsuba rejects them as unknown props.
    """
    p = PhotonMapParams()
    p.photon_count = read_int(props, "photon_count", p.photon_count, low=1)
    max_depth = read_int(props, "max_depth", -1, allowed="= -1 (unlimited) or >= 1")
    if max_depth != -1 and max_depth < 1:
        raise ValueError(f"max_depth must be an integer = -1 (unlimited) or >= 1, "
                         f"got {max_depth}")
    p.max_depth = UNLIMITED if max_depth == -1 else max_depth
    p.rr_depth = read_int(props, "rr_depth", p.rr_depth, low=1)
    p.seed = read_int(props, "seed", p.seed, low=0, high=2**63 - 1)
    p.direct = read_choice(props, "direct", p.direct, DIRECT_MODES)
    p.hide_emitters = read_bool(props, "hide_emitters", p.hide_emitters)
    if not fixed_radius:
        return p
    has_radius = props is not None and "radius" in props
    has_fraction = props is not None and "radius_fraction" in props
    if has_radius and has_fraction:
        raise ValueError("give either radius or radius_fraction, not both")
    if has_radius:
        p.radius = read_float(props, "radius", None, low=0.0)
    else:
        p.radius_fraction = read_float(props, "radius_fraction", p.radius_fraction, low=0.0,
                                       high=1.0)
    return p
