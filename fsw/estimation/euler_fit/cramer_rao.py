"""The Cramér–Rao bound of the fit: the covariance no unbiased estimator beats with the given noise,
sampling and record (the Fisher information at the truth)."""
from __future__ import annotations

import numpy as np

from .. import sampled_moment as sm
from . import field_error
from .identification import FitOptions, fit_prior
from .model import FieldFn, InertiaParam, KnownAction
from .shooting import SingleShooting

def cramer_rao(t_s: np.ndarray, b_inertial: FieldFn, action: KnownAction, sigma_b_T: float, p: np.ndarray,
               q0: np.ndarray, omega0_radps: np.ndarray, opts: FitOptions | None = None, *,
               unknown_moments=(), moments_Nm: np.ndarray | None = None,
               b_samples: np.ndarray | None = None,
               field_error_rms_T: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Cramér–Rao bound of the fit: the covariance (F + prior)⁻¹ of (p, unknown moments) that an efficient
    estimator reaches, F = JᵀJ/σ_B² the Fisher information of white noise σ_B per axis, J the Jacobian
    of the predicted samples at the given parameters (the truth, in a simulation) — tensor ``p`` (for
    ``opts.mode`` "shape" its scale is the one of ``p``), start state (``q0``, ``omega0_radps``) at
    ``t_s[0]``, zero offset, ``moments_Nm`` (K, 3) on ``unknown_moments``. With
    ``opts.field_error_degree`` the field model's error as the fit models it (`field_error`: its
    coefficients with the prior of an error of RMS ``field_error_rms_T`` per axis, the soft iron's with
    ``opts.soft_iron_sigma``) is estimated alongside and marginalised: the bound of a fit that does not
    take its field model as exact. Returns (cov_p (6, 6), cov of the moments (3K, 3K))."""
    opts = opts or FitOptions()
    t = np.asarray(t_s, float)
    if b_samples is None:
        b_samples = np.asarray(b_inertial(t), float).reshape(-1, 3)
    p = np.asarray(p, float)
    I_ref = float(p[0]) if opts.mode in ("shape", "shape_diag") else float(np.mean(p[:3]))
    par = InertiaParam(opts.mode, I_ref, p[None] if opts.mode == "scale" else None,
                       *sm.merged(unknown_moments, action.unknown_intervals, action.unknown_sigma_Nm))
    ss = SingleShooting(t, np.zeros((1, len(t), 3)), b_samples, action, b_inertial, par,
                        np.asarray(q0, float)[None], sigma_b_T, fit_bias=opts.fit_bias,
                        omega_scale=opts.omega_scale, h_max_s=opts.h_max_s)
    theta = np.zeros(ss.n_params)
    theta[:par.n] = par.from_p(p, moments_Nm=moments_Nm)
    theta[par.n:par.n + 3] = np.asarray(omega0_radps, float) / opts.omega_scale
    prior = fit_prior(ss.n_params, par.n, theta[:par.n], opts, sigma_b_T, par)
    if opts.field_error_degree is None:
        _, _, A, _, _ = ss.evaluate(theta[None], np.zeros(1, int))
        cov = A.inverse((prior.w ** 2)[None])[0]
    else:
        if field_error_rms_T is None:
            raise ValueError("a bound with the field model's error needs that error's RMS (field_error_rms_T)")
        _, J = ss.residuals_jacobian(theta[None], np.zeros(1, int))
        tr = ss.trajectory(theta)
        Jc, w_c = field_error.joint_columns(t, tr["q"], tr["b_body_T"], sigma_b_T, field_error_rms_T,
                                            int(opts.field_error_degree), opts.soft_iron_sigma)
        Ja = np.concatenate([J[0], Jc])
        H = np.einsum("kna,lna->kl", Ja, Ja)
        H[np.diag_indices_from(H)] += np.concatenate([prior.w ** 2, w_c * w_c])
        cov = np.linalg.pinv(H)[:ss.n_params, :ss.n_params]
    T = par.jacobian(theta[:par.n])
    nI, nt = par.n, par.n_tensor
    s = par.moment_scale_Nm
    return T @ cov[:nI, :nI] @ T.T, cov[nt:nI, nt:nI] * s * s
