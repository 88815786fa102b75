"""The batch fit with a constant field offset in body axes (what a host calibration leaves of the hard iron)
among its unknowns, against the simulation's truth."""
import math

import numpy as np

from bench import accuracy as acc
from fsw.estimation import rate_kalman as rk
from ground import smoother as sm

OFFSET_T = np.array([0.25e-6, -0.2e-6, 0.15e-6])


def _record(seed: int):
    """A dipole-world tumble (the field model exact), 120 samples at 1 s, 0.5 µT, plus a constant offset."""
    run = acc.simulate("undirected", "asymmetric", 1.0, 0.5e-6, np.random.default_rng([2024, seed]),
                       record_samples=120, warmup_s=0.0)
    t, b = run.t_s[run.record], run.b_T[run.record]
    return t, b + OFFSET_T, sm.tabulated(run.field, t), run.w_true_radps[run.record], math.hypot(0.5e-6,
                                                                                               acc.CHIP_NOISE_T)


def _rms_dps(w, w_true) -> float:
    return math.degrees(float(np.sqrt(np.mean(np.sum((w - w_true) ** 2, axis=1)))))


def test_offset_fitted_and_the_rate_error_it_caused_removed():
    t, b, field, w_true, sig = _record(2)   # a run whose rate the offset moves (0.066 against 0.021 °/s)
    plain = sm.euler_fit(t, b, sig, field_eci_T=field)
    fit = sm.euler_fit(t, b, sig, field_eci_T=field, hard_iron_sigma_T=0.3e-6)
    off = fit.info["hard_iron_residual_uT"]
    s = fit.info["hard_iron_residual_sigma_uT"]
    # the offset found within 3σ and 0.1 µT, with a σ well inside the prior's 0.3 µT
    assert np.all(np.abs(off - OFFSET_T * rk.UT_PER_T) < np.maximum(3 * s, 0.0)) and np.all(
        np.abs(off - OFFSET_T * rk.UT_PER_T) < 0.1)
    assert np.all(s < 0.15)
    # the offset left in costs the rate; fitted, the error is the noise's (clean record: same fit, no offset)
    clean = sm.euler_fit(t, b - OFFSET_T, sig, field_eci_T=field)
    e_plain, e_fit, e_clean = (_rms_dps(r.w_radps, w_true) for r in (plain, fit, clean))
    assert e_fit < 0.5 * e_plain
    assert e_fit < 1.3 * e_clean + 0.005
    # and its σ still covers the error (2σ on every axis at 90 % of the samples)
    assert np.mean(np.abs(fit.w_radps - w_true) < 2 * fit.sigma_radps) > 0.9


def test_no_offset_fitted_without_a_field_model_or_a_prior():
    t, b, field, _, sig = _record(4)
    assert "hard_iron_residual_uT" not in sm.euler_fit(t[:40], b[:40], sig, field_eci_T=field).info
    # without a field model the inertial field is fitted in the first sample's axes: an offset is not separable
    assert "hard_iron_residual_uT" not in sm.euler_fit(t[:40], b[:40], sig, hard_iron_sigma_T=0.3e-6).info
