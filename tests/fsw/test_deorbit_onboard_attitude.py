"""The de-orbit controller on the box's own estimate: no pulse on an attitude it cannot trust (the kit
holds both capsules closed, counts the period and says why), the trust gate's conditions, the known
dipole the estimate is given, and the controller's inputs in DEBRIS_DEORBIT_ATTITUDE."""
import math
from types import SimpleNamespace

import numpy as np
import pytest

from fsw.deorbit.controller import AttitudeInput
from fsw.deorbit.kit import DeorbitKit
from fsw.deorbit.onboard_attitude import EstimatedAttitude, TrustGate
from fsw.estimation.field_motion import CircularOrbitModel, DipoleModel, OrbitField
from fsw.estimation.orbital_attitude import OrbitInputs, orbital_frame
from fsw.estimation.rotations import quat_from_dcm
from fsw.host_calibration import FixedField
from fsw.telemetry.dialect import mavlink
from fsw.telemetry.telemetry import Telemetry
from hil.deorbit_kit import DeorbitKitEmulator
from support import Capture

pytestmark = pytest.mark.fsw
DT = 0.1


class Untrusted:
    description = "never trusted"
    reason = "pointing sigma 0.300 rad > 0.1"

    def attitude(self, now_s):
        return None


def start_controller(kit, t):
    msg = SimpleNamespace(command=mavlink.MAV_CMD_DEBRIS_CONTROLLER, param1=1, param2=0, param3=0, param4=0,
                          param5=0, param6=0, param7=0)
    return kit.handle_command(msg, t)


class Clock:
    """The loop's time over the emulator: `ticks(seconds)` yields each tick's time `t`, the emulator
    advanced to it."""

    def __init__(self, emu):
        self.emu, self.t = emu, 0.0

    def ticks(self, seconds):
        for _ in range(int(round(seconds / DT))):
            self.t = round(self.t + DT, 9)
            self.emu.advance_to(self.t)
            yield self.t


def whole_second(t):
    return abs(t - round(t)) < 1e-6


def run_controller(attitude, seconds, tlm=None):
    """The kit on `attitude`, its magnets homed and its controller started, run for `seconds`."""
    emu = DeorbitKitEmulator()
    kit = DeorbitKit(emu, attitude)
    clock = Clock(emu)
    for ch in (0, 1):
        kit.sequencer.request_home(ch, clock.t)
    for t in clock.ticks(3.0):
        kit.tick(t)
    assert start_controller(kit, clock.t) == mavlink.MAV_RESULT_ACCEPTED
    for t in clock.ticks(seconds):
        kit.tick(t)
        if tlm is not None:
            kit.telemetry(t, tlm)
    return emu, kit


def test_no_pulse_on_an_untrusted_attitude_capsules_held_closed_and_reported():
    cap = Capture()
    emu, kit = run_controller(Untrusted(), 350.0, Telemetry(cap))  # four controller periods
    assert kit.decisions_without_attitude == 4 and kit.controller.decisions == 0
    assert all(c.openings == 0 and c.shutter == 0.0 for c in emu.channels)  # never unscreened
    assert kit.hold_reason == Untrusted.reason
    msgs = cap.messages()
    texts = [m.text for m in msgs if m.get_type() == "STATUSTEXT"]
    assert sum("capsules held closed: pointing sigma" in x for x in texts) == 1  # once, when it changed
    att = [m for m in msgs if m.get_type() == "DEBRIS_DEORBIT_ATTITUDE"]
    assert att and att[-1].held == 4 and att[-1].source == mavlink.DEBRIS_CONTROLLER_ATTITUDE_NONE
    assert math.isnan(att[-1].yaw)


class ForecastFails:
    """A trusted attitude whose field forecast along the orbit fails (SGP4 over the controller's horizon)."""
    description = "trusted, forecast failing"
    reason = ""

    def attitude(self, now_s):
        def forecast(t_s):
            raise ValueError("SGP4 error codes [6]")
        return AttitudeInput(np.eye(3), np.zeros(3), np.array([20e-6, 0.0, 30e-6]), forecast)


def test_a_decision_whose_field_forecast_fails_holds_the_capsules_and_says_why():
    emu, kit = run_controller(ForecastFails(), 250.0)  # three controller periods: the loop goes on
    assert kit.decisions_without_attitude == 3 and kit.hold_reason == "field forecast: SGP4 error codes [6]"
    assert all(c.openings == 0 and c.shutter == 0.0 for c in emu.channels)


def test_the_known_dipole_follows_the_open_capsules_and_polarity():
    emu = DeorbitKitEmulator()
    kit = DeorbitKit(emu)
    clock = Clock(emu)

    def run(seconds):
        for t in clock.ticks(seconds):
            kit.tick(t)

    seq = kit.sequencer
    seq.request_home(0, clock.t)
    seq.request_home(1, clock.t)
    run(3.0)
    assert np.all(kit.known_dipole_body_Am2() == 0.0)  # both screened
    assert seq.request_turn(0, 100, clock.t).accepted  # the pitch magnet half a turn: polarity −1
    run(10.0)
    assert seq.request_capsule(0, True, clock.t).accepted and seq.request_capsule(1, True, clock.t).accepted
    run(5.0)
    # pitch magnet along body z (turned: −z), yaw magnet along body y, 15 A·m² each (the design)
    assert kit.known_dipole_body_Am2() == pytest.approx([0.0, 15.0, -15.0])
    # the emulator's truth agrees
    assert emu.dipole_body_Am2() == pytest.approx([0.0, 15.0, -15.0], abs=1e-6)



class Recorder:
    """An attitude source that only keeps what the kit hands it."""

    description = "records the samples"

    def __init__(self):
        self.seen = []
        self.covs = []

    def observe(self, t_s, b_T, dipole_body_Am2, mean_dipole_body_Am2=None, kit_step_cov_T2=None):
        self.seen.append((t_s, np.array(dipole_body_Am2), mean_dipole_body_Am2))
        self.covs.append(kit_step_cov_T2)

    def attitude(self, now_s):
        return None


def test_the_mean_dipole_between_samples_is_the_emulators_impulse_shutter_ramps_included():
    """The kit hands the estimate the mean of its dipole since the previous sample, a moving shutter counted
    as half open: over a capsule's opening (2 s ramp) and closing (0.5 s) its time integral is the emulator's
    ∫ p dt (what the torque acts with) to a loop tick's worth, where the dipole held from the previous sample
    is seconds of the full dipole off."""
    emu = DeorbitKitEmulator()
    src = Recorder()
    kit = DeorbitKit(emu, src)
    clock = Clock(emu)
    true_impulse, held_impulse = np.zeros(3), np.zeros(3)
    held = np.zeros(3)
    seq = kit.sequencer

    def run(seconds):
        nonlocal held
        p0 = emu.dipole_body_Am2()
        for t in clock.ticks(seconds):
            p1 = emu.dipole_body_Am2()
            true_impulse[:] += 0.5 * (p0 + p1) * DT  # the ramp is linear within a tick
            p0 = p1
            sample = SimpleNamespace(t_s=t, b_T=np.zeros(3)) if whole_second(t) else None
            kit.tick(t, sample)
            if sample is not None:
                held_impulse[:] += held * 1.0
                held = src.seen[-1][1]

    seq.request_home(0, clock.t)
    seq.request_home(1, clock.t)
    run(5.0)
    true_impulse[:], held_impulse[:] = 0.0, 0.0
    n0 = len(src.seen)
    assert seq.request_capsule(1, True, clock.t).accepted  # the yaw magnet, +15 A·m² along body y
    run(10.0)
    assert emu.dipole_body_Am2() == pytest.approx([0.0, 15.0, 0.0], abs=1e-6)
    assert seq.request_capsule(1, False, clock.t).accepted
    run(5.0)
    assert np.all(emu.dipole_body_Am2() == 0.0)
    mean_impulse = sum(m * 1.0 for _, _, m in src.seen[n0:])  # one sample a second
    assert true_impulse[1] == pytest.approx(15.0 * 10.0, abs=15.0 * 2.5)  # about 10 s open
    assert mean_impulse == pytest.approx(true_impulse, abs=15.0 * 2 * DT)  # A·m²·s: a tick at each end
    assert abs(held_impulse[1] - true_impulse[1]) > 15.0 * 0.5  # the held dipole misses the ramps


def test_the_step_the_kit_field_models_error_may_make_is_handed_with_the_sample():
    """At a capsule's opening the kit hands the estimate the kit-field model's covariance of that change
    (before any calibration step: its prior, 15 % of the magnet's field per axis, times the change of the
    screening, 1 − leakage); at rest nothing; while a shutter moves no sample is handed over (the flight loop
    skips them), and a covariance of None would say the state is not known."""
    emu = DeorbitKitEmulator()
    src = Recorder()
    kit = DeorbitKit(emu, src)
    clock = Clock(emu)

    def run(seconds):
        for t in clock.ticks(seconds):
            kit.sensor_field.poll(t)  # as the flight loop does every tick
            moving = any(ch.capsule.state.name in ("OPENING", "CLOSING") for ch in kit.sequencer.channels)
            kit.tick(t, SimpleNamespace(t_s=t, b_T=np.zeros(3)) if whole_second(t) and not moving else None)

    kit.sequencer.request_home(0, clock.t)
    kit.sequencer.request_home(1, clock.t)
    run(5.0)
    n0 = len(src.covs)
    assert kit.sequencer.request_capsule(1, True, clock.t).accepted  # the yaw magnet opens
    run(10.0)
    covs = [c for c in src.covs[n0:] if c is not None]
    steps = [c for c in covs if np.trace(c) > 0.0]
    assert len(steps) == 1  # the one change of state; at rest nothing more
    m = kit.sensor_field.models[1]
    sigma = 0.15 * float(np.linalg.norm(m.fa_design_T)) * (1.0 - m.leakage)
    assert np.sqrt(np.diag(steps[0])) == pytest.approx([sigma] * 3, rel=1e-9)
    assert sigma > 5e-6  # T: five times the 1 µT a change opened the bias by before


def _estimate():
    """An estimate fed 120 samples of a body at rest in the orbital frame (yaw = pitch = roll = 0)."""
    orbit = CircularOrbitModel(600e3, 97.8)
    fld = OrbitField(orbit, DipoleModel(2025.0), era0_rad=0.0)
    inputs = OrbitInputs(fld)
    src = EstimatedAttitude(1.5e-6, gate=TrustGate(), provider=FixedField(fld))
    for t in np.arange(0.0, 120.0):
        r, v, b_eci = inputs(float(t))
        R_oi, _ = orbital_frame(r, v)  # body = orbital frame
        src.observe(float(t), R_oi.T @ b_eci, np.zeros(3))
    return src, R_oi


def test_the_trust_gate_needs_time_sigma_fit_and_agreeing_hypotheses():
    src, R_oi = _estimate()
    assert src.attitude(119.0) is None and "running" in src.reason and not src.trusted
    # the same estimate judged after its minimum run: the hypotheses about B still disagree
    src.bank.t_start_s = -1e4
    assert src.attitude(119.0) is None
    assert "sigma" in src.reason or "disagree" in src.reason
    # one hypothesis, put on the truth, with a small covariance: trusted, and the attitude it gives is right
    best = src.bank.best
    best.q = quat_from_dcm(R_oi)
    best.P = np.diag([1e-4] * 3 + [1e-10] * 3 + [0.01] * 3)
    src.bank.members = [best]
    src.nis_mean = 3.0
    att = src.attitude(119.0)
    assert att is not None and src.trusted and src.reason == ""
    assert att.R_bo == pytest.approx(np.eye(3), abs=1e-3)
    assert att.b_orbital_forecast(np.array([200.0, 300.0])).shape == (2, 3)
    rep = src.report()
    assert rep.source == mavlink.DEBRIS_CONTROLLER_ATTITUDE_TRUSTED and rep.hypotheses == 1
    # once trusted, a σ between the limit and twice the limit keeps the trust (no flapping) ...
    limit = src.gate.max_pointing_sigma_rad
    best.P[1, 1] = (1.5 * limit) ** 2
    assert src.attitude(119.0) is not None and src.trusted
    # ... but is not enough to gain it
    src.trusted = False
    assert src.attitude(119.0) is None and "pointing sigma" in src.reason
    best.P[1, 1] = 1e-4
    assert src.attitude(119.0) is not None
    # samples that do not fit: not trusted
    src.nis_mean = 50.0
    assert src.attitude(119.0) is None and "do not fit" in src.reason
    src.nis_mean = 3.0
    best.P[2, 2] = (2.5 * limit) ** 2  # pointing σ about body z beyond even the trusted limit
    assert src.attitude(119.0) is None and "pointing sigma" in src.reason


def _trusted_estimate():
    src, R_oi = _estimate()
    src.bank.t_start_s = -1e4
    best = src.bank.best
    best.q, best.P = quat_from_dcm(R_oi), np.diag([1e-4] * 3 + [1e-10] * 3 + [0.01] * 3)
    src.bank.members = [best]
    assert src.attitude(119.0) is not None and src.trusted
    return src


def test_an_estimate_without_samples_for_longer_than_the_bank_bridges_is_not_carried_across_the_gap():
    """No sample taken in for longer than the bank's `max_gap_s` (a TLE gone stale, a dead sensor): the
    decision gets no attitude, at once (it was propagated across the whole gap at every decision, a step every
    2 s: a day of it took ~0.8 s), and the bank is left as it was, to start again with the next sample."""
    src = _trusted_estimate()
    gap = src.bank.tuning.max_gap_s
    assert src.attitude(119.0 + 0.9 * gap) is not None                    # within the gap: carried
    t_s, q = src.bank.t_s, src.bank.best.q.copy()
    assert src.attitude(119.0 + 86400.0) is None and not src.trusted
    assert src.reason == "no sample for 86400 s"
    assert src.bank.t_s == t_s and np.all(src.bank.best.q == q)


def test_an_orbit_that_cannot_be_evaluated_at_a_decision_gives_no_attitude_and_never_raises():
    """SGP4 failing at the decision's time (a decayed element set): the decision gets no attitude, with the
    reason, and the flight loop goes on."""
    src = _trusted_estimate()

    def sgp4_error(t_s):
        raise ValueError("SGP4 error codes [6]")
    src._inputs = sgp4_error
    src.bank.inputs_at = sgp4_error
    assert src.attitude(120.0) is None and not src.trusted and src.reason == "SGP4 error codes [6]"


def test_without_a_field_along_the_orbit_there_is_no_estimate():
    src = EstimatedAttitude(1.5e-6)
    src.observe(0.0, np.array([20e-6, 0.0, 0.0]), np.zeros(3))
    assert src.bank is None and src.attitude(0.0) is None and "no orbit" in src.reason
    assert src.report().source == mavlink.DEBRIS_CONTROLLER_ATTITUDE_NONE


def test_the_truth_beside_the_inputs_is_sent_and_its_failure_never_stops_the_loop():
    """SITL's `truth_ypr` rides in DEBRIS_DEORBIT_ATTITUDE; one that raises (a time outside the simulator's
    history) is counted and sent as NaN, the loop runs on."""
    emu = DeorbitKitEmulator()
    kit = DeorbitKit(emu)
    cap = Capture()
    tlm = Telemetry(cap)
    kit.truth_ypr = lambda t: (0.1, -0.2, 0.3)
    kit.telemetry(0.0, tlm)

    def broken(t):
        raise ValueError("no truth at that time")

    kit.truth_ypr = broken
    kit.tick(1.0)
    kit.telemetry(1.0, tlm)
    att = [m for m in cap.messages() if m.get_type() == "DEBRIS_DEORBIT_ATTITUDE"]
    assert len(att) == 2 and kit.truth_errors == 1
    assert list(att[0].truth_ypr) == pytest.approx([0.1, -0.2, 0.3], rel=1e-6)
    assert all(math.isnan(x) for x in att[1].truth_ypr)


class SteppedField(FixedField):
    """A field along the orbit, and the host calibration's changes summed as `HostCalibration.steps_T` does."""

    def __init__(self, fld, report=True):
        super().__init__(fld)
        self.steps = np.zeros(3)
        self.report = report

    @property
    def calibration_steps_T(self):
        return self.steps if self.report else None


@pytest.mark.parametrize("seed", [0, 1])
def test_a_step_the_host_calibration_makes_moves_the_estimates_bias_not_its_attitude(seed):
    """A body at rest in the orbital frame (the truth: yaw = pitch = roll = 0), its samples with 1.5 µT of
    noise; at 600 s the host calibration changes and every later sample carries 3 µT more along body y and z
    (a 4 µT change of the hard iron, as a first calibration's refinement makes; about 0.1 rad of turn at
    this field). Told the step, the estimate moves its bias and its pointing error stays the noise's (RMS
    2–3.5 mrad over the 600 s after it); not told, it takes part of the step as a turn of the body (the bias
    is a slow random walk): 11–14 mrad."""
    orbit = CircularOrbitModel(600e3, 97.8)
    fld = OrbitField(orbit, DipoleModel(2025.0), era0_rad=0.0)
    inputs = OrbitInputs(fld)
    step_T = np.array([0.0, 3e-6, 3e-6])
    errors = {}
    for told in (True, False):
        prov = SteppedField(fld, report=told)
        src = EstimatedAttitude(1.5e-6, gate=TrustGate(), provider=prov)
        rng = np.random.default_rng(seed)
        err = []
        for t in np.arange(0.0, 1200.0):
            r, v, b_eci = inputs(float(t))
            R_oi, w_oi = orbital_frame(r, v)
            z = R_oi.T @ b_eci + rng.normal(0.0, 1.5e-6, 3)
            if t == 1.0:  # one hypothesis, on the truth and settled: what 1,200 s of deciding leave
                best = src.bank.best
                best.q, best.w = quat_from_dcm(R_oi), R_oi.T @ w_oi
                best.P = np.diag([1e-6] * 3 + [1e-12] * 3 + [0.25] * 3)
                src.bank.members = [best]
            if t >= 600.0:
                z = z + step_T
                prov.steps = step_T
            src.observe(float(t), z, np.zeros(3))
            if t >= 600.0:
                R_bo = src.bank.orbital(float(t))[0]
                err.append(max(abs(R_bo[0, 2]), abs(R_bo[0, 1])))  # the sail normal's pointing error
        errors[told] = float(np.sqrt(np.mean(np.square(err))))
    assert errors[True] <= 0.005  # rad RMS: the noise's share
    assert errors[False] >= 2.5 * errors[True] and errors[False] >= 0.008
