"""Kotelnikov (Whittaker–Shannon) series, sedelnikov2023 eq. 9: kernels, reconstruction, noise gains,
edge handling and the rate from it, against analytic truth."""
import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import estimation_reference as reference
from fsw.estimation import kotelnikov as ko

B_I_T = np.array([20e-6, -15e-6, 35e-6])


def test_sinc_derivative_kernels_are_the_derivatives_of_sinc():
    d1, d2 = ko.sinc_derivative_kernels(6)
    m = np.arange(-5, 6, dtype=float)
    h = 1e-4
    num1 = (np.sinc(m + h) - np.sinc(m - h)) / (2 * h)
    num2 = (np.sinc(m + h) - 2 * np.sinc(m) + np.sinc(m - h)) / h ** 2
    np.testing.assert_allclose(d1, num1, atol=1e-6)
    np.testing.assert_allclose(d2, num2, atol=2e-4)
    assert d2[5] == pytest.approx(-math.pi ** 2 / 3)


def test_series_interpolates_a_band_limited_signal():
    """A sum of sines below the Nyquist frequency is rebuilt between the samples (interior)."""
    dt = 1.0
    t = np.arange(400) * dt
    def f(x):
        return np.column_stack([np.sin(0.3 * x), np.cos(0.11 * x + 1), np.sin(0.05 * x) + 0.2 * np.sin(0.9 * x)])

    te = np.linspace(150.3, 250.7, 41)
    np.testing.assert_allclose(reference.kotelnikov_series(t, f(t), te), f(te), atol=0.02)
    # at the samples it returns the samples
    np.testing.assert_allclose(reference.kotelnikov_series(t, f(t), t[100:110]), f(t[100:110]), atol=1e-12)


def test_noise_gains():
    """White noise σ: σ_Ḃ = (π/√3) σ/Δt ≈ 1.81 σ/Δt, σ_B̈ = (π²/√5) σ/Δt² ≈ 4.41 σ/Δt²."""
    rng = np.random.default_rng(0)
    dt = 0.5
    x = rng.normal(size=(6000, 3))
    _, db, ddb = ko.kotelnikov_derivatives(np.arange(6000) * dt, x, detrend=False, edge_samples=0)
    assert np.std(db[1000:-1000]) * dt == pytest.approx(math.pi / math.sqrt(3), rel=0.03)
    assert np.std(ddb[1000:-1000]) * dt ** 2 == pytest.approx(math.pi ** 2 / math.sqrt(5), rel=0.03)


@pytest.mark.parametrize("w_dps,dt_s", [([6.0, -5.0, 6.5], 1.0), ([20.0, 3.0, -1.0], 0.5)])
def test_rate_from_the_series_on_a_constant_rate(w_dps, dt_s):
    """Noise-free constant rate: the analytic form (B̈ × Ḃ)/|Ḃ|² is exact away from the edges once the
    record's line is removed and the ends tapered; without that the ringing spoils every sample."""
    w = np.radians(w_dps)
    t = np.arange(200) * dt_s
    b = Rotation.from_rotvec(-np.outer(t, w)).apply(B_I_T)
    est, sig = ko.kotelnikov_rate(t, b, 0.5e-6)
    interior = slice(30, 170)
    assert np.max(np.linalg.norm(est[interior] - w, axis=1)) < math.radians(0.05)
    # the edges are flagged by a wider σ
    assert np.all(np.linalg.norm(sig[:8], axis=1) > 5 * np.median(np.linalg.norm(sig[interior], axis=1)))
    raw, _ = ko.kotelnikov_rate(t, b, detrend=False, edge_samples=0)
    raw_err = np.median(np.linalg.norm(raw[interior] - w, axis=1))
    assert raw_err > 10 * np.median(np.linalg.norm(est[interior] - w, axis=1))


def test_sigma_per_axis_covers_the_noise_error():
    """The first-order σ per axis (∂ω/∂Ḃ, ∂ω/∂B̈ with the series' noise gains) covers 62–80 % of the per-axis
    errors of a noisy constant rate away from the edges (75 % here: the division by |Ḃ|² is not linear at
    12 % noise on Ḃ); the norm of the error put on every axis covered 90–92 %."""
    w = np.radians([6.0, -5.0, 6.5])
    t = np.arange(2000) * 1.0
    b = Rotation.from_rotvec(-np.outer(t, w)).apply(B_I_T)
    rng = np.random.default_rng(11)
    z = []
    for _ in range(4):
        est, sig = ko.kotelnikov_rate(t, b + rng.normal(scale=0.3e-6, size=b.shape), 0.3e-6)
        z.append(np.abs(est - w)[50:-50] / sig[50:-50])
    cover = np.mean(np.concatenate(z) < 1.0, axis=0)
    assert np.all((cover > 0.62) & (cover < 0.8)), cover   # the norm on every axis: 0.90–0.92


def test_paper_form_is_the_derivative_formula_with_series_derivatives():
    """sedelnikov2023 eq. 1 with the series' Ḃ at consecutive samples: for constant ω the two Ḃ differ by a
    rotation θ = |ω|Δt about ω, so the formula returns sin(θ)/Δt along ω̂ (a bias at coarse sampling)."""
    w = np.radians([16.0, 12.0, -18.0])
    dt = 1.0
    t = np.arange(200) * dt
    b = Rotation.from_rotvec(-np.outer(t, w)).apply(B_I_T)
    est, _ = ko.kotelnikov_rate(t, b, form="paper")
    th = np.linalg.norm(w) * dt
    np.testing.assert_allclose(est[100], math.sin(th) / dt * w / np.linalg.norm(w), atol=math.radians(0.05))
    assert np.all(np.isnan(est[0]))


def test_boer_with_the_analytic_derivative_is_the_perpendicular_rate():
    w = np.radians([6.0, -5.0, 6.5])
    t = np.arange(200) * 1.0
    b = Rotation.from_rotvec(-np.outer(t, w)).apply(B_I_T)
    est = reference.kotelnikov_boer_rate(t, b)
    bh = b / np.linalg.norm(b, axis=1, keepdims=True)
    perp = w - (bh @ w)[:, None] * bh
    assert np.max(np.linalg.norm(est[30:170] - perp[30:170], axis=1)) < math.radians(0.05)


def test_non_uniform_sampling_is_refused_and_can_be_resampled():
    t = np.cumsum(np.r_[0.0, np.full(50, 1.0)])
    t[20] += 0.3
    b = np.random.default_rng(1).normal(size=(51, 3))
    with pytest.raises(ValueError, match="uniform"):
        ko.kotelnikov_rate(t, b)
    tu, bu = ko.resample_uniform(t, b)
    assert np.allclose(np.diff(tu), 1.0) and bu.shape == (len(tu), 3)
