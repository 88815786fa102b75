"""The de-orbit kit's field on the ground, end to end: a SITL run of amds_deorbit with the controller moving
capsules and magnets, its telemetry decoded by ground.decode's Decoder into a recording, then
ground.estimate on that recording. Checked against the simulator: the recording has the kit columns and
the flags; the flagged samples are the box's skipped ones; the field less the recorded kit field is within
1.5 µT RMS per axis of the measured field without the simulator's kit field; the estimate does not jump at
the capsule events (the same recording with --kit-raw does); a sample lost live and sent again from the
store keeps its flag and its kit field."""
from types import SimpleNamespace

import numpy as np
import pytest

from fsw.telemetry.dialect import mavlink
from ground import estimate
from ground.decode import Decoder
from ground.recorder import Recorder
from ground.recording import read_recording, read_rate_estimates
from support import Capture, deorbit_loop, start_controller

pytestmark = [pytest.mark.sitl]  # about 8 s

DURATION_S = 240.0
WINDOW_S = 3.0  # around a capsule event, for the estimate's excursions


def sitl_run():
    """The closed loop at 10 Hz; per sample sent: (time, box's skip flag, simulator's kit field); the link's
    bytes; the capsule events; the flight software."""
    link = Capture()
    box = deorbit_loop(link)
    sim, flight = box.sim, box.fsw
    kit = flight.apps["deorbit"]
    samples = {}
    for k in range(int(DURATION_S * 10) + 1):
        t = k * 0.1
        sim.advance_to(t)
        if k == 0:
            assert start_controller(kit, t) == mavlink.MAV_RESULT_ACCEPTED
        kit_true = sim.kit_field.b_body_T().copy()
        flight.tick(t)
        if flight.new_sample:
            samples[round(flight.sample_t_s * 1e6)] = (flight.kit_skip, kit_true)
    events = [e.t_s for e in kit.sequencer.events if e.what == "capsule"]
    return flight, link, samples, events


@pytest.fixture(scope="module")
def decoded(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("kitground")
    flight, link, samples, events = sitl_run()
    live = link.messages()
    flagged_seq = sorted(m.seq for m in live if m.get_type() == "DEBRIS_MAG_SAMPLE"
                         and m.flags & mavlink.DEBRIS_SAMPLE_FLAGS_KIT_MOVING)
    fs = set(flagged_seq)
    s0 = next(s for s in flagged_seq if s > 0 and s - 1 not in fs)  # a shutter starts moving after a rest
    lost = {s0 - 1, s0, s0 + 1, s0 + 2}  # lost live: the last sample at rest and the first ones while it moves
    n_live = len(link.buf)
    first = min(lost)
    assert flight.resender.request(first, max(lost) - first + 1)
    for k in range(1, 20):  # the store sends them again within its budget
        flight.resender.service(DURATION_S + k, flight.tlm.resend_sample)
    resent = mavlink.MAVLink(None).parse_buffer(bytes(link.buf[n_live:])) or []
    dec = Decoder(recorder=Recorder(tmp / "run.csv", None))
    for m in live:
        if m.get_type() == "DEBRIS_MAG_SAMPLE" and m.seq in lost:
            continue
        dec.handle(m, 100.0 + m.time_usec * 1e-6 if hasattr(m, "time_usec") else 100.0)
    for m in resent:
        dec.handle(m, 100.0 + DURATION_S + 1.0)
    dec.finish()
    return SimpleNamespace(path=tmp / "run.csv", tmp=tmp, samples=samples, events=events, lost=lost,
                           resent=resent, flight=flight)


def test_the_recording_has_the_kit_columns_and_the_boxs_flags(decoded):
    rec = read_recording(decoded.path)
    assert rec.kit_T is not None and rec.flags is not None
    header = [line for line in decoded.path.read_text().splitlines() if not line.startswith("#")][0].split(",")
    assert {"kit_bx_uT", "kit_by_uT", "kit_bz_uT", "flags"} <= set(header)
    times = np.round(rec.t_s * 1e6).astype(np.int64)
    box_flagged = {t for t, (skip, _) in decoded.samples.items() if skip}
    rec_flagged = set(times[(rec.flags & mavlink.DEBRIS_SAMPLE_FLAGS_KIT_MOVING) != 0].tolist())
    assert len(box_flagged) >= 4 and rec_flagged == box_flagged
    assert len(rec) == len(decoded.samples)  # the lost ones came back from the store
    # the field less the recorded kit field against the same field less the simulator's kit field
    keep = (rec.flags & mavlink.DEBRIS_SAMPLE_FLAGS_KIT_MOVING) == 0
    kit_true = np.array([decoded.samples[int(t)][1] for t in times])
    assert np.max(np.abs(kit_true[keep])) > 40e-6  # the kit is there, tens of µT
    resid = (rec.b_T - rec.kit_T)[keep] - (rec.b_T - kit_true)[keep]
    rms = np.sqrt(np.mean(resid ** 2, axis=0))
    assert np.max(rms) < 1.5e-6, rms


def test_a_sample_sent_again_from_the_store_keeps_its_flag_and_kit_field(decoded):
    resent = [m for m in decoded.resent if m.get_type() == "DEBRIS_MAG_SAMPLE"]
    assert {m.seq for m in resent} >= decoded.lost
    assert all(m.flags & mavlink.DEBRIS_SAMPLE_FLAGS_RESENT for m in resent)
    rec = read_recording(decoded.path)
    times = np.round(rec.t_s * 1e6).astype(np.int64)
    for m in resent:
        if m.seq not in decoded.lost:
            continue
        i = int(np.flatnonzero(times == m.time_usec)[0])
        skip, _ = decoded.samples[int(m.time_usec)]
        assert bool(rec.flags[i] & mavlink.DEBRIS_SAMPLE_FLAGS_KIT_MOVING) == skip
        assert not rec.flags[i] & mavlink.DEBRIS_SAMPLE_FLAGS_RESENT
        assert rec.kit_T[i] == pytest.approx(np.array(m.kit_mag) * 1e-4, abs=1e-12)
    assert any(bool(m.flags & mavlink.DEBRIS_SAMPLE_FLAGS_KIT_MOVING) for m in resent if m.seq in decoded.lost)


def excursions(rates_path, rec_path, events):
    """Worst |ω − truth| (°/s, per sample, any axis) within WINDOW_S of a capsule event, and elsewhere."""
    est = read_rate_estimates(rates_path)
    ref = read_recording(rec_path)
    truth = dict(zip(np.round(ref.t_s * 1e6).astype(np.int64).tolist(), np.rad2deg(ref.w_ref_radps)))
    t = est.t_s
    err = np.array([np.abs(np.rad2deg(w) - truth[int(round(tt * 1e6))]).max() for tt, w in zip(t, est.w_radps)])
    near = np.zeros(len(t), dtype=bool)
    for te in events:
        near |= np.abs(t - te) <= WINDOW_S
    ok = np.isfinite(err)
    return float(np.max(err[near & ok])), float(np.percentile(err[~near & ok], 99))


def test_ground_estimate_skips_and_subtracts_the_kit_and_sees_no_steps(decoded, capsys):
    out, raw = decoded.tmp / "rates.csv", decoded.tmp / "rates_raw.csv"
    assert estimate.main([str(decoded.path), "--rates", str(out), "--method", "boer"]) == 0
    first = capsys.readouterr().out.splitlines()[0]
    n_flagged = sum(1 for skip, _ in decoded.samples.values() if skip)
    assert first.startswith(f"kit field: {n_flagged} of {len(decoded.samples)} samples flagged KIT_MOVING skipped")
    assert estimate.main([str(decoded.path), "--rates", str(raw), "--method", "boer", "--kit-raw"]) == 0
    assert capsys.readouterr().out.splitlines()[0].startswith("kit field: kept raw (--kit-raw)")
    assert len(read_rate_estimates(out)) == len(decoded.samples) - n_flagged
    near, elsewhere = excursions(out, decoded.path, decoded.events)
    near_raw, _ = excursions(raw, decoded.path, decoded.events)
    print(f"boer |error| near capsule events: compensated {near:.2f} °/s (elsewhere p99 {elsewhere:.2f}), "
          f"raw {near_raw:.2f} °/s")
    assert near <= 1.5 * elsewhere + 0.5   # no step-driven excursion
    assert near_raw > 5.0 * near           # the raw recording has them
