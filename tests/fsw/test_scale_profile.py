"""The profile of the fit's cost along the tensor's scale (fsw.estimation.euler_fit.profile): its 95 %
interval against the parabola's, and the covariance it widens."""
import numpy as np
import pytest

from fsw.estimation.euler_fit import profile

X0 = 22.0


def parabola(sigma_rel, factors=(0.98, 1.02, 0.96, 1.04)):
    x = X0 * np.asarray(factors)
    return x, ((x - X0) / (sigma_rel * X0)) ** 2


@pytest.mark.parametrize("sigma_rel", [0.01, 0.02, 0.05])
def test_a_parabolas_profile_gives_its_own_interval(sigma_rel):
    # Δχ² = (δ/σ)² reaches 3.84 at 1.96 σ: between the points linearly (within 2.5 %), beyond them exactly
    x, d = parabola(sigma_rel)
    for side in (-1, 1):
        h = profile.half_width(x, d, X0, side)
        assert h == pytest.approx(1.959964 * sigma_rel, rel=0.025)
    prof = profile.profile_of(x, d * 0.9, X0, 0.0, 0.9, 1.959964 * sigma_rel)
    assert prof.ratio == pytest.approx(1.0, abs=0.025)


def test_a_flat_profile_is_wider_and_widens_the_scale_only():
    x = X0 * np.array([0.98, 1.02, 0.96, 1.04])
    d = np.array([2.5, 0.7, 11.2, 6.9])                      # seed 4's first experiment (χ² units of s²)
    p = np.array([X0, 24.0, 12.0, 0.3, -0.2, 0.3])
    cov = np.diag((0.008 * p / 1.96) ** 2 + 1e-6)
    curv = 1.96 * np.sqrt(cov[0, 0]) / X0                      # the curvature's half-width, ~0.8 %
    prof = profile.profile_of(x, d, X0, 0.0, 1.0, curv)
    lo, hi = prof.half_widths
    # where the profile, drawn through its points, crosses χ²₁(0.95) = 1.96²: between the 2 % and 4 % points
    assert 0.02 < lo < 0.04 and 0.02 < hi < 0.04
    assert np.interp(lo, [0.0, 0.02, 0.04], [0.0, 2.5, 11.2]) == pytest.approx(1.959964 ** 2, rel=1e-6)
    assert np.interp(hi, [0.0, 0.02, 0.04], [0.0, 0.7, 6.9]) == pytest.approx(1.959964 ** 2, rel=1e-6)
    assert prof.ratio == pytest.approx(hi / curv)
    wide = profile.widened_cov(p, cov, prof)
    assert 1.96 * np.sqrt(wide[0, 0]) / X0 == pytest.approx(hi, rel=1e-6)   # Ixx's interval is the profile's
    extra = wide - cov
    np.testing.assert_allclose(extra, extra[0, 0] * np.outer(p, p) / X0 ** 2, rtol=1e-12)   # along p pᵀ
    narrow = profile.profile_of(x, 100 * d, X0, 0.0, 1.0, curv)
    assert narrow.ratio < 1 and profile.widened_cov(p, cov, narrow) is cov   # never narrower


def test_a_profile_that_never_rises_is_unbounded_and_left_to_the_curvature():
    x = X0 * np.array([0.98, 1.02])
    prof = profile.profile_of(x, np.zeros(2), X0, 0.0, 1.0, 0.01)
    assert prof.half_widths == (np.inf, np.inf)
    cov = np.eye(6)
    assert profile.widened_cov(np.ones(6), cov, prof) is cov


def test_a_profile_point_below_the_minimum_is_where_the_fit_goes_on():
    """Started 4 % off the minimum along the scale, the profile's 0.96 point is a better fit: the result,
    and the θ handed on (to the field error's step), are the fit from there, back at the minimum."""
    from fsw.estimation import euler_fit as ef
    from fsw.estimation.euler_fit import identification as idn
    from fsw.estimation.euler_fit.solver import LMRuns, complete, lm
    from test_euler_fit import ASYM, FIELD, M_PULSE, PULSE, simulate

    sigma = 0.5e-6
    action = ef.KnownAction.pulses([(PULSE[0], PULSE[1] - PULSE[0], M_PULSE)])
    t, b, _ = simulate(ASYM, [1.0, 0.6, -0.9], 300.0, lambda tt: M_PULSE if PULSE[0] <= tt < PULSE[1] else 0 * M_PULSE,
                       sigma=sigma)
    guess = np.array([200.0] * 3 + [0.0] * 3)
    opts = ef.FitOptions(scale_profile=(0.96, 1.04), ss_iter=15)
    fit = ef.identify(t, b[None], FIELD.b_eci_T, action, sigma, guess, ef.FitOptions())[0]
    ss, theta = idn.single_shooting_for(t, b, FIELD.b_eci_T, action, sigma, fit, opts)
    prior = idn.fit_prior(ss.n_params, ss.inertia.n, ss.inertia.from_p(guess), opts, sigma, ss.inertia)
    off = theta.copy()
    off[:6] *= 1.04
    runs = lm(ss, LMRuns(off[None].copy()), prior, 1, frozen=np.ones(ss.n_params, bool))   # the cost there
    res_off = idn.results(ss, runs, prior)[0]
    res, prof, (problem, th, run) = complete(idn._scale_profile(ss, 0, off, res_off, prior, opts, 0, None))
    assert res.chi2 < res_off.chi2 - 10 * res_off.s2
    np.testing.assert_allclose(res.p, fit.p, rtol=2e-3)                          # back at the minimum
    np.testing.assert_allclose(problem.inertia.to_p(th[None, :6], np.array([run]))[0], res.p, rtol=1e-12)
    assert prof.ixx_min_kgm2 == res.p[0] and np.min(prof.delta_chi2) >= 0.0
