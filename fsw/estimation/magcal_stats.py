"""The sufficient statistics of the host-magnetics calibration's fit (`fsw.estimation.magcal`).

Per sample, the residual is e = z − aᵀφ = ãᵀ(φ, 1) with ã = (−a, z) = P (m(B) ⊗ τ(t)) − |B_model|² e_z,
m(B) the ten monomials of B of degree ≤ 2 and τ(t) = (1) for a constant host, (1, cos ωt, sin ωt) with
the hard iron's drift (ω = 2π / its period). So Σ w e² needs only Σ w τ_k τ_l m mᵀ (monomials of degree
≤ 4: 35 sums per pair k, l), Σ w |B_model|² τ_k m and Σ w |B_model|⁴. With noise in B these are biased
(the regressors are noisy: an errors-in-variables problem, which shrinks the scale by ~σ²/|B|², several
σ of D after an orbit). The adjusted least squares (Kukush, Markovsky & Van Huffel 2004, consistent
ellipsoid fitting) replaces each monomial by its Hermite polynomial in the noise — E[Heₚ(x + ε)] = xᵖ
for Gaussian ε; τ(t) is exact — so the sums estimate the noise-free ones; the raw sums are kept for the
residual test. Units: µT.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: parameters θ = (b, D's 6 unique terms) and linear parameters φ = (c, E's 6 unique terms, μ) of a constant host
N_THETA = 9
N_PHI = 10

_M2 = ((0, 0, 0), (1, 0, 0), (0, 1, 0), (0, 0, 1), (2, 0, 0), (0, 2, 0), (0, 0, 2), (1, 1, 0), (1, 0, 1), (0, 1, 1))
_M4 = tuple(sorted({tuple(p + q for p, q in zip(a, b)) for a in _M2 for b in _M2}, key=lambda e: (sum(e), e)))
_M4_INDEX = {e: k for k, e in enumerate(_M4)}
_PROD = np.array([[_M4_INDEX[tuple(p + q for p, q in zip(a, b))] for b in _M2] for a in _M2])
_M2_IN_M4 = np.array([_M4_INDEX[e] for e in _M2])
_EXP = np.array(_M4)
# ã = P m(B) − |B_model|² e₁₀ for a constant host
_P = np.zeros((N_PHI + 1, len(_M2)))
for _row, _col, _v in ((0, 1, -2.0), (1, 2, -2.0), (2, 3, -2.0), (3, 4, 1.0), (4, 5, 1.0), (5, 6, 1.0), (6, 7, 2.0),
                       (7, 8, 2.0), (8, 9, 2.0), (9, 0, 1.0), (10, 4, 1.0), (10, 5, 1.0), (10, 6, 1.0)):
    _P[_row, _col] = _v


def n_phi(n_tau: int) -> int:
    """Linear parameters: c, E, μ, and (c_k, μ_k) for each harmonic term k ≥ 1."""
    return N_PHI + 4 * (n_tau - 1)


def n_theta(n_tau: int) -> int:
    """Parameters: b, D's unique terms, and β_k (3) for each harmonic term k ≥ 1."""
    return N_THETA + 3 * (n_tau - 1)


def _p_matrix(n_tau: int) -> np.ndarray:
    """ã = P (m ⊗ τ) − |B_model|² e_z; columns in np.kron order (monomial i, term k) → i·n_tau + k."""
    nphi, nm = n_phi(n_tau), len(_M2)
    P = np.zeros((nphi + 1, nm * n_tau))
    cols = np.arange(nm) * n_tau
    P[:N_PHI, cols] = _P[:N_PHI]
    P[nphi, cols] = _P[N_PHI]
    for k in range(1, n_tau):
        r = N_PHI + 4 * (k - 1)
        P[r:r + 3, cols + k] = _P[0:3]      # c_k: the regressor 2B τ_k
        P[r + 3, cols + k] = _P[9]          # μ_k: the regressor −τ_k
    return P


_P_BY_TAU = {1: _p_matrix(1), 3: _p_matrix(3)}


def trig(t_s: float | np.ndarray, period_s: float | None) -> np.ndarray:
    """τ(t): (1) for a constant host, (1, cos ωt, sin ωt) with the drift of period `period_s`; (n_tau,) or
    (n, n_tau)."""
    t = np.asarray(t_s, float)
    if period_s is None:
        return np.ones(t.shape + (1,))
    a = 2.0 * math.pi * t / period_s
    return np.stack((np.ones_like(a), np.cos(a), np.sin(a)), axis=-1)


def _hermite(x: np.ndarray, s2: float) -> np.ndarray:
    """(n, 5): He₀..He₄ of x with noise variance s2 (x, x² − s², x³ − 3s²x, x⁴ − 6s²x² + 3s⁴)."""
    x2 = x * x
    return np.stack((np.ones_like(x), x, x2 - s2, x2 * x - 3 * s2 * x, x2 * x2 - 6 * s2 * x2 + 3 * s2 * s2), axis=-1)


def monomials(b_uT: np.ndarray, sigma_uT: float = 0.0) -> np.ndarray:
    """(n, 35): the monomials of degree ≤ 4 of B (n, 3) in `_M4` order, noise-adjusted for σ per axis."""
    B = np.atleast_2d(np.asarray(b_uT, float))
    H = [_hermite(B[:, i], sigma_uT ** 2) for i in range(3)]
    return H[0][:, _EXP[:, 0]] * H[1][:, _EXP[:, 1]] * H[2][:, _EXP[:, 2]]


def weights(b_model_uT: np.ndarray, sigma_uT: float, sigma_model_uT: float = 0.0) -> np.ndarray:
    """w = 1/σ_z², σ_z² = 4 |B_model|² (σ² + σ_model²)."""
    h = np.atleast_1d(np.asarray(b_model_uT, float))
    return 1.0 / (4.0 * h * h * (sigma_uT ** 2 + sigma_model_uT ** 2))


def _zeros(*shape):
    return lambda: np.zeros(shape)


@dataclass
class Stats:
    """Weighted sums of the samples' monomials times τ_k τ_l, adjusted for the noise (`m` (n_tau, n_tau,
    35), `hm` (n_tau, 10), `h4`) and raw (`raw_*`), `n` samples, `weight` the effective number after
    forgetting. `n_tau`: 1 for a constant host, 3 with the hard iron's drift over the orbit."""

    n_tau: int = 1
    m: np.ndarray | None = None
    hm: np.ndarray | None = None
    h4: float = 0.0
    raw_m: np.ndarray | None = None
    raw_hm: np.ndarray | None = None
    n: int = 0
    weight: float = 0.0

    def __post_init__(self) -> None:
        for name, shape in (("m", (self.n_tau, self.n_tau, len(_M4))), ("hm", (self.n_tau, len(_M2))),
                            ("raw_m", (self.n_tau, self.n_tau, len(_M4))), ("raw_hm", (self.n_tau, len(_M2)))):
            if getattr(self, name) is None:
                setattr(self, name, np.zeros(shape))

    def add(self, other: "Stats", forget: float = 1.0) -> None:
        """Add `other`'s samples, after multiplying what is here by `forget`."""
        for name in ("m", "hm", "raw_m", "raw_hm"):
            a = getattr(self, name)
            if forget != 1.0:
                a *= forget
            a += getattr(other, name)
        self.h4 = self.h4 * forget + other.h4
        self.weight = self.weight * forget + other.weight
        self.n += other.n

    def remove(self, other: "Stats") -> None:
        """Take `other`'s samples out of these sums (they were added to both, with the same forgetting)."""
        for name in ("m", "hm", "raw_m", "raw_hm"):
            getattr(self, name).__isub__(getattr(other, name))
        self.h4 -= other.h4
        self.n -= other.n
        self.weight -= other.weight

    def matrix(self, raw: bool = False) -> np.ndarray:
        """Σ w ã ãᵀ ((n_phi + 1)²)."""
        m, hm = (self.raw_m, self.raw_hm) if raw else (self.m, self.hm)
        k, nm = self.n_tau, len(_M2)
        mm = m[:, :, _PROD].transpose(2, 0, 3, 1).reshape(nm * k, nm * k)  # (i, k, j, l): kron order
        P = _P_BY_TAU[k]
        S = P @ mm @ P.T
        cross = P @ hm.T.reshape(-1)
        z = S.shape[0] - 1
        S[:, z] -= cross
        S[z, :] -= cross
        S[z, z] += self.h4
        return S


def contribution(b_meas_uT: np.ndarray, b_model_uT: np.ndarray, sigma_uT: float,
                 sigma_model_uT: float = 0.0, tau: np.ndarray | None = None) -> Stats:
    """The statistics of samples (n, 3) with the model's magnitudes (n,) and their τ(t) (n, n_tau) (None:
    a constant host)."""
    h = np.atleast_1d(np.asarray(b_model_uT, float))
    w = weights(h, sigma_uT, sigma_model_uT)
    tau = np.ones((len(h), 1)) if tau is None else np.atleast_2d(np.asarray(tau, float))
    k = tau.shape[1]
    if len(h) == 1:  # one sample: the monomials on floats (numpy's per-call overhead dominates here)
        x, y, z = (float(v) for v in np.ravel(b_meas_uT))
        adj = np.array(_monomials_1(x, y, z, sigma_uT ** 2))
        raw = np.array(_monomials_1(x, y, z, 0.0))
        w0, h2 = float(w[0]), float(h[0]) ** 2
        if k == 1:
            return Stats(1, (w0 * adj)[None, None], (w0 * h2 * adj[_M2_IN_M4])[None], w0 * h2 * h2,
                         (w0 * raw)[None, None], (w0 * h2 * raw[_M2_IN_M4])[None], 1, 1.0)
        tt = w0 * np.outer(tau[0], tau[0])[:, :, None]
        th = (w0 * h2 * tau[0])[:, None]
        return Stats(k, tt * adj, th * adj[_M2_IN_M4], w0 * h2 * h2, tt * raw, th * raw[_M2_IN_M4], 1, 1.0)
    adj, raw = monomials(b_meas_uT, sigma_uT), monomials(b_meas_uT)
    wh = w * h * h
    wtt = w[:, None, None] * tau[:, :, None] * tau[:, None, :]  # (n, k, k)
    wht = wh[:, None] * tau
    return Stats(k, np.einsum("nkl,nm->klm", wtt, adj), wht.T @ adj[:, _M2_IN_M4], float(np.sum(wh * h * h)),
                 np.einsum("nkl,nm->klm", wtt, raw), wht.T @ raw[:, _M2_IN_M4], len(h), float(len(h)))


_EXP_ROWS = tuple(tuple(int(v) for v in e) for e in _M4)


def _monomials_1(x: float, y: float, z: float, s2: float) -> list:
    def he(v):
        v2 = v * v
        return (1.0, v, v2 - s2, v2 * v - 3 * s2 * v, v2 * v2 - 6 * s2 * v2 + 3 * s2 * s2)
    hx, hy, hz = he(x), he(y), he(z)
    return [hx[p] * hy[q] * hz[r] for p, q, r in _EXP_ROWS]


def accumulate(st: Stats, b_meas_uT: np.ndarray, b_model_uT: np.ndarray, sigma_uT: float,
               sigma_model_uT: float = 0.0, forget: float = 1.0, tau: np.ndarray | None = None) -> Stats:
    """The statistics with samples (n, 3) and the model's magnitudes (n,) added (in place); `forget`
    multiplies what was there first; `tau`: the samples' τ(t) (None: a constant host)."""
    st.add(contribution(b_meas_uT, b_model_uT, sigma_uT, sigma_model_uT, tau), forget)
    return st


def normal_equations(st: Stats, raw: bool = False) -> tuple[np.ndarray, np.ndarray, float]:
    """(N = Σ w a aᵀ, y = Σ w a z, Σ w z²)."""
    S = st.matrix(raw)
    z = S.shape[0] - 1
    return S[:z, :z], -S[:z, z], float(S[z, z])
