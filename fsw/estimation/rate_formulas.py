"""Body rate from consecutive magnetometer samples: the Boer and derivative formulas.

Convention (physics-and-seeds.md §2): for a field fixed in inertial space,
dB_body/dt = B_body × ω, so ΔB/Δt ≈ B × ω and

- Boer (sedelnikov2024 eq. 1):   ω⊥_k = (ΔB_k × B_k) / (Δt_k · |B_k|²),   ΔB_k = B_k − B_{k−1}.
  Only the part of ω perpendicular to B is observable. The paper prints B_k × ΔB_k, which returns
  −ω⊥ in this convention; :func:`boer_rate_printed` keeps that form for comparison only.
- Derivative (sedelnikov2024 eq. 2, sedelnikov2023 eq. 1–2):
  ω_k = (Ḃ_k × Ḃ_{k−1}) / (Δt_k · |Ḃ_k|²), Ḃ_k = (B_k − B_{k−1}) / Δt_k (difference formula, eq. 6).
  Full vector, exact for constant ω as Δt → 0; biased when ω varies (asymmetric tumbling body) and far
  more sensitive to noise than the Boer formula.

Every function works on arrays of shape (N, 3) (whole recordings) and the streaming classes at the
end run the same kernels one sample at a time in the flight loop. Rows for which a formula has no
value yet (the first sample, or the first two) are NaN in the array forms.

Uncertainty: `*_covariance` propagate white, independent per-axis measurement noise σ_B to first
order (Jacobians below), which is a 1-σ statement; `*_error_bound_eq5/eq10` are the papers'
worst-case bounds for a measurement error ±δ_B.
"""
from __future__ import annotations

import numpy as np

#: Reported 1-σ (rad/s) when a formula has no information (degenerate geometry): wide, finite.
SIGMA_UNOBSERVED_RADPS = 10.0
#: A step whose field change is below this many noise σ is flagged as degenerate.
DEGENERATE_SNR = 1.0


def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrices [v]ₓ for v of shape (..., 3): [v]ₓ u = v × u."""
    s = np.zeros(v.shape[:-1] + (3, 3))
    s[..., 0, 1], s[..., 0, 2] = -v[..., 2], v[..., 1]
    s[..., 1, 0], s[..., 1, 2] = v[..., 2], -v[..., 0]
    s[..., 2, 0], s[..., 2, 1] = -v[..., 1], v[..., 0]
    return s


def _safe_div(num: np.ndarray, den: np.ndarray) -> np.ndarray:
    """num / den[..., None], 0 where den == 0 (callers flag those samples)."""
    den = np.asarray(den, dtype=float)
    out = np.zeros(np.broadcast_shapes(num.shape, den.shape + (3,)))
    ok = den > 0.0
    np.divide(num, den[..., None], out=out, where=ok[..., None])
    return out


# --- kernels on (..., 3) arrays -----------------------------------------------------------------

def boer_kernel(b_prev: np.ndarray, b_k: np.ndarray, dt_s) -> np.ndarray:
    """ω⊥ = (ΔB × B_k) / (Δt |B_k|²)."""
    return _safe_div(np.cross(b_k - b_prev, b_k), np.asarray(dt_s) * np.einsum("...i,...i", b_k, b_k))


def derivative_kernel(b_2: np.ndarray, b_1: np.ndarray, b_k: np.ndarray, dt_prev_s, dt_s) -> np.ndarray:
    """ω = (Ḃ_k × Ḃ_{k−1}) / (Δt_k |Ḃ_k|²) with backward differences Ḃ_k = (B_k − B_{k−1})/Δt_k."""
    d_k = (b_k - b_1) / np.asarray(dt_s)[..., None]
    d_1 = (b_1 - b_2) / np.asarray(dt_prev_s)[..., None]
    return _safe_div(np.cross(d_k, d_1), np.asarray(dt_s) * np.einsum("...i,...i", d_k, d_k))


def boer_jacobians(b_prev: np.ndarray, b_k: np.ndarray, dt_s) -> tuple[np.ndarray, np.ndarray]:
    """∂ω⊥/∂B_{k−1}, ∂ω⊥/∂B_k (each (..., 3, 3)).

    ω⊥ = (B_k × B_{k−1}) / (Δt |B_k|²), so ∂/∂B_{k−1} = [B_k]ₓ / (Δt|B_k|²) and
    ∂/∂B_k = −[B_{k−1}]ₓ / (Δt|B_k|²) − 2 ω⊥ B_kᵀ / |B_k|².
    """
    dt = np.asarray(dt_s, dtype=float)[..., None, None]
    n2 = np.einsum("...i,...i", b_k, b_k)[..., None, None]
    n2 = np.where(n2 > 0, n2, np.inf)
    w = boer_kernel(b_prev, b_k, dt_s)
    j_prev = skew(b_k) / (dt * n2)
    j_k = -skew(b_prev) / (dt * n2) - 2.0 * w[..., :, None] * b_k[..., None, :] / n2
    return j_prev, j_k


def derivative_jacobians(b_2, b_1, b_k, dt_prev_s, dt_s) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """∂ω/∂B_{k−2}, ∂ω/∂B_{k−1}, ∂ω/∂B_k of the derivative formula (each (..., 3, 3)).

    With d_k = Ḃ_k, d_1 = Ḃ_{k−1}: ∂ω/∂d_1 = [d_k]ₓ/(Δt|d_k|²), ∂ω/∂d_k = −[d_1]ₓ/(Δt|d_k|²) − 2ω d_kᵀ/|d_k|²,
    then the chain rule through the backward differences.
    """
    dt = np.asarray(dt_s, dtype=float)[..., None, None]
    dtp = np.asarray(dt_prev_s, dtype=float)[..., None, None]
    d_k = (b_k - b_1) / dt[..., 0]
    d_1 = (b_1 - b_2) / dtp[..., 0]
    n2 = np.einsum("...i,...i", d_k, d_k)[..., None, None]
    n2 = np.where(n2 > 0, n2, np.inf)
    w = derivative_kernel(b_2, b_1, b_k, dt_prev_s, dt_s)
    a_1 = skew(d_k) / (dt * n2)
    a_k = -skew(d_1) / (dt * n2) - 2.0 * w[..., :, None] * d_k[..., None, :] / n2
    return -a_1 / dtp, a_1 / dtp - a_k / dt, a_k / dt


# --- whole-recording forms ----------------------------------------------------------------------

def _check(t_s: np.ndarray, b_T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    t = np.asarray(t_s, dtype=float)
    b = np.asarray(b_T, dtype=float)
    if b.ndim != 2 or b.shape[1] != 3 or t.shape != (b.shape[0],):
        raise ValueError(f"expected t_s (N,) and b_T (N, 3), got {t.shape} and {b.shape}")
    if t.size > 1 and not np.all(np.diff(t) > 0):
        raise ValueError("sample times must be strictly increasing")
    return t, b


def boer_rate(t_s: np.ndarray, b_T: np.ndarray) -> np.ndarray:
    """Boer formula over a recording: (N, 3) perpendicular rate in rad/s, row 0 NaN."""
    t, b = _check(t_s, b_T)
    out = np.full(b.shape, np.nan)
    if len(t) > 1:
        out[1:] = boer_kernel(b[:-1], b[1:], np.diff(t))
    return out


def boer_rate_printed(t_s: np.ndarray, b_T: np.ndarray) -> np.ndarray:
    """The Boer formula exactly as printed in sedelnikov2024 eq. 1/3: (B_k × ΔB)/(Δt|B_k|²).

    Kept only to document the sign problem: in this project's convention it returns −ω⊥.
    """
    t, b = _check(t_s, b_T)
    out = np.full(b.shape, np.nan)
    if len(t) > 1:
        db, bk = b[1:] - b[:-1], b[1:]
        out[1:] = _safe_div(np.cross(bk, db), np.diff(t) * np.einsum("ij,ij->i", bk, bk))
    return out


def derivative_rate(t_s: np.ndarray, b_T: np.ndarray) -> np.ndarray:
    """Derivative formula over a recording: (N, 3) rate in rad/s, rows 0 and 1 NaN."""
    t, b = _check(t_s, b_T)
    out = np.full(b.shape, np.nan)
    if len(t) > 2:
        dt = np.diff(t)
        out[2:] = derivative_kernel(b[:-2], b[1:-1], b[2:], dt[:-1], dt[1:])
    return out


def boer_covariance(t_s: np.ndarray, b_T: np.ndarray, sigma_b_T: float) -> np.ndarray:
    """First-order covariance (N, 3, 3) of :func:`boer_rate` for white per-axis noise σ_B; row 0 NaN."""
    t, b = _check(t_s, b_T)
    out = np.full((len(t), 3, 3), np.nan)
    if len(t) > 1:
        jp, jk = boer_jacobians(b[:-1], b[1:], np.diff(t))
        out[1:] = sigma_b_T**2 * (jp @ jp.swapaxes(-1, -2) + jk @ jk.swapaxes(-1, -2))
    return out


def derivative_covariance(t_s: np.ndarray, b_T: np.ndarray, sigma_b_T: float) -> np.ndarray:
    """First-order covariance (N, 3, 3) of :func:`derivative_rate`; rows 0 and 1 NaN."""
    t, b = _check(t_s, b_T)
    out = np.full((len(t), 3, 3), np.nan)
    if len(t) > 2:
        dt = np.diff(t)
        js = derivative_jacobians(b[:-2], b[1:-1], b[2:], dt[:-1], dt[1:])
        out[2:] = sigma_b_T**2 * sum(j @ j.swapaxes(-1, -2) for j in js)
    return out


def boer_error_bound_eq5(t_s: np.ndarray, b_T: np.ndarray, delta_b_T: float) -> np.ndarray:
    """Per-axis error bound of the Boer formula, sedelnikov2024 eq. 5 (row 0 NaN).

    δω_x = 2δ_B √(B_y² + B_z² + ΔB_y² + ΔB_z²) / (Δt |B|²), and cyclically.
    """
    t, b = _check(t_s, b_T)
    out = np.full(b.shape, np.nan)
    if len(t) > 1:
        bk, db = b[1:], b[1:] - b[:-1]
        s = bk**2 + db**2
        num = np.sqrt(s.sum(axis=1, keepdims=True) - s)  # drop the own axis
        out[1:] = 2.0 * delta_b_T * num / (np.diff(t) * (bk**2).sum(axis=1))[:, None]
    return out


def derivative_error_bound_eq10(t_s: np.ndarray, b_T: np.ndarray, delta_b_T: float) -> np.ndarray:
    """Per-axis error bound of the derivative formula, sedelnikov2024 eq. 10 (rows 0, 1 NaN).

    δω_x = δ* √(ΔB_y,k² + ΔB_z,k² + ΔB_y,k−1² + ΔB_z,k−1²) / (Δt |ΔB_k|²), δ* = 2δ_B + δ_B Δt
    (the paper's δ*, which mixes units of T and T·s; kept as printed with Δt in seconds).
    """
    t, b = _check(t_s, b_T)
    out = np.full(b.shape, np.nan)
    if len(t) > 2:
        dt = np.diff(t)[1:]
        dk, d1 = b[2:] - b[1:-1], b[1:-1] - b[:-2]
        s = dk**2 + d1**2
        num = np.sqrt(s.sum(axis=1, keepdims=True) - s)
        den = dt * (dk**2).sum(axis=1)
        delta_star = 2.0 * delta_b_T + delta_b_T * dt
        with np.errstate(divide="ignore", invalid="ignore"):
            out[2:] = delta_star[:, None] * num / den[:, None]
    return out


# --- streaming forms for the flight loop --------------------------------------------------------

class _StreamBase:
    """Common state of the streaming estimators: latest estimate, 1-σ per axis and flags."""

    #: flags, same bit values as DEBRIS_ESTIMATE_FLAGS in the telemetry dialect
    PERPENDICULAR_ONLY, DEGENERATE, NO_ESTIMATE, DATA_GAP = 1, 2, 4, 8

    def __init__(self, sigma_b_T: float, history: int) -> None:
        if not sigma_b_T > 0:
            raise ValueError(f"sigma_b_T must be > 0, got {sigma_b_T!r}")
        self.sigma_b_T = float(sigma_b_T)
        self.omega_radps = np.zeros(3)
        self.sigma_radps = np.full(3, SIGMA_UNOBSERVED_RADPS)
        self.flags = self.NO_ESTIMATE
        self.t_s = 0.0
        self._t = np.full(history, np.nan)
        self._b = np.zeros((history, 3))
        self._n = 0

    def reset(self) -> None:
        """Forget the history (after a data gap or a sensor re-initialisation)."""
        self._n = 0
        self.omega_radps[:] = 0.0
        self.sigma_radps[:] = SIGMA_UNOBSERVED_RADPS
        self.flags = self.NO_ESTIMATE

    def _push(self, t_s: float, b_T: np.ndarray) -> bool:
        if self._n and not t_s > self._t[-1]:
            return False  # repeated or out-of-order sample: ignored by the caller's contract
        self._t[:-1] = self._t[1:]
        self._b[:-1] = self._b[1:]
        self._t[-1] = t_s
        self._b[-1] = b_T
        self._n = min(self._n + 1, len(self._t))
        self.t_s = t_s
        return True

    def _publish(self, omega: np.ndarray, cov: np.ndarray, degenerate: bool, base_flags: int) -> None:
        flags = base_flags
        sigma = np.sqrt(np.clip(np.diagonal(cov), 0.0, None))
        if degenerate or not (np.all(np.isfinite(omega)) and np.all(np.isfinite(sigma))):
            flags |= self.DEGENERATE
            if not np.all(np.isfinite(omega)):
                omega = np.zeros(3)
            sigma = np.full(3, SIGMA_UNOBSERVED_RADPS)
        self.omega_radps[:] = omega
        self.sigma_radps[:] = np.minimum(sigma, SIGMA_UNOBSERVED_RADPS)
        self.flags = flags


class BoerStream(_StreamBase):
    """Boer formula, one sample at a time; `sigma_b_T` is the per-axis 1-σ of a field sample."""

    def __init__(self, sigma_b_T: float) -> None:
        super().__init__(sigma_b_T, history=2)

    def update(self, t_s: float, b_T: np.ndarray) -> bool:
        """Add a sample; True when a new estimate is available in omega_radps / sigma_radps / flags."""
        if not self._push(t_s, b_T):
            return False
        if self._n < 2:
            return False
        b0, b1 = self._b[0], self._b[1]
        dt = self._t[1] - self._t[0]
        w = boer_kernel(b0, b1, dt)
        jp, jk = boer_jacobians(b0, b1, dt)
        cov = self.sigma_b_T**2 * (jp @ jp.T + jk @ jk.T)
        # a field change within the noise still gives an honest (wide) estimate; only |B| → 0 degenerates
        degenerate = float(np.dot(b1, b1)) < (3.0 * self.sigma_b_T) ** 2
        self._publish(w, cov, degenerate, base_flags=self.PERPENDICULAR_ONLY)
        return True


class DerivativeStream(_StreamBase):
    """Derivative formula, one sample at a time (needs three samples)."""

    def __init__(self, sigma_b_T: float) -> None:
        super().__init__(sigma_b_T, history=3)

    def update(self, t_s: float, b_T: np.ndarray) -> bool:
        if not self._push(t_s, b_T):
            return False
        if self._n < 3:
            return False
        b2, b1, bk = self._b
        dtp, dt = self._t[1] - self._t[0], self._t[2] - self._t[1]
        w = derivative_kernel(b2, b1, bk, dtp, dt)
        js = derivative_jacobians(b2, b1, bk, dtp, dt)
        cov = self.sigma_b_T**2 * sum(j @ j.T for j in js)
        # the formula divides by |ΔB_k|²: below the noise it has no information (ω ∥ B, or ω → 0)
        snr = float(np.linalg.norm(bk - b1) / (np.sqrt(2.0) * self.sigma_b_T))
        self._publish(w, cov, snr < DEGENERATE_SNR, base_flags=0)
        return True
