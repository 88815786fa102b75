"""The onboard results kept across a restart (fsw.persist.BoxState.restore_apps): the host calibration
(its drift phased by the UTC, or dropped without it; applied from the first sample, flagged, dropped when
the new samples refuse it), the kit's field calibration and the inertia estimate; a torn file or one of
another box never loaded. The truth: the drift test's tumble and isoi host (test_magcal_drift)."""
import dataclasses
from types import SimpleNamespace

import numpy as np
import pytest

from fsw.deorbit.kit import DeorbitKit
from fsw.deorbit.kit_field import DESIGN
from fsw.estimation import field_motion as fm
from fsw.estimation import magcal as mc
from fsw.estimation.inertia import InertiaEstimate
from fsw.estimation.onboard_field import InterpolatedOrbitField, flight_field
from fsw.host_calibration import FixedField, HostCalibration
from fsw.ident import ABORTED, DONE, TORQUE, IdentExperiment, IdentResult
from fsw.persist import BoxState
from fsw.telemetry.telemetry import Telemetry
from hil.deorbit_kit import DeorbitKitEmulator
from support import MAGCAL_EPOCH, MAGCAL_ORBIT, Capture
from test_magcal_drift import CHIP_SIGMA_T, TARGET_T, isoi_host, tumble

SYSID = 7
RESTART_S = 1500.0   # the box is killed after 1,500 s of tumble (a calibration published)
DOWN_S = 1400.0      # and starts again 1,400 s later (a quarter orbit: the drift's phase matters)
AFTER_S = 400.0      # then runs 400 s
U0 = 1.79e9          # the UTC at the first run's loop time 0


class Mono:
    def __init__(self, t):
        self.t = t

    def __call__(self):
        return self.t


class Clock:
    """What BoxState reads of `fsw.timeorbit.TimeOrbit`: the UTC, once set."""

    def __init__(self, utc0_s=None):
        self.utc0_s = utc0_s
        self.clock = SimpleNamespace(known=utc0_s is not None, sets=0)

    def utc_s(self, now_s):
        return self.utc0_s + now_s

    def set_time(self, now_s, utc_s):
        self.utc0_s, self.clock.known = utc_s - now_s, True


@pytest.fixture(scope="module")
def record():
    """(t, the sensor's samples, the true hard iron, the onboard field) over both runs."""
    t, b_body = tumble(RESTART_S + DOWN_S + AFTER_S)
    host = isoi_host()
    h = host.hard_iron_at_T(t)
    meas = b_body @ host.soft_iron.T + h + np.random.default_rng(4).normal(0.0, CHIP_SIGMA_T, b_body.shape)
    field = InterpolatedOrbitField(flight_field(fm.CircularOrbitModel(*MAGCAL_ORBIT), MAGCAL_EPOCH))
    return t, meas, h, field


def first_run(record, state_dir, utc=True):
    """The box until it is killed: its calibration saved in `state_dir` (and the time, when it has it)."""
    t, meas, h, field = record
    step = HostCalibration(CHIP_SIGMA_T, FixedField(field))
    clock = Clock()
    state = BoxState(state_dir, monotonic=Mono(1000.0), boot_id="boot-a")
    state.restore(None, clock)
    state.restore_apps(SYSID, calibration=step)
    for k in np.flatnonzero(t < RESTART_S):
        step.process(float(t[k]), meas[k])
    assert step.cal.good and step.cal.restored == mc.NOT_RESTORED
    if utc:
        clock.set_time(0.0, U0)
        clock.clock.sets = 1
    state.tick(RESTART_S)
    state.close()  # a SIGKILL right after the write (the writer's thread wrote it within the tick)
    return step


class Later:
    """The field along the orbit on the new run's clock: its time 0 is the first run's `t0_s` (on target
    the field comes from the TLE at the UTC, which runs on across the restart)."""

    def __init__(self, field, t0_s):
        self.orbit_field, self.t0_s = field, t0_s

    def b_eci_T(self, t_s):
        return self.orbit_field.b_eci_T(np.asarray(t_s) + self.t0_s)


def second_run(record, state_dir, *, system_id=SYSID, boot="boot-a", field=True):
    """The box started again DOWN_S later: (its calibration step, BoxState's notes, per sample of the new
    run: the old time, the hard iron applied, the state, the `restored` flag, σ of b; DEBRIS_MAGCAL's `restored`
    as sent)."""
    t, meas, h, orbit_field = record
    t0 = RESTART_S + DOWN_S  # the new loop's time 0, in the first run's
    step = HostCalibration(CHIP_SIGMA_T, FixedField(Later(orbit_field, t0)) if field else None)
    clock = Clock()
    state = BoxState(state_dir, monotonic=Mono(1000.0 + DOWN_S), boot_id=boot)
    state.restore(None, clock)
    state.restore_apps(system_id, calibration=step)
    rows = []
    cap = Capture()
    tlm = Telemetry(cap)
    for k in np.flatnonzero(t >= t0):
        t_new = float(t[k] - t0)
        step.process(t_new, meas[k])
        step.telemetry(t_new, tlm)
        state.tick(t_new)
        rows.append((t[k], step.cal.calibration_at(t_new).b_T if step.cal.good else np.full(3, np.nan),
                     step.state, step.cal.restored, step.cal.calibration.sigma[:3]))
    state.close()
    return step, state.notes, rows, [m.restored for m in cap.messages() if m.get_type() == "DEBRIS_MAGCAL"]


def test_the_calibration_is_applied_from_the_first_sample_with_its_drift_phased_by_the_utc(record, tmp_path):
    t, meas, h, _ = record
    before = first_run(record, tmp_path)
    step, notes, rows, sent = second_run(record, tmp_path)
    assert "calibration: restored from before the restart (its drift phased by the UTC)" in notes
    k0 = np.searchsorted(t, rows[0][0])
    err = np.array([r[1] - h[np.searchsorted(t, r[0])] for r in rows])
    # the truth's hard iron moved by up to ~0.8 µT while the box was down; the phased drift follows it
    moved = np.max(np.abs(h[k0] - before.cal.hard_iron_T(RESTART_S)))
    assert moved > 0.3e-6
    # the first sample after the restart: the first run's model of b(t) carried on across the restart
    # (exactly: the UTC's shift), within 3 σ of b of the truth (its drift's terms extrapolated 1,400 s)
    np.testing.assert_allclose(rows[0][1], before.cal.hard_iron_T(rows[0][0]), atol=1e-12)
    sigma_T = before.cal.calibration.sigma[:3]
    assert np.all(np.abs(err[0]) < 3 * sigma_T)
    # every sample after it within the target (the drift's terms extrapolated until the first
    # solution from new samples), then as close as before the restart
    assert np.max(np.abs(err)) < TARGET_T
    confirmed = next(i for i, r in enumerate(rows) if r[3] == mc.NOT_RESTORED)
    assert rows[confirmed][0] - rows[0][0] < step.cal.min_samples + 2 * step.cal.solve_every_s
    assert np.max(np.abs(err[confirmed:])) < 3 * np.max(sigma_T)
    assert rows[0][3] == mc.RESTORED and step.cal.restored_dropped == 0
    assert sent[0] == mc.RESTORED and sent[-1] == mc.NOT_RESTORED  # telemetry says so


def test_without_the_utc_the_drift_terms_are_dropped_and_the_error_is_the_drifts(record, tmp_path):
    t, meas, h, _ = record
    before = first_run(record, tmp_path, utc=False)
    step, notes, rows, sent = second_run(record, tmp_path)
    assert any("drift's terms dropped" in n for n in notes), notes
    k0 = np.searchsorted(t, rows[0][0])
    # the constant hard iron published before the restart: off by what the drift did since, no more
    b_pub = before.cal.calibration.b_T
    np.testing.assert_allclose(rows[0][1], b_pub, atol=1e-12)
    err0 = np.abs(rows[0][1] - h[k0])
    assert np.all(err0 <= np.abs(h[k0] - before.cal.hard_iron_T(RESTART_S)) + 3 * before.cal.calibration.sigma[:3])
    assert TARGET_T < np.max(err0) < 1.5e-6  # off by what the drift did (its amplitude 0.6 µT twice, at most)
    # and its σ says so: the drift's amplitude added
    sigma_T = rows[0][4]
    assert np.all(err0 < 3 * sigma_T) and np.all(sigma_T > 2 * before.cal.calibration.sigma[:3])
    assert sent[0] == mc.RESTORED


def test_a_restored_calibration_the_new_samples_refuse_is_dropped_and_counted(record, tmp_path):
    t, meas, h, _ = record
    first_run(record, tmp_path)
    cal_file = tmp_path / "calibration.json"
    from fsw.state_files import load_state, save_state
    payload, _ = load_state(cal_file, "calibration")
    payload["snapshot"]["theta_uT"][0] += 20.0       # another host's hard iron: 20 µT off in x
    payload["snapshot"]["b_T"][0] += 20e-6
    save_state(cal_file, "calibration", payload)
    step, notes, rows, sent = second_run(record, tmp_path)
    assert rows[0][3] == mc.RESTORED and np.isfinite(rows[0][1]).all()   # applied at first
    dropped_at = next(r[0] for r in rows if r[3] == mc.RESTORED_DROPPED) - (RESTART_S + DOWN_S)
    assert dropped_at <= 2 * step.cal.solve_every_s + step.cal.min_samples
    assert step.cal.restored_dropped == 1 and mc.RESTORED_DROPPED in sent
    k = next(i for i, r in enumerate(rows) if r[3] == mc.RESTORED_DROPPED)
    assert not np.isfinite(rows[k][1]).any()  # dropped: nothing applied until a calibration of the new samples
    # which comes (the samples were good) and replaces it, in the file too
    t_end, b_end = rows[-1][0], rows[-1][1]
    assert rows[-1][3] == mc.NOT_RESTORED and np.max(np.abs(b_end - h[np.searchsorted(t, t_end)])) < TARGET_T
    saved = load_state(cal_file, "calibration")[0]["snapshot"]
    assert np.max(np.abs(np.array(saved["b_T"]) - h[np.searchsorted(t, t_end)])) < TARGET_T


def test_a_restored_calibration_is_applied_before_the_box_has_a_field(record, tmp_path):
    t, meas, h, _ = record
    first_run(record, tmp_path, utc=False)
    step, notes, rows, sent = second_run(record, tmp_path, boot="boot-b", field=False)  # a reboot: no UTC, no TLE
    err = np.array([r[1] - h[np.searchsorted(t, r[0])] for r in rows])
    assert np.max(np.abs(err)) < 1.5e-6 and rows[-1][3] == mc.RESTORED


def test_a_torn_calibration_file_is_not_loaded(record, tmp_path):
    first_run(record, tmp_path)
    path = tmp_path / "calibration.json"
    path.write_bytes(path.read_bytes()[:-40])
    step, notes, rows, sent = second_run(record, tmp_path)
    assert any(n.startswith("calibration: not a whole state file (torn") for n in notes), notes
    assert rows[0][3] == mc.NOT_RESTORED and not np.isfinite(rows[0][1]).any()


def test_a_calibration_of_another_box_is_ignored(record, tmp_path):
    first_run(record, tmp_path)
    step, notes, rows, sent = second_run(record, tmp_path, system_id=SYSID + 1)
    assert f"calibration: saved by system id {SYSID}, not this box's {SYSID + 1}: ignored" in notes
    assert rows[0][3] == mc.NOT_RESTORED and not np.isfinite(rows[0][1]).any()


def test_a_state_file_of_another_kind_is_not_loaded(tmp_path):
    from fsw.state_files import save_state
    save_state(tmp_path / "ident.json", "calibration", {"system_id": SYSID, "snapshot": {}})
    ident = IdentExperiment(sigma_b_T=1e-7, b_inertial=None)
    state = BoxState(tmp_path, monotonic=Mono(0.0), boot_id="a")
    state.restore_apps(SYSID, ident=ident)
    state.close()
    assert state.notes == ["ident: not a ident state file: ignored"] and ident.restored is None


# --- the inertia estimate --------------------------------------------------------------------------

def estimate():
    p = np.array([180.0, 220.0, 260.0, 1.5, -2.0, 0.7])
    cov = np.diag([4.0, 5.0, 6.0, 0.3, 0.3, 0.3])
    cov[0, 1] = cov[1, 0] = 1.2
    return InertiaEstimate(p, cov, "test", 4321)


def ident_after_restart(state_dir, system_id=SYSID):
    """A new experiment given what `state_dir` kept (boot "b"); (it, the state with its notes)."""
    ident = IdentExperiment(sigma_b_T=1e-7, b_inertial=None)
    state = BoxState(state_dir, monotonic=Mono(0.0), boot_id="b")
    state.restore_apps(system_id, ident=ident)
    state.close()
    return ident, state


@pytest.mark.parametrize("state_before, state_after", [(DONE, DONE), (TORQUE, ABORTED)])  # cut short: aborted
def test_the_inertia_estimate_is_restored_and_sent_again(tmp_path, state_before, state_after):
    before = IdentExperiment(sigma_b_T=1e-7, b_inertial=None)
    state = BoxState(tmp_path, monotonic=Mono(0.0), boot_id="a")
    state.restore_apps(SYSID, ident=before)
    est = estimate()
    before.result = IdentResult(est, None, 900.0, 899.0, state_before == DONE)
    before._set_state(state_before)
    state.tick(900.0)
    state.close()
    after, state = ident_after_restart(tmp_path)
    assert state.notes == ["ident: restored from before the restart (applied)"]
    cap = Capture()
    tlm = Telemetry(cap)
    for now in (0.0, 1.0, 2.0, 6.0):  # at once, then every period
        after.telemetry(now, tlm)
    sent = [m for m in cap.messages() if m.get_type() == "DEBRIS_INERTIA_ESTIMATE"]
    assert len(sent) == 2
    m = sent[0]
    np.testing.assert_allclose(m.inertia, est.p, rtol=1e-6)
    np.testing.assert_allclose(m.ci95, est.ci95, rtol=1e-6)
    assert m.samples == 4321 and m.state == state_after and m.flags == est.flags
    np.testing.assert_allclose(after.restored["cov"], est.cov)
    # another box's file: not taken
    other, state = ident_after_restart(tmp_path, SYSID + 1)
    assert other.restored is None and "ignored" in state.notes[0]


# --- the kit's field --------------------------------------------------------------------------------

def test_the_kit_field_calibration_is_restored_for_the_same_kit_only(tmp_path):
    model = DeorbitKit(DeorbitKitEmulator()).sensor_field
    state = BoxState(tmp_path, monotonic=Mono(0.0), boot_id="a")
    state.restore_apps(SYSID, kit_field=model)
    # a calibration taken in (as `_update` leaves it): pitch 10 % strong, yaw 7 % weak, their σ 0.5 %
    x = np.concatenate([m.fa_design_T * s for m, s in zip(model.models, (1.10, 0.93))])
    P = np.diag(np.concatenate([(0.005 * m.fa_design_T) ** 2 + 1e-18 for m in model.models]))
    model.restore({"fa_T": x.tolist(), "P": P.tolist(),
                   "fa_design_T": np.concatenate([m.fa_design_T for m in model.models]).tolist(),
                   "steps": [6, 7]})
    state.tick(100.0)
    state.close()
    after = DeorbitKit(DeorbitKitEmulator()).sensor_field
    state = BoxState(tmp_path, monotonic=Mono(0.0), boot_id="a")
    state.restore_apps(SYSID, kit_field=after)
    state.close()
    assert state.notes == ["kit field: restored from before the restart (applied)"]
    for m, m0 in zip(after.models, model.models):
        assert m.scale == pytest.approx(m0.scale, rel=1e-12) and m.scale_sigma == pytest.approx(m0.scale_sigma)
        assert m.steps == m0.steps
    assert [round(m.scale, 6) for m in after.models] == [1.1, 0.93]
    # a kit of another design (a stronger pitch magnet) refuses it
    other_design = (dataclasses.replace(DESIGN[0], moment_Am2=20.0), DESIGN[1])
    other = DeorbitKit(DeorbitKitEmulator(), magnets=other_design).sensor_field
    state = BoxState(tmp_path, monotonic=Mono(0.0), boot_id="a")
    state.restore_apps(SYSID, kit_field=other)
    state.close()
    assert "another kit's design" in state.notes[0] and other.version == 0


@pytest.mark.parametrize("snapshot", [[1, 2], "x", 3.0, {}, {"theta_uT": "abc"}, {"fa_T": [1.0] * 6, "P": 1},
                                      {"theta_uT": [float("nan")] * 15, "b_T": [0, 0, 0], "D": [[0] * 3] * 3},
                                      {"inertia": [1.0] * 5, "ci95": [], "ci99": [], "cov": [], "state": 4}])
def test_a_file_of_this_box_with_fields_not_understood_is_ignored(tmp_path, snapshot):
    from fsw.state_files import save_state
    for kind in ("calibration", "kit_field", "ident"):
        save_state(tmp_path / f"{kind}.json", kind, {"system_id": SYSID, "snapshot": snapshot})
    cal = HostCalibration(CHIP_SIGMA_T)
    kit = DeorbitKit(DeorbitKitEmulator()).sensor_field
    ident = IdentExperiment(sigma_b_T=1e-7, b_inertial=None)
    state = BoxState(tmp_path, monotonic=Mono(0.0), boot_id="a")
    state.restore_apps(SYSID, calibration=cal, kit_field=kit, ident=ident)
    state.close()
    assert all("not understood" in n for n in state.notes), state.notes
    assert not cal.cal.good and kit.version == 0 and ident.restored is None


def test_an_adopted_combined_estimate_is_sent_and_kept(tmp_path):
    """The mission's attempts combined (`IdentExperiment.adopt`): the experiment's result becomes the
    combined estimate, sent at once and saved for a restart; refused before a final result."""
    ident = IdentExperiment(sigma_b_T=1e-7, b_inertial=None)
    with pytest.raises(ValueError, match="finished"):
        ident.adopt(estimate())
    state = BoxState(tmp_path, monotonic=Mono(0.0), boot_id="a")
    state.restore_apps(SYSID, ident=ident)
    ident.result = IdentResult(estimate(), None, 900.0, 899.0, True)
    ident._set_state(DONE)
    ident.telemetry(900.0, Telemetry(Capture()))
    combined = InertiaEstimate(estimate().p + 1.0, 0.5 * estimate().cov, "test, 2 attempts combined", 4321)
    ident.adopt(combined)
    cap = Capture()
    ident.telemetry(901.0, Telemetry(cap))        # at once, not at the next period
    sent = [m for m in cap.messages() if m.get_type() == "DEBRIS_INERTIA_ESTIMATE"]
    assert len(sent) == 1
    np.testing.assert_allclose(sent[0].inertia, combined.p, rtol=1e-6)
    np.testing.assert_allclose(sent[0].ci95, combined.ci95, rtol=1e-6)
    state.tick(901.0)
    state.close()
    after, _ = ident_after_restart(tmp_path)
    np.testing.assert_allclose(after.restored["inertia"], combined.p)
    np.testing.assert_allclose(after.restored["cov"], combined.cov)
