"""Boer and derivative formulas against analytic truth (constant rate, fixed field)."""
import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import estimation_reference as reference
from fsw.estimation import rate_formulas as rf

B_I_T = np.array([20e-6, -15e-6, 35e-6])


def constant_rate_field(omega_radps, dt_s, n, b_inertial_T=B_I_T):
    """B_body(t) for a body spinning at constant ω from identity attitude.

    R_bodyToInertial(t) = exp([ω]ₓ t), so B_body = R(t)ᵀ B_I = rotation by −ω t applied to B_I:
    truth computed independently with scipy's Rotation.
    """
    t = np.arange(n) * dt_s
    b = Rotation.from_rotvec(-np.outer(t, omega_radps)).apply(b_inertial_T)
    return t, b


def perpendicular(omega, b):
    bh = b / np.linalg.norm(b, axis=-1, keepdims=True)
    return omega - np.einsum("...i,...i", omega, bh)[..., None] * bh


def test_convention_field_derivative():
    """dB_body/dt = B_body × ω (physics-and-seeds.md §2)."""
    w = np.radians([3.0, -7.0, 5.0])
    t, b = constant_rate_field(w, 1e-4, 3)
    db = (b[2] - b[0]) / (2e-4)
    np.testing.assert_allclose(db, np.cross(b[1], w), rtol=1e-6)


@pytest.mark.parametrize("w_dps", [[0, 0, 10], [6, -5, 6.5], [20, 3, -1]])
def test_boer_returns_perpendicular_rate(w_dps):
    w = np.radians(w_dps)
    dt = 0.01
    t, b = constant_rate_field(w, dt, 50)
    est = rf.boer_rate(t, b)
    assert np.all(np.isnan(est[0]))
    theta = np.linalg.norm(w) * dt
    truth = perpendicular(w, b[1:])
    # first-order method: error O(|ω| θ)
    assert np.max(np.linalg.norm(est[1:] - truth, axis=1)) < np.linalg.norm(w) * theta


def test_printed_boer_has_the_opposite_sign():
    w = np.radians([6.0, -5.0, 6.5])
    t, b = constant_rate_field(w, 0.01, 20)
    printed = rf.boer_rate_printed(t, b)
    np.testing.assert_allclose(printed[1:], -rf.boer_rate(t, b)[1:], rtol=1e-12)
    truth = perpendicular(w, b[1:])
    # the printed form points away from the true perpendicular rate
    assert np.all(np.einsum("ij,ij->i", printed[1:], truth) < 0)


@pytest.mark.parametrize("dt_s", [0.01, 0.1, 1.0, 3.0])
def test_derivative_formula_exact_chord_value(dt_s):
    """For constant ω the chords Ḃ_k, Ḃ_{k−1} are ⊥ ω and differ by a rotation θ = |ω|Δt,
    so the formula returns sin(θ)/Δt · ω̂ exactly: full vector, +ω, error ≈ θ²/6."""
    w = np.radians([6.0, -5.0, 6.5])
    t, b = constant_rate_field(w, dt_s, 10)
    est = rf.derivative_rate(t, b)
    assert np.all(np.isnan(est[:2]))
    wn = np.linalg.norm(w)
    expected = np.sin(wn * dt_s) / dt_s * w / wn
    np.testing.assert_allclose(est[2:], np.broadcast_to(expected, est[2:].shape), atol=1e-12)


def test_error_bound_eq5_table():
    """Hand-evaluated sedelnikov2024 eq. 5 for B_{k−1} = (0, −0.1, 1), B_k = (0, 0, 1) (arbitrary units)."""
    t = np.array([0.0, 2.0])
    b = np.array([[0.0, -0.1, 1.0], [0.0, 0.0, 1.0]])
    d = 0.05
    bound = reference.boer_error_bound_eq5(t, b, d)[1]
    np.testing.assert_allclose(bound, [2 * d * np.sqrt(1 + 0.01) / 2, 2 * d * np.sqrt(1) / 2,
                                       2 * d * np.sqrt(0.01) / 2])


def test_error_bound_eq10_table():
    t = np.array([0.0, 1.0, 2.0])
    b = np.array([[0.0, 0.0, 1.0], [0.1, 0.0, 1.0], [0.1, 0.2, 1.0]])
    d = 0.01
    bound = reference.derivative_error_bound_eq10(t, b, d)[2]
    ds = 2 * d + d * 1.0
    dk2 = 0.04  # |ΔB_k|² = 0.2²
    np.testing.assert_allclose(bound, [ds * np.sqrt(0.04) / dk2, ds * np.sqrt(0.01) / dk2,
                                       ds * np.sqrt(0.04 + 0.01) / dk2])


@pytest.mark.parametrize("formula,cov", [(rf.boer_rate, rf.boer_covariance),
                                         (rf.derivative_rate, lambda t, b, s: rf.derivative_covariance(
                                             t, b, s, truncation=False))])
def test_propagated_covariance_matches_monte_carlo(formula, cov):
    rng = np.random.default_rng(7)
    w = np.radians([6.0, -5.0, 6.5])
    t, b = constant_rate_field(w, 1.0, 3)
    sigma = 0.05e-6  # small noise: the first-order propagation must hold
    samples = np.array([formula(t, b + rng.normal(0, sigma, b.shape))[2] for _ in range(4000)])
    predicted = cov(t, b, sigma)[2]
    np.testing.assert_allclose(np.cov(samples.T), predicted, rtol=0.12,
                               atol=0.05 * np.max(np.abs(predicted)))


@pytest.mark.parametrize("rate_dps,dt_s", [(16.0, 3.0), (16.0, 1.0), (25.0, 3.0)])
def test_derivative_sigma_holds_the_formulas_truncation_at_a_finite_step(rate_dps, dt_s):
    """For a constant ω (scipy's rotation as the truth) the derivative formula returns ω̂ along ω with
    |ω̂| = sin θ / Δt, θ = |ω|Δt (short by 11.5 % at 16 °/s and 3 s); with no noise its σ along ω is that
    shortfall, and the noise-only σ is zero."""
    w = np.radians(rate_dps) * np.array([0.48, -0.6, 0.64])
    t, b = constant_rate_field(w, dt_s, 4)
    est = rf.derivative_rate(t, b)[3]
    theta = np.linalg.norm(w) * dt_s
    np.testing.assert_allclose(est, w * np.sin(theta) / theta, rtol=1e-9)
    u = w / np.linalg.norm(w)
    cov = rf.derivative_covariance(t, b, 0.0)[3]
    short = np.linalg.norm(w) - np.linalg.norm(est)
    assert math.sqrt(u @ cov @ u) == pytest.approx(short, rel=1e-6)
    np.testing.assert_allclose(cov @ np.cross(u, [1.0, 0.0, 0.0]), 0.0, atol=1e-12 * short ** 2)
    assert np.all(rf.derivative_covariance(t, b, 0.0, truncation=False)[3] == 0.0)
    stream = rf.DerivativeStream(1e-12)
    for tk, bk in zip(t, b):
        stream.update(tk, bk)
    np.testing.assert_allclose(stream.sigma_radps, np.sqrt(np.diagonal(cov)), rtol=1e-6)


def test_streams_match_array_forms():
    rng = np.random.default_rng(1)
    w = np.radians([6.0, -5.0, 6.5])
    t, b = constant_rate_field(w, 1.0, 30)
    b = b + rng.normal(0, 1.5e-6, b.shape)
    boer, deriv = rf.BoerStream(1.5e-6), rf.DerivativeStream(1.5e-6)
    got_b, got_d = [], []
    for tk, bk in zip(t, b):
        got_b.append(boer.omega_radps.copy() if boer.update(tk, bk) else np.full(3, np.nan))
        got_d.append(deriv.omega_radps.copy() if deriv.update(tk, bk) else np.full(3, np.nan))
    np.testing.assert_allclose(np.array(got_b), rf.boer_rate(t, b), equal_nan=True, rtol=1e-12)
    np.testing.assert_allclose(np.array(got_d), rf.derivative_rate(t, b), equal_nan=True, rtol=1e-12)
    sig = np.sqrt(np.diagonal(rf.boer_covariance(t, b, 1.5e-6)[-1]))
    np.testing.assert_allclose(boer.sigma_radps, sig, rtol=1e-12)
    assert boer.flags == rf.BoerStream.PERPENDICULAR_ONLY


def test_degenerate_inputs_give_flagged_finite_estimates():
    deriv, boer = rf.DerivativeStream(1e-6), rf.BoerStream(1e-6)
    b = np.array([20e-6, 0.0, 0.0])
    for k in range(4):  # the field does not change: ω ∥ B or ω = 0
        deriv.update(float(k), b)
    assert deriv.flags & deriv.DEGENERATE
    assert np.all(np.isfinite(deriv.omega_radps)) and np.all(deriv.sigma_radps == rf.SIGMA_UNOBSERVED_RADPS)
    for k in range(3):  # a dead sensor reading zero
        boer.update(float(k), np.zeros(3))
    assert boer.flags & boer.DEGENERATE
    assert np.all(np.isfinite(boer.omega_radps)) and np.all(np.isfinite(boer.sigma_radps))


def test_out_of_order_samples_are_ignored():
    s = rf.BoerStream(1e-6)
    assert not s.update(1.0, B_I_T)
    assert not s.update(1.0, B_I_T)   # same time: no division by zero
    assert not s.update(0.5, B_I_T)   # earlier: ignored
    assert s.update(2.0, B_I_T * 1.01)


def test_bad_shapes_rejected():
    with pytest.raises(ValueError):
        rf.boer_rate(np.arange(3.0), np.zeros((3, 2)))
    with pytest.raises(ValueError):
        rf.derivative_rate(np.array([0.0, 1.0, 1.0]), np.zeros((3, 3)))
