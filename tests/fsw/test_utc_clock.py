"""The onboard UTC estimate against synthetic clocks: a known offset and drift, noisy sets, steps."""
import math

import numpy as np
import pytest

from fsw.estimation.utc_clock import UtcEstimator

UTC0 = 1_780_000_000.0  # 2026-05-28


def box_clock(offset_s, drift):
    """The box's monotonic time at true UTC u: mono = (u − UTC0 − offset) / (1 + drift)."""
    return lambda u: (u - UTC0 - offset_s) / (1.0 + drift)


def test_unknown_before_the_first_set():
    c = UtcEstimator()
    assert not c.known and math.isnan(c.utc_s(10.0)) and np.isnan(c.utc_s(np.array([1.0, 2.0]))).all()
    assert math.isnan(c.drift_ppm)


def test_one_set_gives_the_offset_and_no_drift_yet():
    mono = box_clock(offset_s=-12_345.6, drift=0.0)
    c = UtcEstimator()
    c.set(mono(UTC0 + 100.0), UTC0 + 100.0)
    assert c.known and math.isnan(c.drift)
    assert c.utc_s(mono(UTC0 + 5000.0)) == pytest.approx(UTC0 + 5000.0, abs=1e-6)


@pytest.mark.parametrize("drift_ppm", [-80.0, 0.0, 25.0])
def test_drift_from_successive_noisy_sets(drift_ppm):
    rng = np.random.default_rng(3)
    drift = drift_ppm * 1e-6
    mono = box_clock(offset_s=777.0, drift=drift)
    c = UtcEstimator(window=8, min_span_s=600.0)
    for k in range(8):  # a set every 15 min over 2 h, 20 ms of latency jitter each
        u = UTC0 + 900.0 * k
        c.set(mono(u), u + rng.normal(0.0, 0.02))
    # the slope of 8 sets over 6300 s with 20 ms noise: σ ≈ 0.02 / (6300 · 0.65) ≈ 5 ppm
    assert c.drift_ppm == pytest.approx(drift_ppm, abs=15.0)
    # a day after the last set, the drift-corrected UTC is far better than the offset alone
    u_later = UTC0 + 900.0 * 7 + 86400.0
    err = abs(c.utc_s(mono(u_later)) - u_later)
    assert err < 0.06 + 20e-6 * 86400  # the offset noise plus the drift's uncertainty for a day
    if drift_ppm:
        assert err < 0.5 * abs(drift) * 86400  # the offset alone would be off by |drift|·day


def test_a_step_restarts_the_drift_history_and_is_counted():
    mono = box_clock(0.0, 50e-6)
    c = UtcEstimator(min_span_s=600.0, max_step_s=1.0)
    for k in range(4):
        c.set(mono(UTC0 + 1000.0 * k), UTC0 + 1000.0 * k)
    assert c.drift_ppm == pytest.approx(50.0, abs=1e-3)
    c.set(mono(UTC0 + 4000.0), UTC0 + 4000.0 + 30.0)  # the ground's clock jumped 30 s
    assert c.steps == 1 and math.isnan(c.drift) and c.last_residual_s == pytest.approx(30.0, abs=1e-3)
    assert c.utc_s(mono(UTC0 + 4000.0)) == pytest.approx(UTC0 + 4030.0, abs=1e-6)


def test_refuses_non_finite_times():
    c = UtcEstimator()
    with pytest.raises(ValueError):
        c.set(1.0, math.nan)
    assert not c.known
