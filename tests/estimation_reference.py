"""Reference implementations the estimation tests check the flight code against (not flown, not used by
the flight code): the textbook Kalman steps on (x, P) (Bar-Shalom, Li & Kirubarajan 2001, ch. 5)."""
from __future__ import annotations

import numpy as np


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
