"""The profile of the fit's cost along the tensor's scale, and the interval it gives.

The free motion of a tumbling body does not depend on the tensor's scale; only the response to the known
torque does. A long record's cost along the scale is then not the parabola its curvature at the minimum
describes: on mission records it was flat over a few % around a minimum whose curvature said ±0.8 %
(seed 4's first experiment: Δχ² of 2.5 and 0.7 at Ixx 2 % below and above the fit, where the curvature
puts 24), and the truth lay 6 of the curvature's σ away but inside the profile's interval.

Rule: with Ixx held at each of the fit's value times `FitOptions.scale_profile` (the other parameters
fitted again, from the minimum scaled), the profile Δχ²(Ixx) = (cost − minimum)/s² is taken; its
95 % interval is where Δχ² stays below χ²₁(0.95) = 3.84 (linear between the points, beyond the last one
the parabola through it). When that interval is wider than the curvature's, the tensor's variance along
its scale (p pᵀ: all components scale together) is raised until Ixx's interval is the profile's. A profile
point whose cost is below the minimum's is a better fit: the fit continues from it.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .. import inertia as inr

#: χ²₁ at 95 %: the square of the two-sided normal quantile
CHI2_1_95 = inr.z_value(0.95) ** 2


@dataclass(frozen=True)
class ScaleProfile:
    """The profile of one run: Ixx of each point [kg·m²] and its Δχ² (in units of the fit's s²), the
    relative 95 % half-widths below and above the minimum's Ixx, and the curvature's."""

    ixx_kgm2: np.ndarray
    delta_chi2: np.ndarray
    ixx_min_kgm2: float
    half_widths: tuple[float, float]
    curvature_half_width: float

    @property
    def ratio(self) -> float:
        """How much wider the profile's interval is than the curvature's (≥ 0)."""
        if not self.curvature_half_width > 0:
            return 1.0
        return max(self.half_widths) / self.curvature_half_width


def half_width(x: np.ndarray, d: np.ndarray, x0: float, side: int, threshold: float = CHI2_1_95) -> float:
    """Where the profile (points `x`, Δχ² `d`) first reaches `threshold` on `side` (−1, +1) of its minimum
    `x0` (Δχ² 0), relative to `x0`: linear between the points, the parabola through the farthest beyond."""
    on = np.flatnonzero(np.sign(x - x0) == side)
    order = on[np.argsort(np.abs(x[on] - x0))]
    px, pd = 0.0, 0.0
    for i in order:
        dx, di = abs(x[i] - x0) / abs(x0), max(float(d[i]), 0.0)
        if di >= threshold:
            return px + (dx - px) * (threshold - pd) / (di - pd)
        px, pd = dx, di
    if px == 0.0:
        return math.inf
    return px * math.sqrt(threshold / pd) if pd > 0 else math.inf


def profile_of(ixx_kgm2: np.ndarray, cost: np.ndarray, ixx_min_kgm2: float, cost_min: float, s2: float,
               curvature_half_width: float) -> ScaleProfile:
    """The :class:`ScaleProfile` of points `ixx_kgm2` with costs `cost` (data + prior, χ² units) about the
    minimum (`ixx_min_kgm2`, `cost_min`), the fit's s² = χ²/dof."""
    x = np.asarray(ixx_kgm2, float)
    d = (np.asarray(cost, float) - cost_min) / max(s2, 1e-12)
    d = np.where(np.isfinite(d), d, math.inf)
    return ScaleProfile(x, d, float(ixx_min_kgm2), (half_width(x, d, ixx_min_kgm2, -1),
                                                   half_width(x, d, ixx_min_kgm2, +1)),
                        float(curvature_half_width))


def widened_cov(p: np.ndarray, cov_p: np.ndarray, prof: ScaleProfile) -> np.ndarray:
    """`cov_p` (6, 6) with its variance along the scale (p pᵀ) raised so that Ixx's 95 % half-width is the
    profile's where that is the wider (unchanged otherwise; an unbounded profile is left to the curvature)."""
    ratio = prof.ratio
    if not (ratio > 1.0 and math.isfinite(ratio)):
        return cov_p
    p = np.asarray(p, float)
    v_rel = float(cov_p[0, 0]) / float(p[0]) ** 2
    return cov_p + (ratio * ratio - 1.0) * v_rel * np.outer(p, p)
