"""The de-orbit kit's magnets at the sensor in SITL (scenario amds_deorbit, the controller moving capsules
and magnets): the flight software takes their field out of every sample (against the simulator's own kit
field), skips the samples taken while a shutter moves, and its flown rate filter runs through the
capsule events without a restart or a jump; the same run without the compensation jumps."""

import numpy as np
import pytest

from fsw.telemetry.dialect import mavlink
from hil import sitl
from support import deorbit_loop, start_controller

pytestmark = [pytest.mark.sitl, pytest.mark.slow]

DURATION_S = 320.0
WINDOW_S = 30.0


def closed_loop(compensate: bool):
    box = deorbit_loop()
    sim, flight = box.sim, box.fsw
    kit = flight.apps["deorbit"]
    if not compensate:
        flight.kit_field = None
    kf = flight.estimators["kalman"]
    resets = []
    reset = kf.reset
    kf.reset = lambda: (resets.append(sim.t_s), reset())
    err, resid = [], []
    # per sample at rest: (the host calibration kept it out, a capsule open in the simulator)
    kept_out = []
    for k in range(int(DURATION_S * 10) + 1):
        t = k * 0.1
        sim.advance_to(t)
        b_kit_true = sim.kit_field.b_body_T()
        if k == 0:
            assert start_controller(kit, t) == mavlink.MAV_RESULT_ACCEPTED
        skipped = flight.calibration.skipped
        flight.tick(t)
        if flight.new_sample and not flight.kit_skip:
            resid.append(b_kit_true - flight.kit_T)
            kept_out.append((flight.calibration.skipped > skipped, any(ch.shutter > 0 for ch in sim.kit.channels)))
        if flight.new_estimate["kalman"] and not kf.flags & kf.NO_ESTIMATE:
            tr = sim.truth(t)
            err.append((t, np.degrees(np.linalg.norm(sitl.perpendicular(kf.omega_radps - tr.omega_radps,
                                                                         tr.b_body_T)))))
    events = [e.t_s for e in kit.sequencer.events if e.what == "capsule" and e.new == "OPENING"]
    return flight, np.array(err), np.array(resid), events, resets, np.array(kept_out)


def jumps_dps(err: np.ndarray, events: list[float]) -> list[float]:
    """Per capsule opening after the first minute: the worst ⊥B error in the window after it less the
    worst in the window before it."""
    out = []
    for te in events:
        if te < 60.0:
            continue
        before = err[(err[:, 0] >= te - WINDOW_S) & (err[:, 0] < te), 1]
        after = err[(err[:, 0] > te) & (err[:, 0] <= te + WINDOW_S), 1]
        if len(before) and len(after):
            out.append(float(after.max() - before.max()))
    return out


def test_the_kit_field_is_taken_out_and_the_flown_filter_runs_through_capsule_events():
    flight, err, resid, events, resets, kept_out = closed_loop(compensate=True)
    assert len(events) >= 3  # the controller opened capsules
    assert resets == [] and flight.estimator_resets == 0
    assert flight.kit_skipped >= 2 * len(events)  # the samples while the shutters moved
    # the host's calibration learns from no sample taken while a shutter moved, nor while a capsule was open
    # in the simulator (the kit's model is a few µT off there, which it would take for hard iron), and from
    # every other sample
    assert flight.gate.rejected == 0 and np.any(kept_out[:, 1]) and not np.all(kept_out[:, 1])
    assert np.array_equal(kept_out[:, 0], kept_out[:, 1])
    assert flight.calibration.skipped == flight.kit_skipped + int(np.sum(kept_out[:, 0]))
    # the field the flight software took out against the simulator's (with a kit field of ~55 µT)
    assert np.max(np.sqrt(np.mean(resid ** 2, axis=0))) < 1.5e-6
    jumps = jumps_dps(err, events)
    assert jumps and max(jumps) < 0.5, jumps
    # without the compensation the same filter jumps at the events
    _, err0, resid0, events0, _, _ = closed_loop(compensate=False)
    assert np.max(np.abs(resid0)) > 50e-6
    assert max(jumps_dps(err0, events0)) > 3.0


@pytest.mark.filterwarnings("ignore")
def test_samples_taken_while_a_shutter_opens_are_sent_flagged_and_not_used():
    from support import Capture

    link = Capture()
    box = deorbit_loop(link)
    sim, flight = box.sim, box.fsw
    kit = flight.apps["deorbit"]
    used, skipped = [], []
    for k in range(111):
        t = k * 0.1
        sim.advance_to(t)
        if k == 30:  # the pitch magnet is homed, then its capsule opens
            assert start_controller(kit, t) == mavlink.MAV_RESULT_ACCEPTED
        flight.tick(t)
        if flight.new_sample:
            (skipped if flight.kit_skip else used).append(
                (flight.sample_t_s, any(flight.new_estimate.values()), sim.kit.channels[0].shutter))
    assert skipped and all(not est for _, est, _ in skipped)  # no estimator took them
    # the magnet is homed first (the capsule closed), then the shutter opens over 2 s: every sample taken
    # while it moved skipped, every sample used at a shutter at rest, both before and after
    assert all(s in (0.0, 1.0) for _, _, s in used)
    assert any(s == 0.0 for _, _, s in used) and any(s == 1.0 for _, _, s in used)
    assert sum(1 for _, _, s in skipped if 0.0 < s < 1.0) >= 1
    open_used = sum(1 for _, _, s in used if s == 1.0)  # used by the estimators, not by the host calibration
    assert flight.calibration.skipped == len(skipped) + open_used and flight.estimator_resets == 0
    samples = [m for m in link.messages() if m.get_type() == "DEBRIS_MAG_SAMPLE"]
    flagged = [m for m in samples if m.flags & mavlink.DEBRIS_SAMPLE_FLAGS_KIT_MOVING]
    assert len(flagged) == len(skipped) and len(samples) == len(used) + len(skipped)
    assert kit.sensor_field.models[0].flagged == len(skipped)
