"""The onboard identification experiment (fsw.ident): commands, phases, actuators, the sliced fit, and
the magnets' path (M = p × B) against a simulated truth."""
from types import SimpleNamespace

import numpy as np
import pytest

from fsw.commands import CommandRouter
from fsw.estimation import euler_fit as ef
from fsw.estimation import inertia as inr
from fsw.estimation.euler_fit import field_error
from fsw.estimation.rotations import quat_to_dcm
from fsw.ident import (ABORTED, DONE, IDLE, MAGNETS, OBSERVE_FREE, TORQUE, TUG, IdentConfig,
                       IdentExperiment)
from fsw.telemetry.dialect import mavlink
from hil.dynamics import RigidBody
from hil.field import DipoleField, FieldAlongOrbit
from hil.orbit import CircularOrbit

FIELD = FieldAlongOrbit(CircularOrbit(490e3, 97.3), DipoleField(2025.5))


def cmd(command, *params):
    p = list(params) + [0.0] * (7 - len(params))
    return SimpleNamespace(command=command, confirmation=0, target_system=1, target_component=1,
                           **{f"param{i + 1}": float(v) for i, v in enumerate(p)})


def start(*params):
    return cmd(mavlink.MAV_CMD_DEBRIS_IDENT_START, *params)


class FakeTug:
    def __init__(self):
        self.calls = []

    def apply(self, start_s, duration_s, moment_Nm):
        self.calls.append(("apply", start_s, duration_s, tuple(moment_Nm)))

    def stop(self, now_s):
        self.calls.append(("stop", now_s))


def make(**kw):
    tug = FakeTug()
    ex = IdentExperiment(sigma_b_T=1.5e-6, b_inertial=FIELD.b_eci_T, tug=tug, **kw)
    router = CommandRouter()
    ex.register(router)
    return ex, tug, router


@pytest.mark.parametrize("params, why", [
    ((3, 10, 10, 10, 0.2), "source"),                 # not TUG/MAGNETS
    ((1, -1, 10, 10, 0.2), "negative duration"),
    ((1, 10, 0, 10, 0.2), "torque shorter than the minimum"),
    ((1, 10, 10, 10, 0, 0, 0), "zero moment"),
    ((1, 10, 10, 10, 80.0), "moment above the limit"),
    ((1, 1e4, 1e4, 1e4, 0.2), "too long"),
    ((1, float("nan"), 10, 10, 0.2), "NaN duration"),
    ((2, 10, 10, 10), "no magnets on board"),
])
def test_start_refuses_bad_parameters(params, why):
    ex, tug, router = make()
    assert router.handle(start(*params), 0.0) == mavlink.MAV_RESULT_DENIED, why
    assert ex.state == IDLE and not tug.calls


def test_start_needs_a_field_model_and_a_tug():
    router = CommandRouter()
    IdentExperiment(sigma_b_T=1.5e-6, b_inertial=None, tug=FakeTug()).register(router)
    assert router.handle(start(1, 10, 10, 10, 0.2), 0.0) == mavlink.MAV_RESULT_DENIED
    router = CommandRouter()
    IdentExperiment(sigma_b_T=1.5e-6, b_inertial=FIELD.b_eci_T).register(router)
    assert router.handle(start(1, 10, 10, 10, 0.2), 0.0) == mavlink.MAV_RESULT_DENIED


def test_phases_tug_and_stop():
    ex, tug, router = make()
    assert router.handle(start(TUG, 10, 20, 30, 0.2, -0.1, 0.05), 1.0) == mavlink.MAV_RESULT_ACCEPTED
    assert ex.state == OBSERVE_FREE
    # a second start while running is refused for now
    assert router.handle(start(TUG, 10, 20, 30, 0.2), 2.0) == mavlink.MAV_RESULT_TEMPORARILY_REJECTED
    t = 1.0
    while t <= 11.0:
        ex.step(t)
        t += 0.5
    assert ex.state == TORQUE
    assert tug.calls == [("apply", 11.0, 20.0, (0.2, -0.1, 0.05))]
    ex.step(20.0)
    assert router.handle(cmd(mavlink.MAV_CMD_DEBRIS_IDENT_STOP), 20.0) == mavlink.MAV_RESULT_ACCEPTED
    assert ex.state == ABORTED and tug.calls[-1] == ("stop", 20.0)
    a = ex.known_action()
    np.testing.assert_allclose(a.impulse_Nms(), np.array([0.2, -0.1, 0.05]) * 9.0)   # 11 s → 20 s
    # stopping again is harmless; a new experiment may start
    assert router.handle(cmd(mavlink.MAV_CMD_DEBRIS_IDENT_STOP), 21.0) == mavlink.MAV_RESULT_ACCEPTED
    assert router.handle(start(TUG, 5, 5, 5, 0.1), 22.0) == mavlink.MAV_RESULT_ACCEPTED
    assert ex.state == OBSERVE_FREE and not ex.t


def test_samples_kept_only_while_running_and_telemetry_cadence():
    ex, tug, router = make(config=IdentConfig(tlm_period_s=5.0))
    ex.on_sample(0.5, np.ones(3))
    assert not ex.t and not ex.telemetry_due(0.5)
    router.handle(start(TUG, 2, 2, 2, 0.2), 1.0)
    assert ex.telemetry_due(1.0)                     # the state changed
    assert not ex.telemetry_due(2.0)
    assert ex.telemetry_due(6.0)                     # the period
    for k in range(10):
        ex.on_sample(1.5 + k, np.full(3, 1e-5))
    ex.on_sample(3.5, np.ones(3))                    # not after the last one: ignored
    assert ex.t == [1.5 + k for k in range(6)]       # until the end of the experiment (7 s)
    f = ex.message_fields()
    assert f["samples"] == 0 and f["state"] == OBSERVE_FREE and f["flags"] == 0


def simulate(J, omega0_dps, T, moment_fn=None, dipole_fn=None, h=0.25, seed=0, sigma=1.5e-6):
    """Samples at 1 Hz (t = 0.5, 1.5, ...) of a rigid body under a moment and/or a dipole p × B."""
    body = RigidBody(J, np.array([0.9, 0.1, -0.3, 0.3]), np.radians(omega0_dps))
    rng = np.random.default_rng(seed)
    t, out_t, out_b = 0.0, [], []
    while t < T:
        t_next = t + h
        bI = FIELD.b_eci_T(t + h / 2)
        M = np.zeros(3) if moment_fn is None else moment_fn(t + h / 2)
        if dipole_fn is not None:
            M = M + np.cross(dipole_fn(t + h / 2), quat_to_dcm(body.q).T @ bI)
        body.step(h, M)
        t = t_next
        if abs((t - 0.5) % 1.0) < 1e-9:
            out_t.append(t)
            out_b.append(quat_to_dcm(body.q).T @ FIELD.b_eci_T(t) + sigma * rng.standard_normal(3))
    return np.array(out_t), np.array(out_b)


class FakeMagnets:
    """The box's magnets: a fixed dipole while open."""

    def __init__(self, dipole):
        self.p = np.array(dipole, float)
        self.is_open = False

    def open(self, now_s):
        self.is_open = True
        return True

    def close(self, now_s):
        self.is_open = False

    def dipole_body_Am2(self):
        return self.p if self.is_open else np.zeros(3)


def run_magnets(t, b, p, t_on, t_off, sigma, guess, **cfg):
    """The MAGNETS experiment on the samples (t, b) of a dipole p on [t_on, t_off), run to its end."""
    ex = IdentExperiment(sigma_b_T=sigma, b_inertial=FIELD.b_eci_T, magnets=FakeMagnets(p),
                         config=IdentConfig(inertia_guess_kgm2=guess, update_every_s=1e9, work_per_tick=10**9, **cfg))
    router = CommandRouter()
    ex.register(router)
    assert router.handle(start(MAGNETS, t_on, t_off - t_on, t[-1] + 0.5 - t_off), 0.0) == mavlink.MAV_RESULT_ACCEPTED
    k, now = 0, 0.0
    while ex.state not in (DONE, ABORTED) and now < 2000.0:
        if k < len(t) and t[k] <= now:
            ex.on_sample(t[k], b[k])
            k += 1
        ex.step(now)
        now = round(now + 0.5, 6)
    assert ex.state == DONE
    return ex


@pytest.mark.slow
def test_magnets_experiment_identifies_the_tensor_from_p_cross_b():
    """MAGNETS: the known moment is p × B, a function of the attitude the fit estimates. A 30 A·m² dipole
    for 240 s on a small body (diag(6, 7, 8.5) kg·m²). The sensor is quiet here (0.05 µT) so that a
    wrong moment model would show: with the sign of p × B flipped the fit is far off (checked below). The
    field model is exact here and taken so (no field error, no soft iron fitted: on 240 s those cost ~1 %)."""
    J = np.diag([6.0, 7.0, 8.5])
    p = np.array([0.0, 15.0, 26.0])
    t_on, t_off = 40.0, 280.0
    sigma = 0.05e-6
    t, b = simulate(J, [0.6, -0.4, 0.8], 420.0, dipole_fn=lambda tt: p if t_on <= tt < t_off else np.zeros(3),
                    sigma=sigma)
    ex = run_magnets(t, b, p, t_on, t_off, sigma, 5.0, field_error=False)
    a = ex.known_action()
    assert np.allclose(a.dipole_at(np.array([100.0]))[0], p) and not np.any(a.dipole_at(np.array([300.0])))
    e = ex.result.estimate
    err = np.abs(e.p - inr.params(J))
    assert np.all(err[:3] / np.diag(J) < 0.01), e.p
    assert np.all(err <= 3 * e.ci95 + 1e-4)
    assert e.flags == 7 and e.samples_used == len(t)
    flipped = ef.KnownAction(a.t_s, a.moment_Nm, -a.dipole_Am2)
    quick = ef.FitOptions(ms_iter=(20, 10, 10), ss_iter=10, chain_candidates=((0, 0),), starts_about_b=1)
    wrong = ef.identify(t, b[None], FIELD.b_eci_T, flipped, sigma, np.array([5.0, 5.0, 5.0, 0, 0, 0]), quick)[0]
    assert wrong.s2 > 5.0 and np.max(np.abs(wrong.p[:3] / np.diag(J) - 1)) > 0.1


@pytest.mark.slow
def test_magnets_experiment_fits_what_the_calibrations_leave_in_the_samples():
    """What the box's corrections leave in its samples, at the mission's sizes: the magnets' field at the
    sensor taken out by a model a few µT off while they are open (2.9 µT here, what its calibration's
    steps leave on a fast tumble), and the host's hard iron drifting from its calibration over the
    experiment (a thermal cycle: 1.6 µT here). Taken as exact, they bias the tensor beyond its intervals;
    fitted as terms of their own (the experiment's default), the tensor and the terms come out within
    theirs."""
    J = np.diag([6.0, 7.0, 8.5])
    p = np.array([0.0, 15.0, 26.0])
    t_on, t_off, T = 200.0, 1400.0, 1800.0
    sigma = 1.5e-6
    left = np.array([1.5e-6, -2.0e-6, 1.5e-6])
    t, b = simulate(J, [2.0, -1.5, 2.5], T, dipole_fn=lambda tt: p if t_on <= tt < t_off else np.zeros(3),
                    sigma=sigma, seed=3)
    on = (t >= t_on) & (t < t_off)
    x = 2.0 * (t - t[0]) / (t[-1] - t[0]) - 1.0
    drift = np.outer(x, [0.8e-6, -0.5e-6, 0.3e-6]) + np.outer(1.5 * x * x - 0.5, [-0.3e-6, 0.5e-6, 0.0])
    b[on] += left
    b += drift
    truth = inr.params(J)
    taken = run_magnets(t, b, p, t_on, t_off, sigma, 5.0, kit_offset_sigma_T=None, drift=False,
                        field_error=False).result
    assert taken.fit.errors is None
    assert np.any(np.abs(taken.estimate.p - truth) > taken.estimate.ci95), (taken.estimate.p, taken.estimate.ci95)
    fitted = run_magnets(t, b, p, t_on, t_off, sigma, 5.0).result
    e, terms = fitted.estimate, fitted.fit.errors
    assert np.all(np.abs(e.p - truth) <= e.ci95), (e.p, e.ci95)
    assert np.all(np.abs(e.p[:3] / np.diag(J) - 1) < 0.01)
    assert terms.kit_T.shape == (1, 3) and np.all(np.abs(terms.kit_T[0] - left) <= 3 * terms.kit_sigma_T[0])
    assert terms.drift_T.shape == (2, 3)        # degree_for(1,800 s): linear and quadratic
    assert np.all(np.abs(terms.drift_T - [[0.8e-6, -0.5e-6, 0.3e-6], [-0.3e-6, 0.5e-6, 0.0]])
                  <= 3 * terms.drift_sigma_T), (terms.drift_T, terms.drift_sigma_T)


def test_the_experiments_fit_takes_its_field_model_and_calibration_as_inexact():
    """The experiment's fit marginalises the field model's error, at the degree the record's length asks
    for, and the soft iron the host's calibration may have left, and profiles its cost along the scale;
    switched off, it takes both as exact and its curvature as the interval."""
    cfg = IdentConfig()
    opts = cfg.fit_options(2100.0, MAGNETS)
    assert opts.field_error_degree == field_error.degree_for(2100.0) == 2
    assert opts.soft_iron_sigma == cfg.soft_iron_sigma == 0.005 and opts.robust_cov
    assert opts.kit_offset_sigma_T == cfg.kit_offset_sigma_T and opts.drift_degree == 2
    assert opts.scale_profile == (0.98, 1.02, 0.96, 1.04)
    exact = IdentConfig(field_error=False, scale_profile=()).fit_options(2100.0, MAGNETS)
    assert exact.field_error_degree is None and exact.soft_iron_sigma is None and exact.scale_profile == ()
    assert not exact.robust_cov


def test_fit_runs_in_slices_and_finishes_done():
    """A TUG experiment on simulated samples: the fit job runs over many ticks (bounded work per tick)
    and the final estimate is the truth within its intervals."""
    J = np.diag([175.0, 200.0, 285.0])
    M = np.array([0.2, 0.15, -0.1])
    t, b = simulate(J, [0.8, -0.5, 1.2], 300.0, moment_fn=lambda tt: M if 60.0 <= tt < 180.0 else np.zeros(3),
                    h=0.5)
    ex, tug, router = make(config=IdentConfig(update_every_s=1e9, work_per_tick=15000))
    router.handle(start(TUG, 60, 120, 120, *M), 0.0)
    k, now, busy_ticks = 0, 0.0, 0
    while ex.state not in (DONE, ABORTED) and now < 5000.0:
        if k < len(t) and t[k] <= now:
            ex.on_sample(t[k], b[k])
            k += 1
        ex.step(now)
        busy_ticks += ex.busy
        now = round(now + 0.02, 6)
    assert ex.state == DONE
    assert tug.calls[0][:3] == ("apply", 60.0, 120.0)
    assert busy_ticks > 50                            # the fit was spread over many ticks
    e = ex.result.estimate
    assert np.all(np.abs(e.p[:3] - [175.0, 200.0, 285.0]) / [175.0, 200.0, 285.0] < 0.02), e.p
    assert np.all(np.abs(e.p - inr.params(J)) <= 3 * e.ci95 + 1e-3)
    f = ex.message_fields()
    assert f["state"] == DONE and f["samples"] == len(t) and f["flags"] == 7
    np.testing.assert_allclose(f["ci99"], e.ci99)


def test_a_record_longer_than_max_samples_keeps_every_other_sample_and_spans_the_whole_experiment():
    """4 h at 10 Hz is 144,000 samples against a record of 20,000: the record keeps every other sample
    each time it fills, so it still spans the experiment (the torque and the observation after it) at a
    regular rate, instead of stopping after the first 33 min. Here the same at a 100-sample record."""
    ex, tug, router = make(config=IdentConfig(max_samples=100, min_torque_s=1.0))
    assert router.handle(start(1, 10, 20, 15.0, 0.2), 0.0) == mavlink.MAV_RESULT_ACCEPTED
    t = np.arange(1, 451) * 0.1                                   # 45 s at 10 Hz, the experiment's span
    for tk in t:
        ex.on_sample(float(tk), np.array([20e-6, -10e-6, 30e-6]))
        ex.step(float(tk))
    kept = np.array(ex.t)
    assert ex.thinned == 3 and len(kept) <= 100                   # 450 → kept every 8th
    np.testing.assert_allclose(kept, t[::8])
    assert kept[0] == pytest.approx(0.1) and kept[-1] >= 44.0     # the whole span, torque and after
    assert len(ex.b) == len(kept)
