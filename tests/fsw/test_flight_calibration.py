"""The flight loop's host-magnetics calibration step (fsw.host_calibration in fsw.flight): with the field
along the orbit on board, the estimators get the corrected field and the link the sensor's own; without
one the step is inactive and says so."""
import numpy as np

from fsw.estimation import field_motion as fm
from fsw.estimation import magcal as mc
from fsw.flight import FlightSoftware
from fsw.estimation.onboard_field import flight_field
from fsw.host_calibration import FixedField, HostCalibration
from fsw.telemetry.dialect import mavlink
from fsw.telemetry.telemetry import Telemetry
from support import MAGCAL_EPOCH, MAGCAL_ORBIT, Capture, magcal_host, magcal_orbit, magcal_tumble

SIGMA_T = 1.5e-6


class HostSource:
    """The magnetometer on a host with hard and soft iron: one sample a second of a tumble (the truth)."""

    def __init__(self, b_body_T, S, h, seed=0):
        self.truth = b_body_T
        self.noise = np.random.default_rng(seed).normal(0.0, SIGMA_T, b_body_T.shape)
        self.meas = b_body_T @ S.T + h + self.noise
        self.k = -1
        self.b_body_T = np.zeros(3)
        self.sample_time_s = float("nan")

    def update(self, now_s):
        k = int(np.floor(now_s + 1e-9))
        if k == self.k or k >= len(self.meas):
            return False
        self.k = k
        self.sample_time_s = float(k)
        self.b_body_T[:] = self.meas[k]
        return True


class SeenByEstimator:
    """A rate estimator that records what it is given."""

    omega_radps = np.zeros(3)
    sigma_radps = np.ones(3)
    flags = 0
    gap_history = 0

    def __init__(self):
        self.seen = []

    def update(self, t_s, b_T):
        self.seen.append((t_s, np.array(b_T)))
        return False

    def reset(self):
        pass


def onboard_field():
    return flight_field(fm.CircularOrbitModel(*MAGCAL_ORBIT), MAGCAL_EPOCH)


def fly(field, n_s):
    S, h = magcal_host(21)
    src = HostSource(magcal_tumble(3), S, h)
    link = Capture()
    spy = SeenByEstimator()
    fsw = FlightSoftware(src, Telemetry(link), rate_hz=1.0, sigma_b_T=SIGMA_T, sample_rate_hz=1.0,
                         rate_filter=spy, field=field)
    for k in range(n_s):
        fsw.tick(float(k))
    return fsw, src, spy, link.messages(), (S, h)


def test_estimators_get_the_calibrated_field_within_an_orbit():
    t, _, _ = magcal_orbit()
    fsw, src, spy, msgs, (S, h) = fly(onboard_field(), len(t))
    cal = fsw.calibration
    assert cal.state == mc.CONVERGED and cal.cal.converged_at_s < t[-1]
    # what the estimator was given after convergence: the true field to within the target (0.3 µT RMS
    # per axis, the sensor noise as calibrated taken out), though the sensor's samples are tens of µT off
    t_conv = cal.cal.converged_at_s
    k = np.array([int(ts) for ts, _ in spy.seen if ts > t_conv])
    seen = np.array([b for ts, b in spy.seen if ts > t_conv])
    scaled_noise = src.noise[k] @ (np.eye(3) + cal.cal.calibration.D).T
    assert np.all(np.sqrt(np.mean((seen - src.truth[k] - scaled_noise) ** 2, axis=0)) <= 0.3e-6)
    assert np.sqrt(np.mean((src.meas[k] - src.truth[k]) ** 2)) > 10e-6
    # the samples on the link are the sensor's own
    sent = [m for m in msgs if m.get_type() == "DEBRIS_MAG_SAMPLE"]
    np.testing.assert_allclose(np.array(sent[-1].mag) * 1e-4, src.meas[int(sent[-1].time_usec // 1_000_000)],
                               rtol=1e-6, atol=1e-12)
    # DEBRIS_MAGCAL every 10 s, the last one converged with the host's hard iron within its σ·4
    mcal = [m for m in msgs if m.get_type() == "DEBRIS_MAGCAL"]
    assert abs(len(mcal) - len(t) / 10) <= 2
    last = mcal[-1]
    assert last.state == mavlink.DEBRIS_MAGCAL_STATE_CONVERGED and last.samples > len(t) - 11
    assert np.all(np.abs(np.array(last.hard_iron) - h * 1e6) <= 4 * np.array(last.hard_iron_sigma))
    D_true = np.linalg.inv(S) - np.eye(3)
    assert np.all(np.abs(np.array(last.soft_iron) - [D_true[i, j] for i, j in mc.D_TERMS])
                  <= 4 * np.array(last.soft_iron_sigma))


def test_without_a_field_on_board_the_calibration_is_inactive_and_says_so():
    fsw, src, spy, msgs, _ = fly(None, 30)
    assert fsw.calibration.state == mc.NO_FIELD and "no orbit/field" in fsw.calibration.reason
    for ts, b in spy.seen:
        np.testing.assert_array_equal(b, src.meas[int(ts)])
    mcal = [m for m in msgs if m.get_type() == "DEBRIS_MAGCAL"]
    assert mcal and all(m.state == mavlink.DEBRIS_MAGCAL_STATE_NO_FIELD for m in mcal)
    assert all(np.isnan(m.hard_iron_sigma).all() for m in mcal)


def test_a_field_that_cannot_be_evaluated_is_counted_not_raised():
    class Broken:
        def b_eci_T(self, t_s):
            raise ValueError("SGP4 error codes [1]")

    step = HostCalibration(SIGMA_T, FixedField(Broken()))
    b = np.array([20e-6, 0.0, 30e-6])
    for k in range(5):
        np.testing.assert_array_equal(step.process(float(k), b), b)
    assert step.field_errors == 5 and step.cal.samples == 0


def test_the_calibration_takes_five_samples_a_second_of_a_faster_magnetometer():
    """A 20 Hz stream: one sample in four goes into the calibration's sums (the σ goals come with their number:
    docs/calibration.md), and every sample is handed on."""
    step = HostCalibration(SIGMA_T, FixedField(onboard_field()))
    b = np.array([20e-6, -5e-6, 30e-6])
    out = [step.process(k / 20.0, b) for k in range(200)]
    assert step.cal.samples == 50 and len(out) == 200


def test_a_change_of_the_calibration_is_summed_as_the_step_it_makes_in_the_corrected_samples():
    """`steps_T` moves, at the first sample corrected after a change of the calibration, by what that change
    did to the correction (the same raw sample corrected by the new calibration and by the old; none applied
    before the first: the raw sample): an estimate of what the calibration leaves in the samples moves by it
    instead of meeting it as an error."""
    from fsw.estimation.magcal import apply

    S, h = magcal_host(21)
    t, _, _ = magcal_orbit()
    meas = HostSource(magcal_tumble(3), S, h).meas
    step = HostCalibration(SIGMA_T, FixedField(onboard_field()))
    changes, before = 0, None
    for k in range(len(t)):
        sum_before, published = step.steps_T.copy(), step.cal.published
        # the calibration applied now, as it would correct the next sample (None: none applied)
        old = step.cal.calibration_at(float(t[min(k + 1, len(t) - 1)])) if step.cal.good else None
        out = step.process(float(t[k]), meas[k])
        moved = step.steps_T - sum_before
        if before is not None:  # the sample after a change: corrected by the new calibration, the step counted
            was = apply(before[0], meas[k]) if before[0] is not None else meas[k]
            # what the change did to this sample's correction: the same but for the change of D times how far
            # the sample moved since the one that made the change (~0.3 µT at the first, where D is ~10 %)
            dD = step.cal.calibration.D - (before[0].D if before[0] is not None else 0.0)
            bound = np.linalg.norm(dD, 2) * np.linalg.norm(meas[k] - meas[k - 1]) + 0.01e-6
            assert np.linalg.norm(moved - (out - was)) <= bound
            assert np.linalg.norm(moved) > 0.0
            changes += 1
            before = None
        else:
            np.testing.assert_array_equal(moved, 0.0)  # no change: nothing moves
        if step.cal.published != published:
            before = (old,)  # changed by this sample: counted from the next one on
    assert changes >= 10  # a calibration converging over an orbit changes every solution or so
