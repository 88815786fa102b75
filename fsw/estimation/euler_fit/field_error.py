"""The field model's error along the record, fitted with the tensor and marginalised into its covariance.

The fit's covariance s²(JᵀJ)⁻¹ counts the sensor's white noise only. The field model the fit is given
(the onboard IGRF along the box's TLE at the box's clock) is off by a few tenths of a µT — the TLE's
age, the clock's offset, the model's truncation — and that error is not white: it is a smooth function
of the position along the orbit, i.e. of time, in inertial axes (the field turns once per half orbit on
a low orbit), correlated over the whole record. The tensor is fixed by the slow motion of the attitude,
which is exactly where that error lives, so a white-noise σ is too small (the realistic benchmark:
mean (error/σ)² 1.3–2.1 instead of 1). The fit's residuals cannot show it: what of it the parameters
absorb is missing from them.

Rule: the error is modelled as
- an offset of the inertial field δB_I(t) = Σ_j c_j P_j(x(t)), Legendre polynomials of degree 0…D over
  the record in each inertial axis, D = 1 + ⌊T / (T_turn/2)⌋ for a record of T seconds
  (:func:`degree_for`; T_turn ≈ 2,700 s, the field's turn period on a low orbit: a degree per half turn,
  at least a linear drift);
- the host's hard-iron drift left by a constant calibration: Legendre degree 1…D per body axis (the
  constant is the fit's own offset);
- optionally the calibration's soft-iron error δS (3×3, acting on the body field) with the 1-σ the
  calibration states (``FitOptions.soft_iron_sigma``).
The size of the first two comes from the data, attitude-free: |B_measured| − |B_model| does not depend
on the attitude, and its smooth part's RMS (:func:`error_rms_T`) is shared equally among the
polynomials as their prior 1-σ (:func:`prior_sigmas_T`); a record whose |B| agrees with the model's
gets priors so tight that nothing changes. From the converged fit, one Gauss–Newton step of the problem
with these coefficients added (taken only as far as it lowers the cost: :data:`STEP_LENGTHS`) moves the
tensor by what the errors' fitted part explains, and the covariance is the joint one's block of the
tensor and the motion: the uncertainty of the errors is marginalised into the tensor's
(:func:`apply`). The measurement model is linear in them (B_body = (I + δS) R(q)ᵀ (B_I + δB_I) + b +
δb(t) to first order), so their derivatives are analytic at the fitted attitudes; the change of the
torque m × B through δB_I is of second order and left out.

With a perfect field model the coefficients come out at zero within their σ and the intervals are at
most as much wider as estimating them costs (the price of not assuming the model exact).

What the samples still carry besides white noise is correlated over minutes (the driver's bridge offset is
a running mean over 320 s; the field's and calibration's errors beyond the polynomials), and the
curvature's covariance counts it as white. The joint covariance can therefore be the robust one
(:func:`robust_cov`, `FitOptions.robust_cov`; the onboard experiment's): each variance at least the
Newey–West sandwich's over 200 s of lags. On the
mission's ten first experiments (seeds 0-9, 2,100 samples each) that raised the scale's variance by up to
2.4 times, and without the soft iron's terms by up to 2.7 times.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np
from numpy.polynomial import legendre

from ..rotations import quat_to_dcm

#: the field's direction turns about once per half orbit on a low orbit (2 × the orbital rate):
#: 0.133 °/s, ground.field.LEO_FIELD_TURN_DPS
FIELD_TURN_PERIOD_S = 360.0 / 0.133
#: the window of the |B| residual's moving average [s] (the field's error is smooth over it, the noise
#: averages down by its number of samples)
SMOOTH_S = 60.0
#: the lags of the robust covariance (:func:`robust_cov`) [s]: the errors left in the samples are
#: correlated over minutes (the driver's bridge offset is a running mean over 320 s)
ROBUST_LAG_S = 200.0
#: the error's RMS taken when the |B| residual shows none [T] (a prior so tight the coefficients stay at 0)
FLOOR_T = 1e-9


def degree_for(duration_s: float, turn_period_s: float = FIELD_TURN_PERIOD_S) -> int:
    """The Legendre degree of the field error over a record of `duration_s`: one per half of the field's
    turn period, at least 1 (an offset and a drift)."""
    return 1 + int(math.floor(max(float(duration_s), 0.0) / (0.5 * turn_period_s)))


def basis(t_s: np.ndarray, degree: int) -> np.ndarray:
    """(n, D+1) Legendre polynomials P_0…P_D of the time mapped onto [−1, 1] over the record."""
    t = np.asarray(t_s, float)
    span = max(t[-1] - t[0], 1e-9)
    x = 2.0 * (t - t[0]) / span - 1.0
    return legendre.legvander(x, degree)


def columns(t_s: np.ndarray, q_body_to_inertial: np.ndarray, degree: int) -> np.ndarray:
    """∂B_body/∂c (m, n, 3), m = 3(D+1): the field error's coefficients c (per inertial axis a and degree j,
    index 3j + a) seen in body axes at the attitudes q (n, 4)."""
    phi = basis(t_s, degree)                                   # (n, D+1)
    R = quat_to_dcm(np.asarray(q_body_to_inertial, float))     # (n, 3, 3) body → inertial
    # R(q)ᵀ e_a is the a-th row of R
    return np.einsum("nj,nab->janb", phi, R).reshape(3 * (degree + 1), len(phi), 3)


@dataclasses.dataclass
class FieldError:
    """The fitted field error: degree, coefficients [T] (D+1, 3) (inertial axes), their 1-σ, and the χ² of
    the fit before it was added."""

    degree: int
    coef_T: np.ndarray
    sigma_T: np.ndarray
    chi2_model_exact: float         # the fit's χ² before (the field model taken as exact)
    rms_T: float = 0.0              # the error's RMS |B| showed (the coefficients' prior)
    drift_T: np.ndarray | None = None   # (D, 3) the host's hard-iron drift, Legendre 1…D, body axes
    soft_iron: np.ndarray | None = None  # (3, 3) the soft iron's error, when modelled

    def as_dict(self) -> dict:
        return {"degree": self.degree, "coef_uT": (self.coef_T * 1e6).tolist(),
                "sigma_uT": (self.sigma_T * 1e6).tolist(), "chi2_model_exact": self.chi2_model_exact,
                "rms_uT": self.rms_T * 1e6}


def error_rms_T(t_s: np.ndarray, b_meas_T: np.ndarray, b_model_norm_T: np.ndarray, smooth_s: float = SMOOTH_S) -> float:
    """The field error's RMS that |B| shows: d = |B_measured| − |B_model| does not depend on the attitude.
    The white noise's variance σ² per axis is half that of d's first differences; it biases |B_measured|
    up by σ²/|B| (the two axes across B), which is taken off. The moving average of d over `smooth_s`
    keeps the smooth error and 1/m of the noise's variance (m samples a window): RMS² = mean(d̄²) − σ²/m,
    ≥ 0 (the mean kept: a constant error of |B| is an error too)."""
    bm = np.asarray(b_model_norm_T, float)
    d = np.linalg.norm(b_meas_T, axis=1) - bm
    dt = float(np.median(np.diff(t_s))) if len(t_s) > 1 else 1.0
    m = int(max(1, min(len(d) // 4, round(smooth_s / max(dt, 1e-9)))))
    if len(d) < 8 or m < 2:
        return 0.0
    white = 0.5 * float(np.var(np.diff(d)))
    d = d - white / np.maximum(bm, 1e-12)
    dbar = np.convolve(d, np.ones(m) / m, mode="valid")
    return math.sqrt(max(float(np.mean(dbar * dbar)) - white / m, 0.0))


def prior_sigmas_T(rms_T: float, degree: int) -> np.ndarray:
    """Prior 1-σ of the coefficients (D+1, 3) [T] of an error of RMS `rms_T` per axis shared equally among
    the D+1 polynomials (Parseval over the record: RMS² = Σ_j c_j² / (2j+1))."""
    s = max(float(rms_T), FLOOR_T)
    j = np.arange(degree + 1)
    return np.repeat((s * np.sqrt((2 * j + 1) / (degree + 1)))[:, None], 3, axis=1)


def body_columns(t_s: np.ndarray, b_body_T: np.ndarray, degree: int, sigma_b_T: float,
                 soft_iron: bool) -> np.ndarray:
    """∂r/∂c (m, n, 3) of the host's errors left by the calibration, in body axes (r whitened by
    `sigma_b_T`): the hard iron's drift, Legendre degree 1…D per axis (the constant is the fit's own
    offset; index 3(j−1) + a, per unit c = δb / σ_B), then, with `soft_iron`, the soft iron's 3×3 error δS
    (row-major, per unit δS) acting on the field `b_body_T` (n, 3)."""
    phi = basis(t_s, degree)[:, 1:]                             # (n, D)
    n = len(phi)
    drift = np.einsum("nj,ab->janb", phi, np.eye(3)).reshape(3 * degree, n, 3)
    if not soft_iron:
        return drift
    soft = np.einsum("ac,nb->abnc", np.eye(3), np.asarray(b_body_T, float) / sigma_b_T).reshape(9, n, 3)
    return np.concatenate([drift, soft])


def joint_columns(t_s: np.ndarray, q_body_to_inertial: np.ndarray, b_model_T: np.ndarray, sigma_b_T: float,
                  rms_T: float, degree: int, soft_iron_sigma: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The errors' columns of the whitened residuals (m, n, 3) — the inertial field's offset
    (:func:`columns`), then the host's (:func:`body_columns`) — at the attitudes q and the model's field
    `b_model_T` (body axes, the offset left out), and their prior weights (m,) (σ_B / prior 1-σ: the
    offset's and drift's from `rms_T`, :func:`prior_sigmas_T`; the soft iron's 1/`soft_iron_sigma`)."""
    soft = soft_iron_sigma is not None and soft_iron_sigma > 0
    Jc = np.concatenate([columns(t_s, q_body_to_inertial, degree),      # per unit c = δB / σ_B
                         body_columns(t_s, b_model_T, degree, sigma_b_T, soft)])
    sig = prior_sigmas_T(rms_T, degree)
    w_c = np.concatenate([sigma_b_T / sig.ravel(), sigma_b_T / sig[1:].ravel()]
                         + ([np.full(9, 1.0 / soft_iron_sigma)] if soft else []))
    return Jc, w_c


def robust_cov(cov: np.ndarray, Hinv: np.ndarray, Ja: np.ndarray, r: np.ndarray, t_s: np.ndarray,
               lag_s: float = ROBUST_LAG_S) -> np.ndarray:
    """`cov` (the curvature's s²H⁻¹) with each parameter's variance raised to the sandwich estimate
    H⁻¹ Ω H⁻¹ where that is larger: Ω the Newey–West (Bartlett) long-run covariance of the samples'
    scores g_i = J_iᵀ r_i (`Ja` (k, n, 3) the whitened Jacobian, `r` (n, 3) the residuals at the solution),
    over the lags within `lag_s`. A white residual gives Ω ≈ s²JᵀJ and no change; what the model
    still misses and is correlated over minutes (the running mean of the bridge offset, the rest of the
    field's and the calibration's errors) makes the curvature's intervals too narrow. Only variances are
    raised (D cov D, D diagonal ≥ 1): the correlations stay the curvature's, and no variance falls below it."""
    t = np.asarray(t_s, float)[:r.shape[0]]
    dt = float(np.median(np.diff(t))) if len(t) > 1 else 1.0
    L = int(min(len(t) // 4, round(lag_s / max(dt, 1e-9))))
    g = np.einsum("kna,na->nk", Ja, r)
    om = g.T @ g
    for lag in range(1, L + 1):
        c = g[lag:].T @ g[:-lag]
        om += (1.0 - lag / (L + 1.0)) * (c + c.T)
    sand = np.einsum("ij,jk,ki->i", Hinv, om, Hinv)
    var = np.diag(cov)
    ratio = np.divide(sand, var, out=np.ones_like(var), where=var > 0)
    d = np.sqrt(np.maximum(ratio, 1.0))
    return cov * d[:, None] * d[None, :]


#: step lengths tried, longest first: the Gauss–Newton step is taken only as far as it lowers the cost
STEP_LENGTHS = (1.0, 0.5, 0.25, 0.125, 0.0625)


def _accepted_step(ss, theta: np.ndarray, prior, r: np.ndarray, Jc: np.ndarray, w_c: np.ndarray,
                   step: np.ndarray, run: int) -> tuple[np.ndarray, float]:
    """The joint step scaled by the longest of :data:`STEP_LENGTHS` whose cost (χ² with the trajectory
    integrated at the new θ and the error's columns linear, plus the priors) is not above the fit's; none
    such: no step. Returns (step, χ² of the data there)."""
    k = len(theta)
    n = ss.n

    def cost(alpha: float) -> tuple[float, float]:
        d = alpha * step
        th = theta + d[:k]
        ps = ss.start(th[None], np.array([run]))
        ps.advance()
        rr = (ss.predicted_T(ps.pred, th[None])[0] - ss.b_meas[run, :n]) / ss.sigma + np.einsum("m,mna->na", d[k:], Jc)
        chi2 = float(np.sum(rr * rr))
        pc = float(prior.cost(th)) if prior is not None else 0.0
        return chi2 + pc + float(np.sum((w_c * d[k:]) ** 2)), chi2

    c0 = float(np.sum(r * r)) + (float(prior.cost(theta)) if prior is not None else 0.0)
    for alpha in STEP_LENGTHS:
        c, chi2 = cost(alpha)
        if np.isfinite(c) and c <= c0 + 1e-6 * abs(c0):
            return alpha * step, chi2
    return np.zeros_like(step), float(np.sum(r * r))


def apply(ss, theta: np.ndarray, prior, result, degree: int, run: int = 0, soft_iron_sigma: float | None = None,
          robust: bool = False):
    """`result` (a FitResult of run `run` of the single-shooting problem `ss` at `theta`) with the field
    error of `degree` fitted by one Gauss–Newton step and marginalised (see the module's docstring): a new
    FitResult with the tensor, motion, offset, χ², dof and covariances of the joint problem (with
    `robust`, :func:`robust_cov`'s), and ``field_error`` set."""
    k = len(theta)
    r, J = ss.residuals_jacobian(theta[None], np.array([run]))
    r, J = r[0], J[0]                                          # (n, 3), (k, n, 3)
    q = ss.trajectory(theta, run)["q"]
    t = ss.t[:ss.n]
    b = ss.b_meas[run, :ss.n] - result.bias_T
    if len(ss.columns):                                         # and less the error terms
        b = b - ss.errors_T(theta[None])[0]
    b_model = b + r * ss.sigma                                  # the predicted field less the offsets
    rms = error_rms_T(t, b, np.linalg.norm(b_model, axis=1))
    soft = soft_iron_sigma is not None and soft_iron_sigma > 0
    Jc, w_c = joint_columns(t, q, b_model, ss.sigma, rms, degree, soft_iron_sigma)
    Ja = np.concatenate([J, Jc])
    m = len(Jc)
    H = np.einsum("kna,lna->kl", Ja, Ja)
    w2 = np.concatenate([prior.w ** 2 if prior is not None else np.zeros(k), w_c * w_c])
    H[np.diag_indices_from(H)] += w2
    g = np.einsum("kna,na->k", Ja, r)
    if prior is not None:
        g[:k] += prior.w * prior.residual(theta)
    Hinv = np.linalg.pinv(H)
    step = -Hinv @ g
    delta, chi2 = _accepted_step(ss, theta, prior, r, Jc, w_c, step, run)
    dof = max(3 * ss.n - k - m, 1)
    cov = chi2 / dof * Hinv
    if robust:
        cov = robust_cov(cov, Hinv, Ja, r + np.einsum("kna,k->na", Ja, delta), t)
    th = theta + delta[:k]
    par = ss.inertia
    n_I = par.n
    T = par.jacobian(th[:n_I], run)
    p = par.to_p(th[None, :n_I], np.array([run]))[0]
    _, q0, w0, bias = ss.unpack(th[None], np.array([run]))
    cov_th = cov[:k, :k]
    mom, cov_m = par.moments_of(th[:n_I], cov_th[:n_I, :n_I]) if par.n_moments else (None, None)
    n_kit = 0 if result.errors is None else len(result.errors.kit_T)
    ni = 3 * (degree + 1)
    fe = FieldError(degree, (delta[k:k + ni] * ss.sigma).reshape(degree + 1, 3),
                    (np.sqrt(np.diag(cov)[k:k + ni]) * ss.sigma).reshape(degree + 1, 3), float(result.chi2), rms,
                    (delta[k + ni:k + ni + 3 * degree] * ss.sigma).reshape(degree, 3),
                    delta[k + ni + 3 * degree:].reshape(3, 3) if soft else None)
    return dataclasses.replace(result, p=p, cov_p=T @ cov_th[:n_I, :n_I] @ T.T, omega0_radps=w0[0], q0=q0[0],
                               bias_T=bias[0], chi2=chi2, dof=dof, theta=th, cov_theta=cov_th, moments_Nm=mom,
                               cov_moments=cov_m, field_error=fe,
                               errors=ss.error_terms(th, cov_th, n_kit))
