"""The recording carries what the box knew: the UTC of t = 0, its TLE, its last calibration — in the
metadata block when known at the start, appended as it arrives later, kept by a kill -9, given to the
run it belongs to."""
import math
import signal
import socket
import time
from datetime import datetime

import numpy as np
import pytest

from fsw.estimation.onboard_field import field_from_metadata
from fsw.telemetry.dialect import mavlink
from ground.decode import Decoder
from ground.recorder import MAGCAL_RESTATE_S, Recorder
from ground.recording import read_recording
from support import circular_tle, free_udp_port
from test_decode_recording import Box, feed, rows, start_decoder

UTC_AT_0 = 1795780800.25          # 2026-11-27T12:00:00.25Z, POSIX s
L1, L2 = circular_tle(epoch="26330.00000000")
NEWER = circular_tle(epoch="26331.00000000")


def time_orbit(box, t_s, utc0_s=UTC_AT_0, drift_ppm=math.nan, degree=8):
    utc_us = int(round((utc0_s + t_s * (1 + (0 if math.isnan(drift_ppm) else drift_ppm * 1e-6))) * 1e6))
    return box.pack(mavlink.MAVLink_debris_time_orbit_message(
        int(round(t_s * 1e6)), utc_us, 1.0, drift_ppm, math.nan, 1, 0, 1795600000000000, 2e5,
        mavlink.DEBRIS_TLE_STATE_OK, 1, 0, 0, degree, 1))


def system_time(box, t_s, utc0_s=UTC_AT_0):
    return box.pack(mavlink.MAVLink_system_time_message(int(round((utc0_s + t_s) * 1e6)), int(t_s * 1e3)))


def tle(box, lines=(L1, L2), target=0):
    return box.pack(mavlink.MAVLink_debris_tle_message(target, 0, lines[0].encode(), lines[1].encode()))


def magcal(box, t_s, b_uT=(6.0, -9.0, 4.0), state=mavlink.DEBRIS_MAGCAL_STATE_CONVERGED):
    return box.pack(mavlink.MAVLink_debris_magcal_message(
        int(round(t_s * 1e6)), 100, 0, 0, list(b_uT), [0.01, -0.02, 0.03, 0.004, 0.005, 0.006],
        [0.05, 0.05, 0.05], [1e-3] * 6, 1.0, state))


def test_what_the_box_knew_is_in_the_metadata_and_the_field_follows_from_it(tmp_path):
    dec = Decoder(recorder=Recorder(tmp_path / "run.csv", None))
    box = Box()
    feed(dec, [time_orbit(box, 0.0, drift_ppm=20.0), tle(box), magcal(box, 0.0)], 100.0)
    for k in range(30):
        feed(dec, [box.sample(0.1 * k)], 100.0 + 0.1 * k)
        dec.tick(100.0 + 0.1 * k)
    dec.finish()
    rec = read_recording(tmp_path / "run.csv")
    md = rec.metadata
    assert md["tle_line1"] == L1 and md["tle_line2"] == L2 and md["tle_state"] == "ok"
    assert md["field_model"] == "igrf14:8"
    assert datetime.fromisoformat(md["utc0"]).timestamp() == pytest.approx(UTC_AT_0, abs=1e-6)
    assert md["magcal_hard_iron_uT"] == "6.0, -9.0, 4.0" and md["magcal_state"] == "converged"
    D = np.array(md["magcal_soft_iron"].split(","), float).reshape(3, 3)
    np.testing.assert_allclose(D, [[0.01, 0.004, 0.005], [0.004, -0.02, 0.006], [0.005, 0.006, 0.03]], atol=1e-7)
    assert "hard_iron_uT" not in md and "soft_iron" not in md      # the samples are the sensor's own
    line = next(x for x in dec.summary_text().splitlines() if x.startswith("what the box knew"))
    assert "UTC of t = 0 2026-11-27T12:00:00.250000Z (DEBRIS_TIME_ORBIT)" in line and "TLE 99999 (ok)" in line
    assert "calibration converged at t = 0 s, hard iron 6.0, -9.0, 4.0 µT" in line
    field = field_from_metadata(md)                               # the ground's field along that orbit
    assert field is not None and np.all(np.isfinite(field.b_eci_T(np.array([0.0, 60.0]))))


def test_utc0_is_the_box_s_affine_time_back_at_zero():
    dec = Decoder()
    box = Box()
    feed(dec, [box.sample(0.0)], 1.0)
    feed(dec, [time_orbit(box, 5000.0, drift_ppm=40.0)], 2.0)     # 5000 s at 1 + 40e-6: 0.2 s more than 5000
    assert dec.streams[(box.p.srcSystem, box.p.srcComponent)].current.knowledge.utc0_s == pytest.approx(
        UTC_AT_0, abs=1e-6)


def test_system_time_gives_utc0_to_a_millisecond_unless_the_box_said_more():
    dec = Decoder()
    box = Box()
    feed(dec, [box.sample(0.0), system_time(box, 12.3456)], 1.0)
    k = dec.streams[(box.p.srcSystem, box.p.srcComponent)].current.knowledge
    assert k.utc0_s == pytest.approx(UTC_AT_0, abs=1e-3) and k.utc0_from == "SYSTEM_TIME"
    feed(dec, [time_orbit(box, 13.0, utc0_s=UTC_AT_0 + 0.5), system_time(box, 14.0)], 2.0)
    assert k.utc0_s == pytest.approx(UTC_AT_0 + 0.5, abs=1e-6)      # the box's own, SYSTEM_TIME no longer


@pytest.mark.parametrize("utc0_s, drift_ppm", [(1.8e13, math.nan), (UTC_AT_0, -3e22), (946684800.0 - 1.0, math.nan),
                                               (7258118400.0, math.nan)])
def test_a_time_the_box_could_not_have_had_is_counted_not_kept(utc0_s, drift_ppm):
    """A damaged or hostile frame's UTC (years 2000-2200 are the box's) is refused and counted; the summary,
    which prints the UTC of t = 0, never meets it."""
    dec = Decoder()
    box = Box()
    frame = time_orbit(box, 5.0, utc0_s=utc0_s)
    if not math.isnan(drift_ppm):  # the UTC as the box would send it, with a drift no clock has
        frame = box.pack(mavlink.MAVLink_debris_time_orbit_message(
            5_000_000, int(round((utc0_s + 5.0) * 1e6)), 1.0, drift_ppm, math.nan, 1, 0, 1795600000000000, 2e5,
            mavlink.DEBRIS_TLE_STATE_OK, 1, 0, 0, 8, 1))
    feed(dec, [box.sample(0.0), frame], 1.0)
    if math.isnan(drift_ppm):
        feed(dec, [system_time(box, 6.0, utc0_s=utc0_s)], 2.0)
    assert dec.streams[(box.p.srcSystem, box.p.srcComponent)].current.knowledge.utc0_s is None
    assert dec.invalid["DEBRIS_TIME_ORBIT"] == 1 and dec.invalid["SYSTEM_TIME"] == int(math.isnan(drift_ppm))
    assert "UTC of t = 0" not in dec.summary_text()


def test_knowledge_arriving_later_is_appended_and_replaces_the_header(tmp_path):
    dec = Decoder(recorder=Recorder(tmp_path / "run.csv", None))
    box = Box()
    feed(dec, [time_orbit(box, 0.0), tle(box)], 100.0)
    n = 0

    def samples(k, t_s):
        nonlocal n
        for _ in range(k):
            now = 100.0 + 0.1 * n
            feed(dec, [box.sample(0.1 * n)], now)
            dec.tick(now)
            n += 1

    samples(30, 0)
    assert "magcal" not in (tmp_path / "run.csv").read_text()           # the file started without it
    feed(dec, [magcal(box, 3.0, b_uT=(1.0, 2.0, 3.0), state=mavlink.DEBRIS_MAGCAL_STATE_UNCERTAIN)], 103.0)
    samples(20, 0)
    feed(dec, [magcal(box, 20.0, b_uT=(1.5, 2.0, 3.0), state=mavlink.DEBRIS_MAGCAL_STATE_UNCERTAIN)], 105.0)
    samples(20, 0)                                  # same state, 17 s later: not restated yet
    assert read_recording(tmp_path / "run.csv").metadata["magcal_hard_iron_uT"] == "1.0, 2.0, 3.0"
    feed(dec, [magcal(box, 25.0, b_uT=(6.0, -9.0, 4.0)), tle(box, NEWER)], 107.0)   # converged: restated
    samples(20, 0)
    text = (tmp_path / "run.csv").read_text()
    md = read_recording(tmp_path / "run.csv").metadata
    assert md["magcal_hard_iron_uT"] == "6.0, -9.0, 4.0" and md["magcal_state"] == "converged"
    assert md["tle_line1"] == NEWER[0] and md["tle_line2"] == NEWER[1]
    assert text.count("# tle_line1:") == 2 and text.count("# magcal_state:") == 2
    feed(dec, [magcal(box, 25.0 + MAGCAL_RESTATE_S / 2, b_uT=(6.01, -9.0, 4.0))], 109.0)
    dec.finish()                                    # the end states the latest
    md = read_recording(tmp_path / "run.csv").metadata
    assert md["magcal_hard_iron_uT"] == "6.01, -9.0, 4.0" and len(read_recording(tmp_path / "run.csv")) == 90


def test_a_restart_s_knowledge_goes_to_the_new_run_not_the_old(tmp_path):
    dec = Decoder(recorder=Recorder(tmp_path / "run.csv", None))
    first, second = Box(run_id=1), Box(run_id=2)
    second.p.seq = 100
    feed(dec, [time_orbit(first, 0.0), tle(first)], 10.0)
    for k in range(100):
        feed(dec, [first.sample(0.1 * k)], 10.0 + 0.1 * k)
    # the new run says its time (it was set again: 3 s later) and TLE before its first sample arrives
    feed(dec, [time_orbit(second, 0.5, utc0_s=UTC_AT_0 + 3.0), tle(second, NEWER)], 21.0)
    for k in range(20):
        feed(dec, [second.sample(1.0 + 0.1 * k)], 21.0 + 0.1 * k)
    dec.finish()
    old = read_recording(tmp_path / "run.csv").metadata
    new = read_recording(tmp_path / f"run.{first.p.srcSystem}-{first.p.srcComponent}.run2.csv").metadata
    assert datetime.fromisoformat(old["utc0"]).timestamp() == pytest.approx(UTC_AT_0, abs=1e-6)
    assert old["tle_line1"] == L1
    assert datetime.fromisoformat(new["utc0"]).timestamp() == pytest.approx(UTC_AT_0 + 3.0, abs=1e-6)
    assert new["tle_line1"] == NEWER[0]


def test_a_bad_tle_or_a_station_s_upload_is_not_taken_for_the_box_s(tmp_path):
    dec = Decoder()
    box = Box()
    bad = (L1[:-1] + str((int(L1[-1]) + 1) % 10), L2)
    feed(dec, [box.sample(0.0), tle(box, bad), tle(box, NEWER, target=box.p.srcSystem)], 1.0)
    assert "tle_line1" not in dec.metadata() and dec.invalid["DEBRIS_TLE"] == 1


def test_knowledge_appended_to_a_live_recording_survives_kill_9(tmp_path):
    port = free_udp_port()
    proc = start_decoder(tmp_path, port)
    box = Box()
    path = tmp_path / "live.csv"
    try:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
            deadline = time.monotonic() + 60
            while rows(path) < 10:                                   # the file started without it
                assert time.monotonic() < deadline
                sock.sendto(box.sample(0.1 * box.seq), ("127.0.0.1", port))
                time.sleep(0.02)
            for frame in (time_orbit(box, 0.1 * box.seq), tle(box), magcal(box, 0.1 * box.seq)):
                sock.sendto(frame, ("127.0.0.1", port))
            while "magcal_state" not in path.read_text() or rows(path) < 40:
                assert time.monotonic() < deadline
                sock.sendto(box.sample(0.1 * box.seq), ("127.0.0.1", port))
                time.sleep(0.02)
        proc.send_signal(signal.SIGKILL)
        proc.communicate(timeout=30)
    finally:
        proc.kill()
    rec = read_recording(path)
    assert len(rec) >= 40 and rec.metadata["tle_line1"] == L1 and rec.metadata["magcal_state"] == "converged"
    assert datetime.fromisoformat(rec.metadata["utc0"]).timestamp() == pytest.approx(UTC_AT_0, abs=1e-6)
