"""A degenerate sample — no field, a field that does not change — carries no information about the rate:
every estimator says so with σ = inf (array forms, ground) or the DEGENERATE flag with the link's finite
'unobserved' σ (streaming forms, flight), never σ = 0 with a finite ω."""
import math

import numpy as np
import pytest

from fsw.estimation import attitude_kalman as ak
from fsw.estimation import filter_banks as fb
from fsw.estimation import kotelnikov as ko
from fsw.estimation import rate_formulas as rf
from fsw.estimation import rate_kalman as rk
from ground.recording import RateEstimates, RecordingError, read_rate_estimates, write_rate_estimates

SIGMA_B = 0.5e-6
B = np.array([20e-6, -15e-6, 35e-6])
N = 30
T = np.arange(N) * 1.0
ZERO = np.zeros((N, 3))
STILL = np.tile(B, (N, 1))                        # ω = 0, or ω ∥ B: ΔB = 0


def no_information(sigma):
    """Every row with an estimate has σ = inf on every axis."""
    s = sigma[~np.isnan(sigma).any(axis=1)]
    return s.size > 0 and np.all(np.isinf(s))


@pytest.mark.parametrize("field", ["zero", "near_zero"])
def test_boer_without_a_field(field):
    b = ZERO if field == "zero" else np.random.default_rng(1).normal(scale=0.5 * SIGMA_B, size=(N, 3))
    cov = rf.boer_covariance(T, b, SIGMA_B)
    assert np.all(np.isinf(np.diagonal(cov[1:], axis1=1, axis2=2)))
    assert np.all(np.isfinite(rf.boer_rate(T, b)[1:]))
    if field == "zero":
        assert np.all(rf.boer_rate(T, b)[1:] == 0.0)
        assert np.all(np.isinf(np.diagonal(rf.boer_covariance(T, b, 0.0)[1:], axis1=1, axis2=2)))


def test_derivative_without_a_field_change():
    for b in (ZERO, STILL):
        cov = rf.derivative_covariance(T, b, SIGMA_B)
        assert np.all(np.isinf(np.diagonal(cov[2:], axis1=1, axis2=2)))
        assert np.all(rf.derivative_rate(T, b)[2:] == 0.0)


def test_a_degenerate_row_does_not_spill_onto_its_neighbours():
    b = np.array([B, B * 0.99, np.zeros(3), B, B * 1.01])
    t = np.arange(5.0)
    s = np.sqrt(np.diagonal(rf.boer_covariance(t, b, SIGMA_B), axis1=1, axis2=2))
    assert np.all(np.isinf(s[2])) and np.all(np.isfinite(s[[1, 3, 4]])) and np.all(s[[1, 3, 4]] > 0)


@pytest.mark.parametrize("stream, field", [(rf.BoerStream, ZERO), (rf.DerivativeStream, ZERO),
                                           (rf.DerivativeStream, STILL)])
def test_the_streams_flag_it_with_the_links_finite_sigma(stream, field):
    s = stream(SIGMA_B)
    published = [s.update(t, b) and (s.flags, s.omega_radps.copy(), s.sigma_radps.copy())
                 for t, b in zip(T, field)]
    for flags, w, sg in [p for p in published if p]:
        assert flags & s.DEGENERATE and np.all(np.isfinite(w))
        assert np.all(sg == rf.SIGMA_UNOBSERVED_RADPS)


@pytest.mark.parametrize("form", ["analytic", "paper"])
@pytest.mark.parametrize("field", ["zero", "still"])
def test_kotelnikov(form, field):
    w, s = ko.kotelnikov_rate(T, ZERO if field == "zero" else STILL, SIGMA_B, form=form)
    first = 1 if form == "paper" else 0
    assert np.all(np.isinf(s[first:])) and np.all(np.isfinite(w[first:]))
    assert np.all(np.isnan(w[:first]))


def test_the_kalman_filter_on_a_zero_field():
    w, s, flags = rk.kalman_rate(T, ZERO, SIGMA_B)       # was 0 ± 28.6 °/s: the prior, as an estimate
    assert no_information(s)
    ok = ~np.isnan(s).any(axis=1)
    assert np.all(flags[ok] & rk.DEGENERATE) and np.all(np.isfinite(w[ok]))


@pytest.mark.parametrize("kind", ["orbit", "models", "hypotheses"])
def test_the_attitude_filters_wait_for_a_field(kind):
    """No field, no attitude to align with the model's: no estimate (NaN), flagged; after a zero sample
    in a running filter that sample's σ is inf."""
    from fsw.estimation import field_motion as fm
    fld = fm.OrbitField(fm.CircularOrbitModel(500e3, 97.0))
    run = {"orbit": ak.attitude_kalman_rate, "models": fb.rate_model_bank_rate,
           "hypotheses": fb.euler_acquisition_rate}[kind]
    kw = {"field_eci_T": fld}
    with np.errstate(all="raise"):
        w, s, flags = run(T, ZERO, SIGMA_B, **kw)
    assert np.all(np.isnan(w)) and np.all(np.isnan(s)) and np.all(flags & rk.DEGENERATE)
    b = 40e-6 * fld(T) / np.linalg.norm(fld(T), axis=1, keepdims=True)
    b[20] = 0.0
    w, s, flags = run(T, b, SIGMA_B, **kw)
    assert np.all(np.isinf(s[20])) and flags[20] & rk.DEGENERATE and np.all(np.isfinite(s[5:20]))


def test_the_smoothers_on_a_zero_field():
    from ground import smoother as sm
    rw = sm.rts_smooth(T, ZERO, SIGMA_B)
    assert no_information(rw.sigma_radps)
    eu = sm.smooth(T, ZERO, SIGMA_B, model="euler")             # σ = s²(JᵀJ)⁻¹ was 0: χ² = 0, J = 0
    assert no_information(eu.sigma_radps)


def test_sigma_inf_goes_through_the_rate_estimate_csv_and_the_plot(tmp_path):
    from ground.plot import plot_rates
    w = np.array([[np.nan] * 3, [0.1, 0.2, 0.3], [0.0, 0.0, 0.0]])
    s = np.array([[np.nan] * 3, [0.01, 0.02, 0.03], [math.inf] * 3])
    path = tmp_path / "r.csv"
    write_rate_estimates(path, RateEstimates([0.0, 1.0, 2.0], w, s))
    assert path.read_text().splitlines()[-1] == "2.0,0,0,0,inf,inf,inf"
    back = read_rate_estimates(path)
    assert np.all(np.isinf(back.sigma_radps[2])) and np.all(np.isnan(back.sigma_radps[0]))
    np.testing.assert_allclose(back.sigma_radps[1], s[1], rtol=1e-12)
    with pytest.raises(RecordingError, match="wx_dps"):
        write_rate_estimates(tmp_path / "x.csv", RateEstimates([0.0], [[math.inf, 0, 0]], [[0.1, 0.1, 0.1]]))
    bad = tmp_path / "neg.csv"
    bad.write_text(path.read_text().replace("inf,inf,inf", "-inf,inf,inf"))
    with pytest.raises(RecordingError, match=r"neg\.csv:\d+: column 'sx_dps'"):
        read_rate_estimates(bad)
    png = tmp_path / "r.png"
    plot_rates(png, back.t_s, back.w_radps, back.sigma_radps)
    assert png.read_bytes()[:4] == b"\x89PNG"


def test_the_replays_csv_writes_the_links_unobserved_sigma_as_inf(tmp_path):
    from types import SimpleNamespace

    from ground.replay import write_replay_rates
    replay = SimpleNamespace(t=np.array([0.0, 1.0, 2.0]), b=np.tile(B, (3, 1)))
    rates = {1.0: (np.zeros(3), np.full(3, rf.SIGMA_UNOBSERVED_RADPS)), 2.0: (np.ones(3) * 0.1, np.full(3, 0.01))}
    write_replay_rates(tmp_path / "r.csv", replay, rates, "rec.csv")
    s = read_rate_estimates(tmp_path / "r.csv").sigma_radps
    assert np.all(np.isnan(s[0])) and np.all(np.isinf(s[1])) and np.allclose(s[2], 0.01)
