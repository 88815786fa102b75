"""The ground decoder on a tlog built from frames packed with the project dialect (known field, rate and
moment; garbage, a bad-CRC frame and a skipped sequence number injected), and over UDP loopback."""
from __future__ import annotations

import math
import socket
import struct
import threading
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fsw.telemetry import dialect
from fsw.telemetry.dialect import FSW_COMPID, FSW_SYSID, mavlink
from ground.decode import Decoder, main, run, tlog_record
from ground.recording import read_rate_estimates, read_recording

FSW = (FSW_SYSID, FSW_COMPID)
N = 40
PERIOD_US = 100_000                  # 10 Hz magnetometer
T0_US = 2_000_000                     # first sample 2 s after the flight software started
WALL0_S = 1_700_000_000.0             # tlog time stamps
OMEGA_RADPS = np.array([0.1, -0.2, 0.3])
B0_GAUSS = np.array([0.20, -0.05, 0.40])  # 45 µT
SKIPPED_K = 7                         # the BOER estimate of this sample is never sent (seq skipped)
BAD_CRC_K = 20                        # the DEBRIS_SIM_STATE of this sample arrives with a bad CRC
GARBAGE = bytes([0x11, 0x22, 0x33, 0x00, 0x55, 0x66, 0x77, 0x88, 0x99, 0xAA, 0xBB, 0xCC, 0x01])


def field_gauss(k: int) -> np.ndarray:
    """Field fixed in inertial space seen from a body turning at ω: B(t) = exp(−[ω]× t) B0, the
    solution of dB/dt = B × ω."""
    t = k * PERIOD_US * 1e-6
    return Rotation.from_rotvec(-OMEGA_RADPS * t).apply(B0_GAUSS)


def boer_radps(k: int) -> np.ndarray:
    return OMEGA_RADPS + 0.001 * k


def derivative_radps(k: int) -> np.ndarray:
    return -OMEGA_RADPS - 0.002 * k


def moment_Nm(k: int) -> np.ndarray:
    return np.array([0.0, 0.01 * k, -0.02])


def t_us(k: int) -> int:
    return T0_US + k * PERIOD_US


class Stream:
    """Frames packed by the dialect as the flight software sends them, as tlog records."""

    def __init__(self) -> None:
        self.mav = mavlink.MAVLink(None, srcSystem=FSW[0], srcComponent=FSW[1])
        self.records: list[bytes] = []

    def send(self, msg, wall_s: float, corrupt: bool = False) -> None:
        frame = bytearray(msg.pack(self.mav))
        self.mav.seq = (self.mav.seq + 1) % 256
        if corrupt:
            frame[14] ^= 0x04
        self.records.append(struct.pack(">Q", int(wall_s * 1e6)) + bytes(frame))

    def skip(self) -> None:
        self.mav.seq = (self.mav.seq + 1) % 256


def build_tlog(path: Path) -> Path:
    s = Stream()
    m = s.mav
    for k in range(N):
        wall = WALL0_S + 0.1 * k
        if k % 10 == 0:
            s.send(m.heartbeat_encode(mavlink.MAV_TYPE_ONBOARD_CONTROLLER, mavlink.MAV_AUTOPILOT_INVALID,
                                      0, 0, mavlink.MAV_STATE_ACTIVE), wall)
        b = field_gauss(k)
        s.send(m.highres_imu_encode(t_us(k), 0, 0, 0, 0, 0, 0, *b, 0, 0, 0, 0, 0x1C0), wall)
        flags = mavlink.DEBRIS_ESTIMATE_FLAGS_PERPENDICULAR_ONLY
        if k == 0:
            flags |= mavlink.DEBRIS_ESTIMATE_FLAGS_NO_ESTIMATE
        if k == SKIPPED_K:
            s.skip()
        else:
            s.send(m.debris_rate_estimate_encode(t_us(k), *boer_radps(k), 0.01, 0.02, 0.03,
                                                 mavlink.DEBRIS_RATE_METHOD_BOER, flags), wall)
        s.send(m.debris_rate_estimate_encode(t_us(k), *derivative_radps(k), 0.1, 0.1, 0.1,
                                             mavlink.DEBRIS_RATE_METHOD_DERIVATIVE,
                                             mavlink.DEBRIS_ESTIMATE_FLAGS_NO_ESTIMATE if k < 2 else 0), wall)
        q = Rotation.from_rotvec(OMEGA_RADPS * k * 0.1).as_quat(scalar_first=True)
        s.send(m.debris_sim_state_encode(t_us(k), *OMEGA_RADPS, q, *b, *moment_Nm(k)), wall,
               corrupt=(k == BAD_CRC_K))
        if k == 12:
            s.records.append(struct.pack(">Q", int(wall * 1e6)) + GARBAGE)
    path.write_bytes(b"".join(s.records))
    return path


@pytest.fixture(scope="module")
def tlog(tmp_path_factory) -> Path:
    return build_tlog(tmp_path_factory.mktemp("tlog") / "flight.tlog")


def test_csv_holds_the_known_field_truth_and_moment(tlog: Path, tmp_path: Path) -> None:
    lines: list[str] = []
    run(str(tlog), csv=tmp_path / "rec.csv", rates_csv=tmp_path / "rates.csv", on_line=lines.append)
    rec = read_recording(tmp_path / "rec.csv")
    assert len(rec) == N
    np.testing.assert_allclose(rec.t_s, [t_us(k) * 1e-6 for k in range(N)], rtol=0, atol=1e-12)
    b_true_uT = np.array([field_gauss(k) for k in range(N)]) * 100.0
    # float32 on the wire: 45 µT to ~3e-6 µT
    np.testing.assert_allclose(rec.b_T * 1e6, b_true_uT, rtol=0, atol=1e-5)
    np.testing.assert_allclose(np.linalg.norm(rec.b_T, axis=1) * 1e6, 45.0, atol=0.01)
    ok = np.arange(N) != BAD_CRC_K
    np.testing.assert_allclose(np.rad2deg(rec.w_ref_radps[ok]),
                               np.tile(np.rad2deg(OMEGA_RADPS), (N - 1, 1)), rtol=0, atol=1e-5)
    np.testing.assert_allclose(rec.m_Nm[ok], np.array([moment_Nm(k) for k in range(N)])[ok], atol=1e-8)
    assert np.isnan(rec.w_ref_radps[BAD_CRC_K]).all() and np.isnan(rec.m_Nm[BAD_CRC_K]).all()
    assert "MAVLink telemetry" in rec.metadata["source"] and str(tlog) in rec.metadata["source"]

    est = read_rate_estimates(tmp_path / "rates.csv")
    np.testing.assert_array_equal(est.t_s, rec.t_s)
    have = (np.arange(N) != 0) & (np.arange(N) != SKIPPED_K)
    assert np.isnan(est.w_radps[~have]).all() and np.isnan(est.sigma_radps[~have]).all()
    np.testing.assert_allclose(np.rad2deg(est.w_radps[have]),
                               np.rad2deg([boer_radps(k) for k in range(N)])[have], atol=1e-5)
    np.testing.assert_allclose(np.rad2deg(est.sigma_radps[have]),
                               np.tile(np.rad2deg([0.01, 0.02, 0.03]), (have.sum(), 1)), atol=1e-6)
    assert est.metadata["method"].startswith("boer")

    # live lines on the recorded timeline (~4 s): about one per second
    status = [ln for ln in lines if "µT" in ln]
    assert 3 <= len(status) <= 4
    assert "ω[boer]" in status[-1] and f"true |ω| {np.linalg.norm(np.rad2deg(OMEGA_RADPS)):6.2f}" in status[-1]


def test_rejects_and_loss_are_counted(tlog: Path) -> None:
    dec = run(str(tlog), quiet=True)
    summary = dec.stats.summary()
    src = summary["sources"][FSW]
    assert src["lost"] == 2              # the skipped seq and the frame that failed its CRC
    assert summary["bad_crc"] == 1
    assert 1 <= summary["garbage_bytes"] <= len(GARBAGE) and summary["garbage_chunks"] >= 1
    assert src["duplicates"] == 0 and src["samples"] == N and src["samples_missing"] == 0
    assert dec.frames_by_type["HIGHRES_IMU"] == N
    assert dec.frames_by_type["DEBRIS_RATE_ESTIMATE"] == 2 * N - 1
    assert dec.frames_by_type["DEBRIS_SIM_STATE"] == N - 1
    assert dec.frames_by_type["HEARTBEAT"] == N // 10
    assert src["received"] == N + 2 * N - 1 + N - 1 + N // 10
    text = dec.summary_text()
    assert "1 bad CRC" in text and f"source {FSW[0]}/{FSW[1]}: received" in text and "lost 2" in text


def test_tlog_output_replays_to_the_same_recording(tlog: Path, tmp_path: Path) -> None:
    first = run(str(tlog), tlog=tmp_path / "copy.tlog", quiet=True)
    second = run(str(tmp_path / "copy.tlog"), quiet=True)
    a, b = first.recording(), second.recording()
    np.testing.assert_array_equal(a.t_s, b.t_s)
    np.testing.assert_array_equal(a.b_T, b.b_T)
    np.testing.assert_array_equal(a.w_ref_radps, b.w_ref_radps)
    intact = sum(n for kind, n in first.frames_by_type.items() if kind != "BAD_DATA")
    assert second.stats.summary()["garbage_bytes"] == 0 and second.stats.summary()["bad_crc"] == 0
    assert sum(second.frames_by_type.values()) == intact
    # the copy keeps the recorded time stamps
    raw = (tmp_path / "copy.tlog").read_bytes()
    assert abs(struct.unpack(">Q", raw[:8])[0] * 1e-6 - WALL0_S) < 1e-5


def test_main_with_derivative_method(tlog: Path, tmp_path: Path, capsys) -> None:
    rc = main([str(tlog), "--rates-csv", str(tmp_path / "d.csv"), "--method", "derivative", "--quiet"])
    assert rc == 0
    est = read_rate_estimates(tmp_path / "d.csv")
    assert np.isnan(est.w_radps[:2]).all()
    np.testing.assert_allclose(np.rad2deg(est.w_radps[2:]),
                               np.rad2deg([derivative_radps(k) for k in range(2, N)]), atol=1e-5)
    out = capsys.readouterr().out
    assert "frames by type:" in out and "HIGHRES_IMU 40" in out and "rejected:" in out
    assert "µT" not in out  # --quiet: no live lines


def test_count_and_duration_stop_early(tlog: Path) -> None:
    dec = run(str(tlog), count=10, quiet=True)
    assert sum(n for kind, n in dec.frames_by_type.items() if kind != "BAD_DATA") == 10
    dec = run(str(tlog), duration_s=0.95, quiet=True)  # recorded time line of a 10 Hz stream
    assert len(dec.recording()) == 10  # samples at 0.0 … 0.9 s; the first frame at 1.0 s stops it


def test_ctrl_c_still_writes_the_outputs(tlog: Path, tmp_path: Path) -> None:
    def interrupt(line: str) -> None:
        raise KeyboardInterrupt

    dec = run(str(tlog), csv=tmp_path / "part.csv", on_line=interrupt)
    rec = read_recording(tmp_path / "part.csv")
    assert 0 < len(rec) < N and len(rec) == len(dec.recording())


def test_decoder_driven_in_process_locks_onto_the_sample_source() -> None:
    """Samples from a second system do not mix into the recording."""
    dec = Decoder()
    parser = mavlink.MAVLink(None)
    for src, gauss in ((FSW, 0.3), ((7, 1), 0.9), (FSW, 0.3)):
        packer = mavlink.MAVLink(None, srcSystem=src[0], srcComponent=src[1])
        msg = packer.highres_imu_encode(t_us(len(dec.recording())), 0, 0, 0, 0, 0, 0, gauss, 0, 0, 0, 0, 0, 0, 0x1C0)
        for m in parser.parse_buffer(msg.pack(packer)):
            dec.handle(m, 0.0)
    rec = dec.recording()
    assert dec.source == FSW and len(rec) == 2
    np.testing.assert_allclose(rec.b_T[:, 0], 0.3e-4, rtol=1e-6)
    assert rec.w_ref_radps is None and not rec.m_Nm.any()


def test_flight_software_restart_starts_a_new_segment() -> None:
    lines: list[str] = []
    dec = Decoder(on_line=lines.append)
    parser = mavlink.MAVLink(None)
    packer = mavlink.MAVLink(None, srcSystem=FSW[0], srcComponent=FSW[1])
    for t in [t_us(k) for k in range(30)] + [k * PERIOD_US for k in range(5)]:
        frame = packer.highres_imu_encode(t, 0, 0, 0, 0, 0, 0, 0.3, 0, 0, 0, 0, 0, 0, 0x1C0).pack(packer)
        packer.seq = (packer.seq + 1) % 256
        for m in parser.parse_buffer(frame):
            dec.handle(m, 0.0)
    rec = dec.recording()
    np.testing.assert_allclose(rec.t_s, np.arange(5) * 0.1)
    assert any("restarted" in ln for ln in lines)
    assert rec.metadata["segment"].startswith("run 2 of 2 runs")
    assert len(dec.recording(dec.segments[0])) == 30            # the first run is kept, not discarded


def test_tlog_record_format() -> None:
    packer = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    msg = packer.heartbeat_encode(0, 0, 0, 0, 0)
    msg.pack(packer)
    rec = tlog_record(msg, 1.5)
    assert rec[:8] == struct.pack(">Q", 1_500_000) and rec[8:] == bytes(msg.get_msgbuf())


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_udp_loopback(tmp_path: Path) -> None:
    port = _free_udp_port()
    stop = threading.Event()

    def sender() -> None:
        out = dialect.open_link(f"udpout:127.0.0.1:{port}", source_system=FSW[0], source_component=FSW[1])
        k = 0
        while not stop.is_set() and k < 5000:
            b = field_gauss(k % N)
            out.mav.send(out.mav.highres_imu_encode(t_us(k), 0, 0, 0, 0, 0, 0, *b, 0, 0, 0, 0, 0x1C0))
            out.mav.send(out.mav.debris_sim_state_encode(t_us(k), *OMEGA_RADPS, [1, 0, 0, 0], *b, 0, 0, 0))
            k += 1
            stop.wait(0.002)
        out.close()

    thread = threading.Thread(target=sender, daemon=True)
    thread.start()
    try:
        dec = run(f"udpin:127.0.0.1:{port}", count=60, duration_s=20.0, csv=tmp_path / "udp.csv", quiet=True)
    finally:
        stop.set()
        thread.join(5.0)
    assert sum(dec.frames_by_type.values()) == 60
    summary = dec.stats.summary()
    assert summary["sources"][FSW]["received"] == 60 and summary["sources"][FSW]["lost"] == 0
    rec = read_recording(tmp_path / "udp.csv")
    assert len(rec) in (30, 31)  # the first frame seen may be either message of a pair
    np.testing.assert_allclose(np.diff(rec.t_s), PERIOD_US * 1e-6, rtol=1e-9)
    matched = ~np.isnan(rec.w_ref_radps[:, 0])
    assert matched.sum() >= 29
    np.testing.assert_allclose(rec.w_ref_radps[matched], np.tile(OMEGA_RADPS, (matched.sum(), 1)), atol=1e-7)


def test_udp_silence_ends_at_the_duration() -> None:
    calls = iter(np.arange(0.0, 100.0, 0.1))  # an injected clock: each wait advances it 0.1 s
    dec = run(f"udpin:127.0.0.1:{_free_udp_port()}", duration_s=0.35, quiet=True, clock=lambda: next(calls))
    assert sum(dec.frames_by_type.values()) == 0 and len(dec.recording()) == 0
    assert math.isclose(dec.stats.summary()["totals"]["loss_fraction"], 0.0)


def test_non_finite_values_are_counted_not_recorded(tmp_path: Path) -> None:
    dec = Decoder()
    parser = mavlink.MAVLink(None)
    packer = mavlink.MAVLink(None, srcSystem=FSW[0], srcComponent=FSW[1])
    msgs = [packer.highres_imu_encode(t_us(0), 0, 0, 0, 0, 0, 0, 0.3, 0, 0.1, 0, 0, 0, 0, 0x1C0),
            packer.highres_imu_encode(t_us(1), 0, 0, 0, 0, 0, 0, math.nan, 0, 0.1, 0, 0, 0, 0, 0x1C0),
            packer.debris_rate_estimate_encode(t_us(0), math.inf, 0, 0, 0, 0, 0, mavlink.DEBRIS_RATE_METHOD_BOER, 0),
            packer.debris_sim_state_encode(t_us(0), 0.1, 0, 0, [1, 0, 0, 0], 0.3, 0, 0.1, math.nan, 0, 0)]
    for msg in msgs:
        frame = msg.pack(packer)
        packer.seq += 1
        for m in parser.parse_buffer(frame):
            dec.handle(m, 0.0)
    dec.write(csv=tmp_path / "r.csv", rates_csv=tmp_path / "e.csv")
    assert len(read_recording(tmp_path / "r.csv")) == 1
    assert np.isnan(read_rate_estimates(tmp_path / "e.csv").w_radps).all()
    assert dict(dec.invalid) == {"HIGHRES_IMU": 1, "DEBRIS_RATE_ESTIMATE": 1, "DEBRIS_SIM_STATE": 1}
    assert "non-finite values" in dec.summary_text()


@pytest.mark.parametrize("time_us", [2**53, 2**63, 2**64 - 1])
def test_impossible_sample_times_are_counted_not_recorded(tmp_path: Path, time_us: int) -> None:
    """Found by the fuzz (tests/test_fuzz_readers.py): a sample time of 2**63 µs or more (any uint64 is
    a valid time_usec) made the summary raise OverflowError; from 2**53 µs on, two times could become
    the same float in the recording, which the writer refuses."""
    dec = Decoder()
    parser = mavlink.MAVLink(None)
    packer = mavlink.MAVLink(None, srcSystem=FSW[0], srcComponent=FSW[1])
    msgs = [packer.highres_imu_encode(t_us(0), 0, 0, 0, 0, 0, 0, 0.3, 0, 0.1, 0, 0, 0, 0, 0x1C0),
            packer.highres_imu_encode(time_us, 0, 0, 0, 0, 0, 0, 0.3, 0, 0.1, 0, 0, 0, 0, 0x1C0),
            packer.debris_mag_sample_encode(time_us, 0, 7, [0.3, 0, 0.1], 0)]
    for msg in msgs:
        frame = msg.pack(packer)
        packer.seq += 1
        for m in parser.parse_buffer(frame):
            dec.handle(m, 0.0)
    assert "impossible times" in dec.summary_text()
    dec.write(csv=tmp_path / "r.csv")
    assert len(read_recording(tmp_path / "r.csv")) == 1
    assert dec.invalid["DEBRIS_MAG_SAMPLE"] == 1 and dec.invalid["HIGHRES_IMU"] == 1
