"""Progressive photon mapping: each eye path's statistics, updated pass after pass.

Stochastic progressive photon mapping (Hachisuka and Jensen 2009) keeps, for every eye path (a
lane of the camera's wavefront: one pixel sample), a photon count N, a flux tau and a radius
r. Each pass traces new photons and new eye paths; the flux Phi and the count M of the
photons found within r at the path's visible points are added, and r shrinks so that only
the fraction ``alpha`` of the new photons is kept:

    N' = N + alpha M,    r'^2 = r^2 (N + alpha M) / (N + M),    tau' = (tau + Phi) r'^2 / r^2

and the radiance after P passes of N_p photons each is tau / (P N_p pi r^2) (our photon powers
are already divided by N_p, so the N_p drops out). The radius goes to zero and the photon
count to infinity, so the estimate converges.

The partitioned maps fit this scheme: in a pass every eye path has ONE radius, the same in
every map, so the pass's Phi and M are sums over the maps (eq. (2) holds pass by pass) and the
maps stay independent. With the MPI backend one reduction per pass sums Phi and M over the
ranks before the update.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

from .kdtree.radius import MIN_RADIUS, below_min_radius, radius_array

__all__ = ["SPPMState", "sppm_update", "accumulate", "RadianceSum", "radius_schedule",
           "check_first_pass", "check_schedule"]


def sppm_update(N, tau, r2, flux, found, alpha: float):
    """One SPPM update (the module's formulas); lanes with M = 0 keep their state.

    Returns the new (N, tau, r2)."""
    M = mi.Float(found)
    some = M > 0
    N_new = N + alpha * M
    ratio = dr.select(some, N_new / dr.select(some, N + M, 1.0), 1.0)
    r2_new = r2 * ratio
    tau_new = dr.select(some, (tau + flux) * ratio, tau)
    return dr.select(some, N_new, N), tau_new, r2_new


@dataclass
class SPPMState:
    """Per eye path: photon count N, flux tau, squared radius r^2; and the passes done."""

    N: object
    tau: object
    r2: object
    alpha: float
    passes: int = 0
    start_radius: float = 0.0

    @classmethod
    def start(cls, width: int, radius, alpha: float) -> "SPPMState":
        return cls(N=dr.zeros(mi.Float, width), tau=dr.zeros(mi.Spectrum, width),
                   r2=dr.zeros(mi.Float, width) + dr.square(radius_array(radius)), alpha=alpha,
                   start_radius=float(radius))

    @property
    def radius(self):
        """Each path's current radius."""
        return dr.sqrt(self.r2)

    def update(self, flux, found):
        """Add one pass's flux and photon count (summed over every map and rank)."""
        self.N, self.tau, self.r2 = sppm_update(self.N, self.tau, self.r2, flux, found,
                                                self.alpha)
        self.passes += 1
        dr.eval(self.N, self.tau, self.r2)
        self._check_radius()

    def _check_radius(self):
        """A ValueError naming ``alpha`` where an eye path's radius has shrunk below
        :data:`~mi_partpm.kdtree.radius.MIN_RADIUS` (the next pass's queries would refuse
        it). r^2 shrinks by at least alpha a pass, so the paths are looked at only once
        start_radius^2 alpha^passes is below it: with alpha 0.7 and a radius of 0.05, after
        about 150 passes; the radius itself shrinks far slower, as N grows."""
        if self.start_radius <= 0 or 2 * math.log(self.start_radius) + \
                self.passes * math.log(self.alpha) >= 2 * math.log(MIN_RADIUS):
            return
        least = float(dr.sqrt(dr.min(self.r2))[0]) if dr.width(self.r2) else MIN_RADIUS
        if least < MIN_RADIUS:
            raise ValueError(f"alpha = {self.alpha:g} has shrunk an eye path's radius from "
                             f"{self.start_radius:g} to {least:.3g} by pass {self.passes}, "
                             f"{below_min_radius()}: raise alpha (SPPM uses 2/3) or use fewer "
                             f"passes")

    def radiance(self):
        """tau / (P pi r^2): the photon maps' radiance after the passes so far."""
        if self.passes == 0:
            return dr.zeros(mi.Spectrum, dr.width(self.N))
        return self.tau * dr.rcp(dr.opaque(mi.Float, self.passes * dr.pi) * self.r2)


@dataclass
class RadianceSum:
    """Per eye path: the mean over passes of a radiance already normalised per visible point
    (the k-nearest-neighbour estimate, whose radius is not the path's)."""

    total: object
    passes: int = 0

    @classmethod
    def start(cls, width: int) -> "RadianceSum":
        return cls(total=dr.zeros(mi.Spectrum, width))

    def update(self, radiance, found=None):
        self.total = self.total + radiance
        self.passes += 1
        dr.eval(self.total)

    def radiance(self):
        return self.total * dr.rcp(dr.opaque(mi.Float, max(self.passes, 1)))


def accumulate(points, values, found, width: int):
    """Sum every visible point's ``values`` (times its throughput beta) and ``found`` onto its
    eye path; returns (Spectrum, Float) per lane of a wavefront of ``width``.

    The points are added part by part (one part per depth of the paths, where no lane comes
    twice), so no two additions race for one lane and the sums are the same in every run."""
    flux = dr.zeros(mi.Spectrum, width)
    count = dr.zeros(mi.Float, width)
    weighted = points.beta * values
    start = 0
    for size in points.parts or (len(points),):
        if size == 0:
            continue
        index = dr.arange(mi.UInt32, size) + dr.opaque(mi.UInt32, start)
        lane = dr.gather(mi.UInt32, points.lane, index)
        # Distinct lanes: plain adds. Dr.Jit's default mode on the LLVM backend copies a
        # target of up to dr.expand_threshold() entries per thread and compiles its size
        # into the kernel: a new kernel for every count of eye paths.
        distinct = dr.ReduceMode.NoConflicts
        dr.scatter_add(flux, dr.gather(mi.Spectrum, weighted, index), lane, mode=distinct)
        dr.scatter_add(count, mi.Float(dr.gather(type(found), found, index)), lane,
                       mode=distinct)
        dr.eval(flux, count)
        start += size
    return flux, count


def radius_schedule(radius: float, alpha: float, pass_index: int) -> float:
    """The radius of pass ``pass_index`` (0 first) where the photon count per pass is the
    same everywhere: the update above with a constant M, r_i^2 = r_0^2 prod_{j < i}
    alpha (j + 1) / (alpha j + 1). It goes to zero as i^((alpha - 1) / 2) while the photons
    found grow without bound: the radius of estimates that have no eye path of their own
    (a final gather's hits)."""
    return float(radius) * math.exp(_log_shrink(alpha, pass_index) / 2)


#: Passes up to which :func:`_log_shrink` sums the factors' logarithms one by one, for an
#: alpha below :data:`_EXACT_ALPHA` (above it the log-gammas keep 1e-9 of their value).
_SUMMED_PASSES = 4096
_EXACT_ALPHA = 1e-6


def _log_shrink(alpha: float, pass_index: int) -> float:
    """log(r_i^2 / r_0^2) of :func:`radius_schedule`, in logarithms (no underflow):
    Gamma(i + 1) Gamma(1/alpha) / Gamma(i + 1/alpha), whose log-gammas cancel each other's
    digits for a tiny alpha (all of them below about 1e-16), so there, up to
    :data:`_SUMMED_PASSES` passes, the sum of the factors' logarithms (past them a radius is
    far below the least)."""
    if alpha < _EXACT_ALPHA and pass_index <= _SUMMED_PASSES:
        return math.fsum(math.log(alpha * (j + 1)) - math.log1p(alpha * j)
                         for j in range(pass_index))
    return math.lgamma(pass_index + 1) + math.lgamma(1 / alpha) - \
        math.lgamma(pass_index + 1 / alpha)


def check_first_pass(radius: float, alpha: float, name: str = "radius", prop: str = None):
    """A ValueError naming ``alpha`` and ``name`` (and ``prop``, the prop that sets it, where
    ``name`` is not one) where a progressive render's radius would fall below
    :data:`~mi_partpm.kdtree.radius.MIN_RADIUS` in its first pass: an eye path that finds
    photons keeps ``alpha`` of them, and its r^2 shrinks by ``alpha`` then."""
    if float(radius) * float(alpha) ** 0.5 < MIN_RADIUS:
        raise ValueError(f"alpha = {alpha:g} shrinks the {name} {radius:g} to "
                         f"{radius * alpha ** 0.5:.3g} in the first pass, {below_min_radius()}: "
                         f"raise alpha (SPPM uses 2/3) or the {name}"
                         + (f" ({prop})" if prop else ""))


def check_schedule(radius: float, alpha: float, passes: int):
    """A ValueError naming ``alpha`` where :func:`radius_schedule` falls below
    :data:`~mi_partpm.kdtree.radius.MIN_RADIUS` within ``passes`` passes (the final gather's
    radius: a small alpha shrinks it by about alpha times the pass count each pass)."""
    log_r2 = 2 * math.log(radius) + _log_shrink(alpha, passes - 1)
    if log_r2 < 2 * math.log(MIN_RADIUS):
        raise ValueError(f"alpha = {alpha:g} shrinks the final gather's radius {radius:g} to "
                         f"{math.exp(log_r2 / 2):.3g} by pass {passes}, {below_min_radius()}: "
                         f"raise alpha (SPPM uses 2/3) or use fewer passes")
