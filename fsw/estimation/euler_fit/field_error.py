"""The field model's error along the record, fitted with the tensor and marginalised into its covariance.

The fit's covariance s²(JᵀJ)⁻¹ counts the sensor's white noise only. The field model the fit is given
(the onboard IGRF along the box's TLE at the box's clock) is off by a few tenths of a µT — the TLE's
age, the clock's offset, the model's truncation — and that error is not white: it is a smooth function
of the position along the orbit, i.e. of time, in inertial axes (the field turns once per half orbit on
a low orbit), correlated over the whole record. The tensor is fixed by the slow motion of the attitude,
which is exactly where that error lives, so a white-noise σ is too small (the realistic benchmark:
mean (error/σ)² 1.3–2.1 instead of 1). The fit's residuals cannot show it: what of it the parameters
absorb is missing from them.

Rule: the error is modelled as an offset of the inertial field δB_I(t) = Σ_j c_j P_j(x(t)), Legendre
polynomials of degree 0…D over the record in each inertial axis, D = 1 + ⌊T / (T_turn/2)⌋ for a record
of T seconds (:func:`degree_for`; T_turn ≈ 2,700 s, the field's turn period on a low orbit: a degree
per half turn, at least a linear drift), each coefficient with a weak prior of 10 µT (no field model in
use is off by more than the dipole is, 8.6 µT RMS). From the converged fit, one Gauss–Newton step of
the problem with the 3(D+1) coefficients added moves the tensor by what the error's fitted part
explains, and the covariance is the joint one's block of the tensor and the motion: the uncertainty of
the field's error is marginalised into the tensor's (:func:`apply`). The measurement model is linear in
δB_I (B_body = R(q)ᵀ (B_I + δB_I) + b), so its derivatives are analytic at the fitted attitudes; the
change of the torque m × B through δB_I is of second order and left out.

With a perfect field model the coefficients come out at zero within their σ and the intervals are
wider by what estimating them costs (the price of not assuming the model exact).
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
#: prior 1-σ of each coefficient [T]: the dipole is 8.6 µT RMS off the degree-13 field
PRIOR_SIGMA_T = 10e-6


def degree_for(duration_s: float, turn_period_s: float = FIELD_TURN_PERIOD_S) -> int:
    """The Legendre degree of the field error over a record of `duration_s`: one per half of the field's
    turn period, at least 1 (an offset and a drift)."""
    return 1 + int(math.floor(max(float(duration_s), 0.0) / (0.5 * turn_period_s)))


def basis(t_s: np.ndarray, degree: int) -> np.ndarray:
    """(n, D+1) Legendre polynomials P_0…P_D of the time mapped onto [−1, 1] over the record."""
    t = np.asarray(t_s, float)
    span = max(t[-1] - t[0], 1e-9)
    x = 2.0 * (t - t[0]) / span - 1.0
    return np.stack([legendre.legval(x, np.eye(degree + 1)[j]) for j in range(degree + 1)], axis=1)


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

    def as_dict(self) -> dict:
        return {"degree": self.degree, "coef_uT": (self.coef_T * 1e6).tolist(),
                "sigma_uT": (self.sigma_T * 1e6).tolist(), "chi2_model_exact": self.chi2_model_exact}


def apply(ss, theta: np.ndarray, prior, result, degree: int, run: int = 0, prior_sigma_T: float = PRIOR_SIGMA_T):
    """`result` (a FitResult of run `run` of the single-shooting problem `ss` at `theta`) with the field
    error of `degree` fitted by one Gauss–Newton step and marginalised (see the module's docstring): a new
    FitResult with the tensor, motion, offset, χ², dof and covariances of the joint problem, and
    ``field_error`` set."""
    k = len(theta)
    r, J = ss.residuals_jacobian(theta[None], np.array([run]))
    r, J = r[0], J[0]                                          # (n, 3), (k, n, 3)
    q = ss.trajectory(theta, run)["q"]
    Jc = columns(ss.t[:ss.n], q, degree)                        # per unit c = δB / σ_B
    Ja = np.concatenate([J, Jc])
    m = len(Jc)
    H = np.einsum("kna,lna->kl", Ja, Ja)
    w_c = ss.sigma / prior_sigma_T
    w2 = np.concatenate([prior.w ** 2 if prior is not None else np.zeros(k), np.full(m, w_c * w_c)])
    H[np.diag_indices_from(H)] += w2
    g = np.einsum("kna,na->k", Ja, r)
    if prior is not None:
        g[:k] += prior.w * prior.residual(theta)
    Hinv = np.linalg.pinv(H)
    delta = -Hinv @ g
    r_new = r + np.einsum("k,kna->na", delta, Ja)
    chi2 = float(np.sum(r_new * r_new))
    dof = max(3 * ss.n - k - m, 1)
    cov = chi2 / dof * Hinv
    th = theta + delta[:k]
    par = ss.inertia
    n_I = par.n
    T, c0 = par.affine(run)
    p = T @ th[:n_I] + c0
    _, q0, w0, bias = ss.unpack(th[None], np.array([run]))
    cov_th = cov[:k, :k]
    mom, cov_m = par.moments_of(th[:n_I], cov_th[:n_I, :n_I]) if par.n_moments else (None, None)
    fe = FieldError(degree, (delta[k:] * ss.sigma).reshape(degree + 1, 3),
                    (np.sqrt(np.diag(cov)[k:]) * ss.sigma).reshape(degree + 1, 3), float(result.chi2))
    return dataclasses.replace(result, p=p, cov_p=T @ cov_th[:n_I, :n_I] @ T.T, omega0_radps=w0[0], q0=q0[0],
                               bias_T=bias[0], chi2=chi2, dof=dof, theta=th, cov_theta=cov_th, moments_Nm=mom,
                               cov_moments=cov_m, field_error=fe)
