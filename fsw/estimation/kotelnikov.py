"""Rate from the Kotelnikov (Whittaker–Shannon) series of the field (sedelnikov2023 eq. 9).

The series rebuilds a band-limited B(t) from uniform samples B_k = B(kΔt):

    B(t) = Σ_k B_k sinc((t − t_k)/Δt),   sinc(x) = sin(πx)/(πx),

and differentiates analytically. At the sample times the derivatives are discrete convolutions:

    Ḃ(t_n) = (1/Δt) Σ_{m≠0} (−1)^m / m · B_{n−m}
    B̈(t_n) = (1/Δt²) [−π²/3 · B_n + Σ_{m≠0} 2(−1)^{m+1} / m² · B_{n−m}]

(with sinc'(m) = (−1)^m/m, sinc''(0) = −π²/3, sinc''(m) = 2(−1)^{m+1}/m² for integer m ≠ 0).
sedelnikov2023 then puts Ḃ into its eq. 1–2, the derivative formula ω_k = Ḃ_k × Ḃ_{k−1}/(Δt|Ḃ_k|²)
(`form="paper"`); with the analytic second derivative the same idea holds in continuous time, for
constant ω exactly: Ḃ = B × ω ⊥ ω, B̈ = Ḃ × ω, so ω = (B̈ × Ḃ)/|Ḃ|² (`form="analytic"`, the
default). The Boer formula with the analytic Ḃ gives the perpendicular part ω⊥ = (Ḃ × B)/|B|².

Known weaknesses, and what is done about them:
- Noise: white per-axis noise σ becomes σ_Ḃ = (π/√3) σ/Δt ≈ 1.81 σ/Δt and σ_B̈ = (π²/√5) σ/Δt² ≈
  4.41 σ/Δt² at the samples, uncorrelated with each other at a sample (the kernel of Ḃ is odd, that of B̈
  even); the reported 1-σ propagates these to first order, per axis: ω = (B̈ × Ḃ)/|Ḃ|² has
  ∂ω/∂B̈ = −[Ḃ]ₓ/|Ḃ|², ∂ω/∂Ḃ = ([B̈]ₓ − 2ω Ḃᵀ)/|Ḃ|², so cov ω = σ_B̈² J_B̈ J_B̈ᵀ + σ_Ḃ² J_Ḃ J_Ḃᵀ (an error
  only ⊥Ḃ from B̈; the per-axis split matters: the norm of the error put on every axis covered 86–99 %
  in the accuracy benchmark).
- Edges: the series of a finite record treats the samples outside as zeros, so a record that does not
  start and end at zero rings (Gibbs), worst at the ends and decaying only as 1/distance. The record's
  least-squares line (DC and ramp) is removed first and its derivative added back analytically; the
  remainder is tapered over `edge_samples` at each end by a cosine (Tukey) window, and the estimates
  there are flagged: their σ is multiplied by `edge_sigma_factor`.
- Uniform sampling only: a record whose steps differ by more than `uniform_tol` (relative) is an error
  (resample first).
"""
from __future__ import annotations

import math

import numpy as np
from scipy.signal import fftconvolve

from .rotations import skew


def sinc_derivative_kernels(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Kernels d1[m], d2[m] for m = −(n−1)…(n−1) (index m + n − 1): sinc'(m) and sinc''(m)."""
    m = np.arange(-(n - 1), n, dtype=float)
    d1 = np.zeros_like(m)
    d2 = np.zeros_like(m)
    nz = m != 0
    sign = np.where(np.abs(m) % 2 == 0, 1.0, -1.0)
    d1[nz] = sign[nz] / m[nz]
    d2[nz] = -2.0 * sign[nz] / m[nz] ** 2
    d2[~nz] = -math.pi ** 2 / 3.0
    return d1, d2


def kotelnikov_derivatives(t_s: np.ndarray, b: np.ndarray, *, detrend: bool = True,
                           edge_samples: int = 8) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """B, Ḃ, B̈ at the sample times from the series (with the edge handling of the module docstring)."""
    t, b, dt = _uniform(t_s, b)
    n = len(t)
    tau = (t - t[0]) / dt
    if detrend and n >= 2:
        A = np.column_stack([np.ones(n), tau])
        coef, *_ = np.linalg.lstsq(A, b, rcond=None)
        trend = A @ coef
        slope = coef[1] / dt
    else:
        trend = np.zeros_like(b)
        slope = np.zeros(3)
    r = b - trend
    w = tukey_edges(n, edge_samples)
    r = r * w[:, None]
    d1, d2 = sinc_derivative_kernels(n)
    db = np.column_stack([fftconvolve(r[:, i], d1)[n - 1:2 * n - 1] for i in range(3)]) / dt + slope
    ddb = np.column_stack([fftconvolve(r[:, i], d2)[n - 1:2 * n - 1] for i in range(3)]) / dt ** 2
    return b, db, ddb


def tukey_edges(n: int, edge_samples: int) -> np.ndarray:
    """1 inside, a half cosine over `edge_samples` at each end (0 < w ≤ 1)."""
    w = np.ones(n)
    m = min(edge_samples, n // 2)
    if m > 0:
        ramp = 0.5 * (1.0 - np.cos(math.pi * (np.arange(m) + 1) / (m + 1)))
        w[:m] = ramp
        w[n - m:] = ramp[::-1]
    return w


def kotelnikov_rate(t_s: np.ndarray, b_T: np.ndarray, sigma_b_T: float | None = None, *,
                    form: str = "analytic", detrend: bool = True, edge_samples: int = 8,
                    edge_sigma_factor: float = 10.0) -> tuple[np.ndarray, np.ndarray]:
    """Full rate from the series: ω (N, 3) rad/s and its 1-σ (N, 3) (NaN without `sigma_b_T`).

    `form="analytic"`: ω = (B̈ × Ḃ)/|Ḃ|² at every sample; `form="paper"`: sedelnikov2023 eq. 1,
    ω_k = (Ḃ_k × Ḃ_{k−1})/(Δt|Ḃ_k|²), row 0 NaN. A sample with |Ḃ| at or below its noise (a zero
    field, a field that does not turn) is degenerate: σ = inf, and ω = 0 where the formula divides by
    zero (NaN when no `sigma_b_T` is given).
    """
    if form not in ("analytic", "paper"):
        raise ValueError(f"form must be 'analytic' or 'paper', got {form!r}")
    t, b, dt = _uniform(t_s, b_T)
    _, db, ddb = kotelnikov_derivatives(t, b, detrend=detrend, edge_samples=edge_samples)
    n2 = np.einsum("ij,ij->i", db, db)
    w = np.full(b.shape, np.nan)
    with np.errstate(divide="ignore", invalid="ignore"):
        if form == "analytic":
            w = np.cross(ddb, db) / n2[:, None]
        else:
            w[1:] = np.cross(db[1:], db[:-1]) / (dt * n2[1:, None])
    w[~np.isfinite(w)] = np.nan
    sig = np.full(b.shape, np.nan)
    if sigma_b_T is not None:
        s1 = math.pi / math.sqrt(3.0) * sigma_b_T / dt
        s2 = math.pi ** 2 / math.sqrt(5.0) * sigma_b_T / dt ** 2
        with np.errstate(divide="ignore", invalid="ignore"):
            dn = np.sqrt(n2)
            if form == "analytic":
                sig = _analytic_sigma(db, ddb, np.nan_to_num(w), s1, s2)
            else:
                sig = np.repeat((math.sqrt(2.0) * s1 / (dt * dn))[:, None], 3, axis=1)
            degenerate = ~(np.all(np.isfinite(sig), axis=1) & (dn > s1))
            sig[degenerate] = np.inf
        m = min(edge_samples, len(t) // 2)
        if m:
            sig[:m] *= edge_sigma_factor
            sig[len(t) - m:] *= edge_sigma_factor
        if form == "paper":
            degenerate[0] = False                    # no estimate there: NaN
        w[degenerate & np.isnan(w).any(axis=1)] = 0.0
        sig[np.isnan(w).any(axis=1)] = np.nan
    return w, sig


def _analytic_sigma(db: np.ndarray, ddb: np.ndarray, w: np.ndarray, s1: float, s2: float) -> np.ndarray:
    """Per-axis 1-σ (N, 3) of ω = (B̈ × Ḃ)/|Ḃ|² for white, mutually uncorrelated errors of σ `s1` in Ḃ and
    `s2` in B̈ per axis (module docstring)."""
    n2 = np.einsum("ij,ij->i", db, db)[:, None, None]
    J_dd = -skew(db) / n2
    J_d = (skew(ddb) - 2.0 * w[:, :, None] * db[:, None, :]) / n2
    cov = s2 ** 2 * J_dd @ J_dd.transpose(0, 2, 1) + s1 ** 2 * J_d @ J_d.transpose(0, 2, 1)
    return np.sqrt(np.clip(np.einsum("kii->ki", cov), 0.0, None))


def _uniform(t_s, b, uniform_tol: float = 0.02) -> tuple[np.ndarray, np.ndarray, float]:
    t = np.asarray(t_s, float)
    b = np.asarray(b, float)
    if b.ndim != 2 or b.shape[1] != 3 or t.shape != (b.shape[0],) or len(t) < 3:
        raise ValueError(f"expected t_s (N,) and b (N, 3) with N >= 3, got {t.shape} and {b.shape}")
    steps = np.diff(t)
    dt = float(np.median(steps))
    if not dt > 0 or np.max(np.abs(steps - dt)) > uniform_tol * dt:
        raise ValueError("the Kotelnikov series needs uniform sampling (steps differ by more than "
                         f"{100 * uniform_tol:g} %); resample the record first")
    return t, b, dt


def resample_uniform(t_s: np.ndarray, b: np.ndarray, dt_s: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Linear interpolation of a jittery record onto a uniform grid (default: the median step)."""
    t = np.asarray(t_s, float)
    b = np.asarray(b, float)
    dt = float(np.median(np.diff(t))) if dt_s is None else float(dt_s)
    tu = t[0] + dt * np.arange(int(math.floor((t[-1] - t[0]) / dt + 1e-9)) + 1)
    return tu, np.column_stack([np.interp(tu, t, b[:, i]) for i in range(3)])
