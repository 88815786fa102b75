"""The hard iron's thermal drift followed by the onboard calibration (fsw.estimation.magcal's first harmonic
per orbit, fsw.host_calibration's step) against the simulator's truth: a torque-free tumble (hil.dynamics)
in the field along the orbit (hil.field: IGRF-14 to degree 13; the box's own model is degree 8), the
shipped isoi host (hil.host_magnetics: hard ~12 µT, soft ~3 %, a thermal drift of 0.5 / −0.4 / 0.6 µT
over the orbit) and the isoi chip's noise (0.04 µT)."""
import functools

import numpy as np
import pytest

from fsw.estimation import field_motion as fm
from fsw.estimation import magcal as mc
from fsw.estimation.onboard_field import InterpolatedOrbitField, flight_field
from fsw.host_calibration import FixedField, HostCalibration, orbit_period_s
from fsw.telemetry.telemetry import Telemetry
from hil.dynamics import RigidBody
from hil.field import FieldAlongOrbit, IgrfField
from hil.host_magnetics import HostMagnetics
from hil.orbit import CircularOrbit
from support import MAGCAL_EPOCH, MAGCAL_ORBIT, Capture

CHIP_SIGMA_T = 0.04e-6
TARGET_T = 0.3e-6  # the residual target, per axis RMS


@functools.lru_cache(maxsize=None)
def tumble(duration_s: float):
    """(t, B in body axes [T]) along a 4 °/s torque-free tumble, 1 Hz."""
    orbit = CircularOrbit(*MAGCAL_ORBIT)
    t = np.arange(0.0, duration_s, 1.0)
    b_eci = FieldAlongOrbit(orbit, IgrfField(MAGCAL_EPOCH)).b_eci_T(t)
    rng = np.random.default_rng(3)
    w = rng.normal(size=3)
    body = RigidBody(np.diag([180.0, 220.0, 260.0]), rng.normal(size=4), w / np.linalg.norm(w) * np.radians(4.0))
    out = np.empty_like(b_eci)
    for k, tk in enumerate(t):
        while body.t_s < tk - 1e-9:
            body.step(min(2.0, tk - body.t_s), np.zeros(3))
        out[k] = body.dcm.T @ b_eci[k]
    return t, out


def isoi_host() -> HostMagnetics:
    """The shipped isoi scenario's host (hil/scenarios/isoi.toml), the drift's phase 30°."""
    return HostMagnetics(np.array([6.0, -9.0, 4.0]) * 1e-6,
                         np.array([[1.02, 0.01, -0.008], [0.01, 0.98, 0.012], [-0.008, 0.012, 1.03]]),
                         np.array([0.5, -0.4, 0.6]) * 1e-6, CircularOrbit(*MAGCAL_ORBIT).period_s, np.radians(30.0))


def fly(duration_s, jump_T=None, jump_at_s=np.inf):
    """The loop's calibration step over the record; per sample: state, hard iron applied [T], its σ [T],
    what it hands on, and the truth (hard iron, body field)."""
    t, b_body = tumble(duration_s)
    host = isoi_host()
    h_true = host.hard_iron_at_T(t)
    if jump_T is not None:
        h_true = h_true + np.where(t[:, None] >= jump_at_s, jump_T, 0.0)
    meas = b_body @ host.soft_iron.T + h_true + np.random.default_rng(4).normal(0.0, CHIP_SIGMA_T, b_body.shape)
    field = InterpolatedOrbitField(flight_field(fm.CircularOrbitModel(*MAGCAL_ORBIT), MAGCAL_EPOCH))  # as flown
    step = HostCalibration(CHIP_SIGMA_T, FixedField(field))
    n = len(t)
    state, b_T, sig_T, out = np.zeros(n, int), np.zeros((n, 3)), np.zeros((n, 3)), np.zeros((n, 3))
    for k in range(n):
        out[k] = step.process(float(t[k]), meas[k])
        state[k] = step.state
        b_T[k] = step.cal.calibration_at(float(t[k])).b_T
        sig_T[k] = step.cal.calibration.sigma[:3]
    # the noise-free sample as the step hands it on (its noise scaled by I + D taken out)
    clean = out - (meas - (b_body @ host.soft_iron.T + h_true)) @ (np.eye(3) + step.cal.calibration.D).T
    return step, t, state, b_T, sig_T, clean - b_body, h_true


def rms(x):
    return np.sqrt(np.mean(x ** 2, axis=0))


def test_the_period_of_the_drift_is_the_orbits():
    field = flight_field(fm.CircularOrbitModel(*MAGCAL_ORBIT), MAGCAL_EPOCH)
    assert orbit_period_s(field) == pytest.approx(CircularOrbit(*MAGCAL_ORBIT).period_s, rel=1e-9)
    assert orbit_period_s(InterpolatedOrbitField(field)) == orbit_period_s(field)
    assert orbit_period_s(object()) is None


def test_the_calibration_follows_the_drift_through_the_first_orbit():
    """Before: a constant calibration, ~0.4 µT off by mid-orbit, refused later minutes as misfits (REJECTED
    from ~2,500 s here). Now: never refused once applied, the hard iron within 0.1 µT of the truth at every
    sample after the first 1,000 s, and the field handed on within the target."""
    step, t, state, b_T, sig_T, resid_T, h_true = fly(3600.0)
    first = step.cal.first_good_at_s
    assert first is not None and first < 600.0
    assert not np.any(state[t > first] == mc.REJECTED)
    later = t > 1000.0
    assert np.max(np.abs(b_T[later] - h_true[later])) < 0.1e-6
    assert np.all(rms(resid_T[later]) <= TARGET_T)
    assert step.cal.dropped == 0


@pytest.mark.slow
def test_three_orbits_of_drift_tracked_with_an_honest_sigma_and_published():
    step, t, state, b_T, sig_T, resid_T, h_true = fly(3 * isoi_host().drift_period_s)
    P = isoi_host().drift_period_s
    assert not np.any(state[t > step.cal.first_good_at_s] == mc.REJECTED)
    assert state[-1] == mc.CONVERGED and step.cal.rejections <= 1  # at most the very first solution
    for j in (1, 2):  # the 2nd and 3rd orbits
        orbit = (t >= j * P) & (t < (j + 1) * P)
        assert np.all(rms(resid_T[orbit]) <= TARGET_T)
        assert np.max(np.abs(b_T[orbit] - h_true[orbit])) < 0.05e-6
    # the σ of the hard iron covers its error (within 1σ at least 68 % of the time, within 3σ always) and
    # says what it is worth (the field model's error is counted as noise: σ is on the safe side)
    after = t > step.cal.first_good_at_s
    ratio = np.abs(b_T[after] - h_true[after]) / sig_T[after]
    assert np.mean(ratio <= 1.0) >= 0.68 and np.all(ratio <= 3.0)
    assert np.all(sig_T[-1] < 0.03e-6)
    # DEBRIS_MAGCAL carries the drift's rate and period: the truth's rate within 0.5 µT/h
    link = Capture()
    step.telemetry(float(t[-1]), Telemetry(link))
    (msg,) = [m for m in link.messages() if m.get_type() == "DEBRIS_MAGCAL"]
    host = isoi_host()
    w = 2 * np.pi / host.drift_period_s
    rate_true_uT_h = host.drift_T * w * np.cos(w * t[-1] + host.drift_phase_rad) * 1e6 * 3600
    assert np.max(np.abs(np.array(msg.hard_iron_rate) - rate_true_uT_h)) < 0.5
    assert msg.drift_period == pytest.approx(P, rel=1e-6)


def test_a_sudden_jump_is_flagged_then_learned_again():
    """A 20 µT jump of the hard iron (a part magnetised, a latch-up's current): the minutes after it are
    refused as misfits and left out, the last good calibration stays applied and the state says REJECTED;
    after `restart_after` such minutes the sums start again and the new hard iron is learned and published
    within an orbit of the jump."""
    jump_at = 2500.0
    jump = np.array([20e-6, 0.0, 0.0])
    step, t, state, b_T, sig_T, resid_T, h_true = fly(jump_at + 4000.0, jump, jump_at)
    lim = step.cal.limits
    flagged = (t > jump_at + 61) & (t < jump_at + 60 * lim.restart_after)
    assert np.all(state[flagged] == mc.REJECTED)
    # the last good one applied: the hard iron of before the jump (to within 10 min of its drift)
    assert np.max(np.abs(b_T[flagged] - h_true[flagged] + jump)) < 0.5e-6
    assert step.cal.restarts == 1 and step.cal.dropped >= 60 * (lim.restart_after - 1)
    learned = np.flatnonzero((t > jump_at) & (state == mc.CONVERGED) | (t > jump_at) & (state == mc.UNCERTAIN))
    assert len(learned) and t[learned[0]] < jump_at + 3600.0
    end = t > t[-1] - 600.0
    assert np.max(np.abs(b_T[end] - h_true[end])) < 0.2e-6
    assert np.all(rms(resid_T[end]) <= TARGET_T)


def test_a_field_that_swings_far_beyond_a_thermal_drift_is_never_published():
    """A hard iron that swings by 20–30 µT over the orbit (a current loop, not the iron's temperature):
    no solution passes the checks (implausible drift, residual, conditioning), nothing is applied."""
    from support import MAGCAL_PERIOD_S, magcal_host, magcal_orbit, magcal_tumble

    t, _, b_mag = magcal_orbit()
    S, h = magcal_host(7)
    swing = np.sin(2 * np.pi * t / MAGCAL_PERIOD_S)[:, None] * np.array([30e-6, -20e-6, 25e-6])
    meas = magcal_tumble(1) @ S.T + h + swing + np.random.default_rng(0).normal(0.0, 1.5e-6, (len(t), 3))
    cal = mc.MagCal(1.5e-6, drift_period_s=MAGCAL_PERIOD_S)
    for k in range(len(t)):
        assert not cal.update(meas[k], b_mag[k], t[k])
    assert not cal.good and cal.state == mc.REJECTED and cal.rejections > 50
    np.testing.assert_array_equal(cal.apply(meas[-1], t[-1]), meas[-1])
