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
order (Jacobians below), and the derivative formula's adds its own truncation error at the step (it is
exact only as Δt → 0; :func:`_add_truncation`); a 1-σ statement (the papers' worst-case bounds for a measurement
error ±δ_B, eqs. 5 and 10, are in tests/estimation_reference.py, which the tests check against).

Degenerate samples: a formula that divides by |B_k|² (Boer) or |ΔB_k|² (derivative) has nothing to
say when that vector is lost in the noise — a zero or near-zero field, a field that does not change
(ω ∥ B, or ω = 0) — and its first-order σ, which shrinks with the noise it divides, is meaningless
there (at |B| = 0 exactly it is 0). Below :data:`FIELD_MIN_SIGMAS` σ_B (Boer) or a change below
:data:`DEGENERATE_SNR` times its noise (derivative) the kernels give the row an infinite σ (ω is 0
where the formula divides by zero): the array forms return it, and the streaming forms publish the
DEGENERATE flag with σ = :data:`SIGMA_UNOBSERVED_RADPS`, the finite "no information" that the link
carries (the ground decoder refuses non-finite values as damaged frames).

A field taken as fixed in inertial space: every formula above, and every estimator run without a field
model along the orbit, reads the field's own turning as the body's. In low Earth orbit the field's
direction turns by up to about twice the orbital rate (:data:`LEO_FIELD_TURN_RADPS`, 0.13 °/s), about an
axis perpendicular to B: an error of that size in the part of ω perpendicular to B that no sample of
the record can reveal. :func:`widen_for_field_turn` adds it to a 1-σ, as a variance (turn rate)²/2 on
each of the two axes perpendicular to B (a vector of that length in a random direction of the plane).
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

#: Reported 1-σ (rad/s) on the link when an estimator has no information (degenerate geometry): wide,
#: finite; the array forms (ground) give +inf instead.
SIGMA_UNOBSERVED_RADPS = 10.0
#: A step whose field change is below this many noise σ (√2 σ_B) is degenerate (derivative formula).
DEGENERATE_SNR = 1.0
#: A field below this many σ_B has no direction to speak of (Boer formula).
FIELD_MIN_SIGMAS = 3.0
#: How fast the geomagnetic field's direction turns in inertial space along a low orbit, at most: about
#: twice the orbital rate (2 · 2π / 5,400 s; the dipole's direction turns at 1–2 n along a polar orbit).
LEO_FIELD_TURN_RADPS = 2.0 * 2.0 * math.pi / 5400.0


def _safe_div(num: np.ndarray, den: np.ndarray) -> np.ndarray:
    """num / den[..., None], 0 where den == 0 (callers flag those samples)."""
    den = np.asarray(den, dtype=float)
    out = np.zeros(np.broadcast_shapes(num.shape, den.shape + (3,)))
    ok = den > 0.0
    np.divide(num, den[..., None], out=out, where=ok[..., None])
    return out


# --- kernels: compiled loops over the rows of a record, shared by the array and streaming forms ---

@njit(cache=True, inline="always")
def _skew_ij(v0: float, v1: float, v2: float, i: int, j: int) -> float:
    """Element (i, j) of [v]ₓ (inlined into the compiled row kernels; rotations.skew is the array form)."""
    if i == j:
        return 0.0
    if i == 0:
        return -v2 if j == 1 else v1
    if i == 1:
        return v2 if j == 0 else -v0
    return -v1 if j == 0 else v0


@njit(cache=True)
def _add_jjt(J: np.ndarray, n: int, s2: float, cov: np.ndarray, k: int) -> None:
    """cov[k] = s2 Σ_m J[m] J[m]ᵀ over the first n Jacobians."""
    for i in range(3):
        for j in range(3):
            acc = 0.0
            for m in range(n):
                for c in range(3):
                    acc += J[m, i, c] * J[m, j, c]
            cov[k, i, j] = s2 * acc


@njit(cache=True)
def _chord(c0: float, c1: float, c2: float, p0: float, p1: float, p2: float, dt: float, w: np.ndarray, k: int,
           J: np.ndarray) -> None:
    """The chord rate of two consecutive vectors, c (now) and p (before), the form both formulas share:
    w[k] = (c × p) / (Δt |c|²) (0 where c = 0), with J[0] = ∂ω/∂p = [c]ₓ/(Δt|c|²) and
    J[1] = ∂ω/∂c = −[p]ₓ/(Δt|c|²) − 2ω cᵀ/|c|²."""
    n2 = c0 * c0 + c1 * c1 + c2 * c2
    if n2 > 0.0:
        f = 1.0 / (dt * n2)
        w0, w1, w2 = (c1 * p2 - c2 * p1) * f, (c2 * p0 - c0 * p2) * f, (c0 * p1 - c1 * p0) * f
        g = 2.0 / n2
    else:
        f = w0 = w1 = w2 = g = 0.0
    w[k, 0], w[k, 1], w[k, 2] = w0, w1, w2
    wv = (w0, w1, w2)
    cv = (c0, c1, c2)
    for i in range(3):
        for j in range(3):
            J[0, i, j] = _skew_ij(c0, c1, c2, i, j) * f
            J[1, i, j] = -_skew_ij(p0, p1, p2, i, j) * f - g * wv[i] * cv[j]


@njit(cache=True)
def _unobserved(cov: np.ndarray, k: int) -> None:
    """cov[k] = diag(inf): no information on any axis."""
    for i in range(3):
        for j in range(3):
            cov[k, i, j] = math.inf if i == j else 0.0


@njit(cache=True)
def boer_rows(t: np.ndarray, b: np.ndarray, s2: float, k0: int, w: np.ndarray, cov: np.ndarray,
              J: np.ndarray) -> None:
    """Boer rate and its first-order covariance for rows k ≥ max(k0, 1), in place.

    ω⊥_k = (ΔB_k × B_k) / (Δt_k |B_k|²) = (B_k × B_{k−1}) / (Δt_k |B_k|²) (0 where |B_k| = 0, which the
    callers flag). Jacobians: ∂ω⊥/∂B_{k−1} = [B_k]ₓ / (Δt|B_k|²) and
    ∂ω⊥/∂B_k = −[B_{k−1}]ₓ / (Δt|B_k|²) − 2 ω⊥ B_kᵀ / |B_k|²; cov = s2 Σ J Jᵀ for white per-axis
    noise of variance s2. J is a (3, 3, 3) work array. A row with |B_k| ≤ FIELD_MIN_SIGMAS √s2 (with
    s2 = 0: |B_k| = 0) is degenerate: cov = diag(inf).
    """
    lim2 = FIELD_MIN_SIGMAS * FIELD_MIN_SIGMAS * s2
    for k in range(max(k0, 1), t.shape[0]):
        _chord(b[k, 0], b[k, 1], b[k, 2], b[k - 1, 0], b[k - 1, 1], b[k - 1, 2], t[k] - t[k - 1], w, k, J)
        if b[k, 0] * b[k, 0] + b[k, 1] * b[k, 1] + b[k, 2] * b[k, 2] <= lim2:
            _unobserved(cov, k)
        else:
            _add_jjt(J, 2, s2, cov, k)


@njit(cache=True)
def derivative_rows(t: np.ndarray, b: np.ndarray, s2: float, k0: int, w: np.ndarray, cov: np.ndarray,
                    J: np.ndarray, truncation: bool = True) -> None:
    """Derivative-formula rate and its first-order covariance for rows k ≥ max(k0, 2), in place.

    ω_k = (Ḃ_k × Ḃ_{k−1}) / (Δt_k |Ḃ_k|²) with backward differences Ḃ_k = (B_k − B_{k−1})/Δt_k (0 where
    Ḃ_k = 0, which the callers flag). With d_k = Ḃ_k, d_1 = Ḃ_{k−1}: A₁ = ∂ω/∂d_1 = [d_k]ₓ/(Δt|d_k|²),
    A_k = ∂ω/∂d_k = −[d_1]ₓ/(Δt|d_k|²) − 2ω d_kᵀ/|d_k|², then the chain rule through the differences:
    ∂ω/∂B_{k−2} = −A₁/Δt_{k−1}, ∂ω/∂B_{k−1} = A₁/Δt_{k−1} − A_k/Δt_k, ∂ω/∂B_k = A_k/Δt_k.
    A row with |ΔB_k| ≤ DEGENERATE_SNR √(2 s2) (with s2 = 0: ΔB_k = 0) is degenerate: cov = diag(inf).
    With `truncation`, the formula's own error at a finite step is added (:func:`_add_truncation`).
    """
    lim2 = 2.0 * DEGENERATE_SNR * DEGENERATE_SNR * s2
    for k in range(max(k0, 2), t.shape[0]):
        dt, dtp = t[k] - t[k - 1], t[k - 1] - t[k - 2]
        d0, d1, d2 = (b[k, 0] - b[k - 1, 0]) / dt, (b[k, 1] - b[k - 1, 1]) / dt, (b[k, 2] - b[k - 1, 2]) / dt
        e0, e1, e2 = ((b[k - 1, 0] - b[k - 2, 0]) / dtp, (b[k - 1, 1] - b[k - 2, 1]) / dtp,
                      (b[k - 1, 2] - b[k - 2, 2]) / dtp)
        _chord(d0, d1, d2, e0, e1, e2, dt, w, k, J)  # J[0] = A₁, J[1] = A_k
        if (d0 * d0 + d1 * d1 + d2 * d2) * dt * dt <= lim2:
            _unobserved(cov, k)
            continue
        for i in range(3):
            for j in range(3):
                a1, ak = J[0, i, j], J[1, i, j]
                J[0, i, j] = -a1 / dtp
                J[1, i, j] = a1 / dtp - ak / dt
                J[2, i, j] = ak / dt
        _add_jjt(J, 3, s2, cov, k)
        if truncation:
            _add_truncation(w, cov, k, dt)


@njit(cache=True)
def _add_truncation(w: np.ndarray, cov: np.ndarray, k: int, dt: float) -> None:
    """Add the derivative formula's truncation error at row k to its covariance, as a variance along ω̂.

    For a constant ω the two chords of B turn by θ = |ω|Δt about ω, and the formula returns ω̂ along ω with
    |ω̂| = sin θ / Δt (exact only as Δt → 0): short by (θ − sin θ)/Δt, with θ = asin(|ω̂|Δt) (θ ≤ 90°;
    beyond, the turn is ambiguous and the error is taken at 90°). At 16 °/s and 3 s (θ = 48°) that is 11.5 %
    of |ω|, far above the noise's share at 0.5 µT. |ω̂| is taken less the noise's share of it along ω̂."""
    n2 = w[k, 0] * w[k, 0] + w[k, 1] * w[k, 1] + w[k, 2] * w[k, 2]
    if not n2 > 0.0:
        return
    # |ω̂|² less the noise's share of it along ω̂ (cov holds the noise's covariance here): where the noise
    # dominates (a slow rate, a short step) |ω̂| is mostly noise and says nothing of θ
    q = 0.0
    for i in range(3):
        for j in range(3):
            q += w[k, i] * cov[k, i, j] * w[k, j]
    m2 = n2 - q / n2
    if not m2 > 0.0:
        return
    m = math.sqrt(m2)
    x = min(m * dt, 1.0)
    e = (math.asin(x) / x - 1.0) * m
    f = e * e / n2
    for i in range(3):
        for j in range(3):
            cov[k, i, j] += f * w[k, i] * w[k, j]


# --- whole-recording forms ----------------------------------------------------------------------

def _check(t_s: np.ndarray, b_T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    t = np.ascontiguousarray(t_s, dtype=float)
    b = np.ascontiguousarray(b_T, dtype=float)
    if b.ndim != 2 or b.shape[1] != 3 or t.shape != (b.shape[0],):
        raise ValueError(f"expected t_s (N,) and b_T (N, 3), got {t.shape} and {b.shape}")
    if t.size > 1 and not np.all(np.diff(t) > 0):
        raise ValueError("sample times must be strictly increasing")
    return t, b


def _rows(kernel, first: int, t_s: np.ndarray, b_T: np.ndarray, sigma_b_T: float,
          *extra) -> tuple[np.ndarray, np.ndarray]:
    """(rate (N, 3), covariance (N, 3, 3)) of a row kernel over a record; rows before `first` NaN."""
    t, b = _check(t_s, b_T)
    w = np.full(b.shape, np.nan)
    cov = np.full((len(t), 3, 3), np.nan)
    if len(t) > first:
        kernel(t, b, float(sigma_b_T) ** 2, first, w, cov, np.empty((3, 3, 3)), *extra)
    return w, cov


def boer_rate(t_s: np.ndarray, b_T: np.ndarray) -> np.ndarray:
    """Boer formula over a recording: (N, 3) perpendicular rate in rad/s, row 0 NaN."""
    return _rows(boer_rows, 1, t_s, b_T, 0.0)[0]


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
    return _rows(derivative_rows, 2, t_s, b_T, 0.0)[0]


def boer_covariance(t_s: np.ndarray, b_T: np.ndarray, sigma_b_T: float) -> np.ndarray:
    """First-order covariance (N, 3, 3) of :func:`boer_rate` for white per-axis noise σ_B; row 0 NaN;
    diag(inf) on a degenerate row (|B_k| ≤ 3σ_B)."""
    return _rows(boer_rows, 1, t_s, b_T, sigma_b_T)[1]


def derivative_covariance(t_s: np.ndarray, b_T: np.ndarray, sigma_b_T: float, truncation: bool = True
                          ) -> np.ndarray:
    """Covariance (N, 3, 3) of :func:`derivative_rate`: the noise's to first order and, with `truncation`,
    the formula's own error at the step (:func:`_add_truncation`); rows 0 and 1 NaN; diag(inf) on a
    degenerate row (|ΔB_k| ≤ √2 σ_B)."""
    return _rows(derivative_rows, 2, t_s, b_T, sigma_b_T, bool(truncation))[1]


def unobserved_sigma(sigma_radps: np.ndarray, b_T: np.ndarray, sigma_b_T: float) -> np.ndarray:
    """1-σ (N, 3) of a full-vector estimator's array form with "no information" as +inf: every axis of
    a row whose field is at or below FIELD_MIN_SIGMAS σ_B (the sample has no direction), and an axis
    whose σ is 0 (a covariance that found nothing to say) or at least SIGMA_UNOBSERVED_RADPS (the
    link's finite stand-in). NaN (no estimate) stays NaN."""
    s = np.array(sigma_radps, dtype=float)
    with np.errstate(invalid="ignore"):
        s[(s <= 0.0) | (s >= SIGMA_UNOBSERVED_RADPS)] = math.inf
    weak = np.linalg.norm(np.asarray(b_T, float), axis=1) <= FIELD_MIN_SIGMAS * sigma_b_T
    s[weak & ~np.isnan(s).any(axis=1)] = math.inf
    return s


def widen_for_field_turn(sigma_radps: np.ndarray, b_T: np.ndarray,
                         turn_radps: float = LEO_FIELD_TURN_RADPS) -> np.ndarray:
    """1-σ (N, 3) of an estimate that took the field as fixed in inertial space, widened by the field's
    own turning (module docstring): σ_i² + (turn²/2)(1 − b̂_i²) per axis i, b̂ = B/|B| of the sample.
    NaN and inf stay as they are; `turn_radps` = 0 (a laboratory's fixed field) leaves σ unchanged."""
    s = np.asarray(sigma_radps, dtype=float)
    if not turn_radps > 0:
        return s.copy()
    b = np.asarray(b_T, dtype=float)
    n = np.linalg.norm(b, axis=1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        bh2 = np.where(n > 0, (b / np.where(n > 0, n, 1.0)) ** 2, 1.0 / 3.0)
    return np.sqrt(s ** 2 + 0.5 * turn_radps ** 2 * (1.0 - bh2))


def widen_for_field_error(sigma_radps: np.ndarray, w_radps: np.ndarray, rel_error: float) -> np.ndarray:
    """1-σ (N, 3) widened by a field error that no noise model holds (an uncalibrated host's iron, an
    imperfect calibration): a field off by a fraction ε of |B| turns into a rate error of about ε|ω| per
    axis (Boer's ω⊥ = ΔB × B / (Δt|B|²) with B + δB: δω ~ |ω| |δB| / |B|). σ_i² + (ε |ω̂|)² per sample,
    |ω̂| the estimate's own; NaN and inf stay."""
    s = np.asarray(sigma_radps, dtype=float)
    if not rel_error > 0:
        return s.copy()
    mag = np.linalg.norm(np.nan_to_num(np.asarray(w_radps, dtype=float)), axis=1, keepdims=True)
    return np.sqrt(s ** 2 + (rel_error * mag) ** 2)


# --- streaming forms for the flight loop --------------------------------------------------------

@njit(cache=True)
def _shift_in(t: np.ndarray, b: np.ndarray, t_s: float, bx: float, by: float, bz: float) -> None:
    """Drop the oldest row of a short history, append (t_s, B)."""
    n = t.shape[0]
    for k in range(n - 1):
        t[k] = t[k + 1]
        b[k, 0], b[k, 1], b[k, 2] = b[k + 1, 0], b[k + 1, 1], b[k + 1, 2]
    t[n - 1] = t_s
    b[n - 1, 0], b[n - 1, 1], b[n - 1, 2] = bx, by, bz


class _StreamBase:
    """Common state of the streaming estimators: latest estimate, 1-σ per axis and flags.

    They run the same compiled row kernels as the array forms, on a history of `history` rows that
    they own; a sample allocates no array."""

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
        #: estimates that span a data gap after it (`fsw.estimation.sample_gate.mark_gap`): a formula on
        #: `history` samples has history − 1 of them
        self.gap_history = history - 1
        self._t = np.full(history, np.nan)
        self._b = np.zeros((history, 3))
        self._w = np.zeros((history, 3))
        self._cov = np.zeros((history, 3, 3))
        self._J = np.zeros((3, 3, 3))
        self._n = 0

    def reset(self) -> None:
        """Forget the history (after a data gap or a sensor re-initialisation)."""
        self._n = 0
        self.omega_radps[:] = 0.0
        self.sigma_radps[:] = SIGMA_UNOBSERVED_RADPS
        self.flags = self.NO_ESTIMATE

    def _push(self, t_s: float, b_T) -> bool:
        """Append a sample; False for a repeated or out-of-order one, or before the history is full."""
        if self._n and not t_s > self.t_s:
            return False  # repeated or out-of-order sample: ignored by the caller's contract
        _shift_in(self._t, self._b, t_s, float(b_T[0]), float(b_T[1]), float(b_T[2]))
        h = len(self._t)
        self._n = min(self._n + 1, h)
        self.t_s = t_s
        return self._n == h

    def _publish(self, base_flags: int) -> None:
        """Publish the newest row of the kernel's output; a non-finite σ (degenerate row) or ω is
        published as DEGENERATE with σ = SIGMA_UNOBSERVED_RADPS."""
        flags = base_flags
        k = len(self._t) - 1
        w0, w1, w2 = self._w[k].tolist()
        c = self._cov[k]
        s0, s1, s2 = math.sqrt(max(float(c[0, 0]), 0.0)), math.sqrt(max(float(c[1, 1]), 0.0)), \
            math.sqrt(max(float(c[2, 2]), 0.0))
        finite_w = math.isfinite(w0 + w1 + w2)
        if not (finite_w and math.isfinite(s0 + s1 + s2)):
            flags |= self.DEGENERATE
            if not finite_w:
                w0 = w1 = w2 = 0.0
            s0 = s1 = s2 = SIGMA_UNOBSERVED_RADPS
        om, sg = self.omega_radps, self.sigma_radps
        om[0], om[1], om[2] = w0, w1, w2
        sg[0], sg[1], sg[2] = (min(s0, SIGMA_UNOBSERVED_RADPS), min(s1, SIGMA_UNOBSERVED_RADPS),
                               min(s2, SIGMA_UNOBSERVED_RADPS))
        self.flags = flags


class BoerStream(_StreamBase):
    """Boer formula, one sample at a time; `sigma_b_T` is the per-axis 1-σ of a field sample."""

    def __init__(self, sigma_b_T: float) -> None:
        super().__init__(sigma_b_T, history=2)

    def update(self, t_s: float, b_T: np.ndarray) -> bool:
        """Add a sample; True when a new estimate is available in omega_radps / sigma_radps / flags."""
        if not self._push(t_s, b_T):
            return False
        boer_rows(self._t, self._b, self.sigma_b_T ** 2, 1, self._w, self._cov, self._J)
        # a field change within the noise still gives an honest (wide) estimate; only |B| → 0 degenerates
        # (the kernel's infinite σ)
        self._publish(self.PERPENDICULAR_ONLY)
        return True


class DerivativeStream(_StreamBase):
    """Derivative formula, one sample at a time (needs three samples)."""

    def __init__(self, sigma_b_T: float) -> None:
        super().__init__(sigma_b_T, history=3)

    def update(self, t_s: float, b_T: np.ndarray) -> bool:
        if not self._push(t_s, b_T):
            return False
        derivative_rows(self._t, self._b, self.sigma_b_T ** 2, 2, self._w, self._cov, self._J, True)
        # the formula divides by |ΔB_k|²: below the noise it has no information (ω ∥ B, or ω → 0): the
        # kernel's infinite σ
        self._publish(0)
        return True
