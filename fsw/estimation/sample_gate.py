"""Plausibility gate between the magnetometer driver and the rate estimators.

A sample the driver delivers is not necessarily a measurement of the field: the chip can saturate
(±8 G full scale, MMC5983MA datasheet p2), freeze (outputs not updated while Meas_M_Done still comes),
or return a corrupted reading (a spike). The rate formulas difference consecutive samples, so one bad
sample spoils two (Boer) or three (derivative) estimates. The gate refuses such samples before the
estimators see them; every refusal is counted by reason and shown in SYS_STATUS.

Tests, on a sample B_k at t_k against the last accepted sample B_p at t_p (Δt = t_k − t_p), with σ
the per-axis 1-σ noise of a sample:

- non-finite: any component NaN/inf;
- saturated: any |B_i| ≥ `saturation_fraction` × full scale (the ADC clips at 0 and 2¹⁸ − 1 counts);
- stuck: B_k bit-identical to the previous delivered sample. With the chip's noise (≥ 0.4 mG RMS ≈ 6.5
  counts per axis at 16384 counts/G) three identical 18-bit axes do not happen by chance;
- spike in magnitude: ||B_k| − |B_p|| > n_σ √2 σ + ρ |B_p| Δt. The geomagnetic field magnitude along
  an orbit changes by at most a factor 2 between equator and pole (dipole), about 0.05 %/s in LEO;
  ρ = `max_rel_change_per_s` (default 0.5 %/s) leaves a factor 10;
- spike in direction: ∠(B_k, B_p) > ω_max Δt + n_σ √2 σ / |B_p|, for a body tumbling at most at
  ω_max = `max_rate_radps` (dB/dt = B × ω turns B by at most |ω| Δt).

The host's own magnetism moves both tests: the sensor measures m = S v + h (v the Earth's field in body
axes, h the hard iron, S the soft iron), so |m| changes with the attitude at up to |ω| |h_eff| with
h_eff = h + (S − I) v, and m turns by up to |ω| Δt (|m| + |h_eff|)/|m|. `host_bound_T` is the bound on
|h_eff| the flight software sets sample by sample: the largest host field it allows for before the
calibration (`fsw.host_calibration`) has one, the calibration's own (with 3 σ) after; 0 (the default)
for a sensor without a host.

After `reseed_after` refusals in a row for spikes, the newest sample becomes the reference (the
earlier reference may have been the bad one, or the body changed its motion).

For the estimators the gate reports `gap_samples`: how many samples are missing before an accepted
one (refused by the gate, or never delivered: the driver re-initialising after a bus fault or a chip
reset), from the step to the previous accepted sample and the nominal sample period. The flight
software flags the next estimates DATA_GAP and widens their σ by :func:`gap_sigma_factor`; after a
gap longer than `reset_after_gap` samples the estimators start afresh.
"""
from __future__ import annotations

import math

import numpy as np

#: MMC5983MA full scale, ±8 G [DS p2]
FULL_SCALE_T = 8e-4


def gap_sigma_factor(gap_samples: int) -> float:
    """σ multiplier for an estimate made across `gap_samples` missing samples: the step is
    (1 + gap) nominal steps, and the truncation error of the finite-difference formulas grows with
    the square of the step (sedelnikov2024 eq. 5 and 10: the bounds grow with ω Δt). Conservative:
    the noise part of σ shrinks with a longer step, the factor ignores that."""
    return float((1 + max(gap_samples, 0)) ** 2)


class SampleGate:
    """Decides, sample by sample, which samples the estimators may use."""

    NON_FINITE, SATURATED, STUCK, SPIKE = 1, 2, 4, 8
    REASONS = {NON_FINITE: "non_finite", SATURATED: "saturated", STUCK: "stuck", SPIKE: "spike"}

    def __init__(self, sigma_b_T: float, sample_period_s: float, *, max_rate_radps: float = math.radians(90.0),
                 max_rel_change_per_s: float = 0.005, n_sigma: float = 6.0,
                 saturation_fraction: float = 0.98, full_scale_T: float = FULL_SCALE_T,
                 reseed_after: int = 3, reset_after_gap: int = 5) -> None:
        if not (sigma_b_T > 0 and sample_period_s > 0):
            raise ValueError("sigma_b_T and sample_period_s must be > 0")
        self.sigma_b_T = float(sigma_b_T)
        self.sample_period_s = float(sample_period_s)
        self.max_rate_radps = float(max_rate_radps)
        self.max_rel_change_per_s = float(max_rel_change_per_s)
        self.n_sigma = float(n_sigma)
        self.saturation_T = float(saturation_fraction * full_scale_T)
        self.reseed_after = int(reseed_after)
        self.reset_after_gap = int(reset_after_gap)
        self.counts = {name: 0 for name in self.REASONS.values()}
        self.accepted = 0
        self.rejected = 0
        self.flags = 0  # reasons of the latest refusal (0: latest sample accepted)
        self.gap_samples = 0  # samples missing before the latest accepted one
        self.in_a_row = 0
        self._spikes_in_a_row = 0
        self._ref_t = math.nan
        self._ref_b = (0.0, 0.0, 0.0)
        self._prev_raw = (math.nan, math.nan, math.nan)
        #: the host's field not removed from the samples (T), see the module's docstring
        self.host_bound_T = 0.0

    @property
    def rejecting(self) -> bool:
        """True while the latest sample was refused (the sensor output is not usable now)."""
        return self.flags != 0

    def check(self, t_s: float, b_T: np.ndarray, b_judged_T: np.ndarray | None = None) -> bool:
        """True when the sample may go to the estimators; else `flags` tells why. `b_judged_T`: the sample
        the spike test judges (the calibrated one; default `b_T`); saturation and a stuck chip are the
        chip's own output's."""
        flags = 0
        bx, by, bz = float(b_T[0]), float(b_T[1]), float(b_T[2])
        jx, jy, jz = (bx, by, bz) if b_judged_T is None else (float(b_judged_T[0]), float(b_judged_T[1]),
                                                              float(b_judged_T[2]))
        if not (math.isfinite(t_s) and math.isfinite(bx) and math.isfinite(by) and math.isfinite(bz)):
            flags = self.NON_FINITE
        else:
            sat = self.saturation_T
            if abs(bx) >= sat or abs(by) >= sat or abs(bz) >= sat:
                flags |= self.SATURATED
            prev = self._prev_raw
            if bx == prev[0] and by == prev[1] and bz == prev[2]:
                flags |= self.STUCK
            if not flags and not math.isnan(self._ref_t) and self._is_spike(t_s, jx, jy, jz):
                flags |= self.SPIKE
            self._prev_raw = (bx, by, bz)
        if flags == self.SPIKE:
            self._spikes_in_a_row += 1
            if self._spikes_in_a_row > self.reseed_after:  # the reference itself is doubtful: move on
                flags = 0
        if flags:
            self.flags = flags
            self.rejected += 1
            self.in_a_row += 1
            for bit, name in self.REASONS.items():
                if flags & bit:
                    self.counts[name] += 1
            return False
        self._spikes_in_a_row = 0
        self.flags = 0
        self.in_a_row = 0
        self.accepted += 1
        if math.isnan(self._ref_t):
            self.gap_samples = 0
        else:
            self.gap_samples = max(0, int(round((t_s - self._ref_t) / self.sample_period_s)) - 1)
        self._ref_t = float(t_s)
        self._ref_b = (jx, jy, jz)
        return True

    def _is_spike(self, t_s: float, bx: float, by: float, bz: float) -> bool:
        dt = max(t_s - self._ref_t, 0.0)
        px, py, pz = self._ref_b
        np_ = math.sqrt(px * px + py * py + pz * pz)
        nk = math.sqrt(bx * bx + by * by + bz * bz)
        noise = self.n_sigma * math.sqrt(2.0) * self.sigma_b_T
        host = self.host_bound_T
        turn = self.max_rate_radps * dt
        if abs(nk - np_) > noise + self.max_rel_change_per_s * np_ * dt + min(2.0 * host, turn * host):
            return True
        if np_ <= noise or nk <= noise:
            return False  # direction undefined near zero field
        cos = (bx * px + by * py + bz * pz) / (nk * np_)
        angle = math.acos(min(1.0, max(-1.0, cos)))
        return angle > turn * (1.0 + host / np_) + noise / np_

    def rebase(self, b_T: np.ndarray) -> None:
        """The reference sample re-expressed (the same last accepted sample, calibrated anew)."""
        if not math.isnan(self._ref_t):
            self._ref_b = (float(b_T[0]), float(b_T[1]), float(b_T[2]))

    def reset(self) -> None:
        """Forget the reference (a new sensor configuration): the next finite sample is accepted."""
        self._ref_t = math.nan
        self._prev_raw = (math.nan, math.nan, math.nan)
        self._spikes_in_a_row = 0


def mark_gap(est, gap_samples: int) -> None:
    """Flag a streaming estimator's latest estimate DATA_GAP and widen its σ (`gap_sigma_factor`),
    never beyond the 'no information' σ."""
    from .rate_formulas import SIGMA_UNOBSERVED_RADPS

    est.flags |= est.DATA_GAP
    np.minimum(est.sigma_radps * gap_sigma_factor(gap_samples), SIGMA_UNOBSERVED_RADPS, out=est.sigma_radps)
