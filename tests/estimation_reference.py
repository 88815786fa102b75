"""Reference implementations the estimation tests check against; the flight and ground code do not use
them: the textbook Kalman steps on (x, P) (Bar-Shalom, Li & Kirubarajan 2001, ch. 5), the error bounds
printed in sedelnikov2024 (eqs. 5 and 10) and the Kotelnikov series summed directly (sedelnikov2023
eq. 9)."""
from __future__ import annotations

import numpy as np

from fsw.estimation import kotelnikov as ko

# --- textbook Kalman steps ---------------------------------------------------------------------------


def predict(x: np.ndarray, P: np.ndarray, F: np.ndarray, Q: np.ndarray,
            fx: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """x⁻ = F x (or `fx`, the nonlinear propagation, for an EKF); P⁻ = F P Fᵀ + Q."""
    return (F @ x if fx is None else np.asarray(fx, float)), F @ P @ F.T + Q


def update(x: np.ndarray, P: np.ndarray, z: np.ndarray, H: np.ndarray, R: np.ndarray,
           hx: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Measurement update; returns (x⁺, P⁺, innovation y, its covariance S).

    y = z − H x (or z − `hx` for an EKF), S = H P Hᵀ + R, K = P Hᵀ S⁻¹, x⁺ = x + K y and the Joseph
    form P⁺ = (I − KH) P (I − KH)ᵀ + K R Kᵀ, which stays symmetric positive semi-definite.
    """
    z = np.asarray(z, float).reshape(-1)
    y = z - (H @ x if hx is None else np.asarray(hx, float).reshape(-1))
    S = H @ P @ H.T + R
    K = np.linalg.solve(S, H @ P).T
    IKH = np.eye(len(x)) - K @ H
    return x + K @ y, IKH @ P @ IKH.T + K @ R @ K.T, y, S


# --- the papers' printed error bounds ------------------------------------------------------------------

def boer_error_bound_eq5(t_s: np.ndarray, b_T: np.ndarray, delta_b_T: float) -> np.ndarray:
    """Per-axis error bound of the Boer formula, sedelnikov2024 eq. 5 (row 0 NaN).

    δω_x = 2δ_B √(B_y² + B_z² + ΔB_y² + ΔB_z²) / (Δt |B|²), and cyclically.
    """
    t, b = np.asarray(t_s, float), np.asarray(b_T, float)
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
    t, b = np.asarray(t_s, float), np.asarray(b_T, float)
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


# --- the Kotelnikov series -----------------------------------------------------------------------------

def kotelnikov_series(t_s: np.ndarray, b: np.ndarray, t_eval: np.ndarray) -> np.ndarray:
    """B(t_eval) from uniform samples by the series itself (eq. 9), direct sum (O(N·M)); (M, 3)."""
    t, b = np.asarray(t_s, float), np.asarray(b, float)
    dt = float(np.median(np.diff(t)))
    x = (np.asarray(t_eval, float)[:, None] - t[None, :]) / dt
    return np.sinc(x) @ b


def kotelnikov_boer_rate(t_s: np.ndarray, b_T: np.ndarray, **kw) -> np.ndarray:
    """Perpendicular rate ω⊥ = (Ḃ × B)/|B|² with the series' analytic Ḃ (fsw's kotelnikov_derivatives)."""
    b = np.asarray(b_T, float)
    _, db, _ = ko.kotelnikov_derivatives(t_s, b, **kw)
    return np.cross(db, b) / np.einsum("ij,ij->i", b, b)[:, None]
