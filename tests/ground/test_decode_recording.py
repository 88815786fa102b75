"""The decoder's recordings: written while the frames arrive, every source and run apart, readable after
a kill -9, complete after SIGTERM; nothing received is said, not written as empty files."""
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from fsw.telemetry.dialect import FSW_COMPID, FSW_SYSID, mavlink
from ground.decode import Decoder, main
from ground.recorder import Recorder
from ground.recording import read_recording
from support import free_udp_port

ROOT = Path(__file__).resolve().parents[2]


class Box:
    """Packs the frames a box sends: numbered samples and their truth."""

    def __init__(self, sysid=FSW_SYSID, compid=FSW_COMPID, run_id=0x1234):
        self.p = mavlink.MAVLink(None, srcSystem=sysid, srcComponent=compid)
        self.run_id = run_id
        self.seq = 0

    def pack(self, msg) -> bytes:
        frame = msg.pack(self.p)
        self.p.seq = (self.p.seq + 1) % 256
        return frame

    def sample(self, t_s, gauss=0.3, seq=None) -> bytes:
        seq = self.seq if seq is None else seq
        self.seq = seq + 1
        return self.pack(mavlink.MAVLink_debris_mag_sample_message(int(round(t_s * 1e6)), seq, self.run_id,
                                                                   [gauss, 0.1, -0.2], 0))

    def truth(self, t_s) -> bytes:
        return self.pack(mavlink.MAVLink_debris_sim_state_message(int(round(t_s * 1e6)), 0.1, 0.2, 0.3, [1, 0, 0, 0],
                                                                  0.3, 0.1, -0.2, 0.0, 0.0, 0.0))


def feed(dec, frames, now_s):
    parser = mavlink.MAVLink(None)
    for f in frames:
        for m in parser.parse_buffer(f) or []:
            dec.handle(m, now_s)


def test_a_stray_source_and_a_forged_run_never_touch_the_recorded_stream(tmp_path):
    dec = Decoder(recorder=Recorder(tmp_path / "run.csv", tmp_path / "rates.csv"))
    box, stranger, forger = Box(), Box(sysid=7, compid=1), Box(run_id=0x9999)
    for k in range(300):
        feed(dec, [box.sample(0.1 * k), box.truth(0.1 * k)], 100.0 + 0.1 * k)
        if k == 150:
            feed(dec, [stranger.sample(0.0, gauss=0.9), forger.sample(0.01, gauss=0.5)], 100.0 + 0.1 * k)
        dec.tick(100.0 + 0.1 * k)
    dec.finish()
    rec = read_recording(tmp_path / "run.csv")
    assert len(rec) == 300 and np.allclose(rec.b_T[:, 0], 0.3e-4)
    assert np.isfinite(rec.w_ref_radps).all()                               # truth columns, matched
    other = read_recording(tmp_path / "run.7-1.run1.csv")
    assert len(other) == 1 and other.b_T[0, 0] == pytest.approx(0.9e-4)
    forged = read_recording(tmp_path / f"run.{FSW_SYSID}-{FSW_COMPID}.run2.csv")
    assert len(forged) == 1 and forged.b_T[0, 0] == pytest.approx(0.5e-4)
    assert ("recording", tmp_path / "run.csv") in dec.recorder.written


def test_a_restart_goes_to_its_own_file_and_the_first_run_is_kept(tmp_path):
    dec = Decoder(recorder=Recorder(tmp_path / "run.csv", None))
    first, second = Box(run_id=1), Box(run_id=2)
    for k in range(50):
        feed(dec, [first.sample(0.1 * k)], 10.0 + 0.1 * k)
    for k in range(20):
        feed(dec, [second.sample(0.1 * k)], 20.0 + 0.1 * k)
    dec.finish()
    assert len(read_recording(tmp_path / "run.csv")) == 50
    rec2 = read_recording(tmp_path / f"run.{FSW_SYSID}-{FSW_COMPID}.run2.csv")
    assert len(rec2) == 20 and "run 2 of 2" in rec2.metadata["segment"]


def test_a_sample_sent_again_after_its_place_was_written_is_merged_at_the_end(tmp_path):
    dec = Decoder(recorder=Recorder(tmp_path / "run.csv", None))
    box = Box()
    frames = [box.sample(0.1 * k) for k in range(100)]
    for k, f in enumerate(frames):
        if k != 40:
            feed(dec, [f], 0.1 * k)
        dec.tick(0.1 * k)
    for k in range(60):                          # long enough for the decoder (no uplink) to give 40 up
        dec.tick(10.0 + 0.5 * k)
    assert len(read_recording(tmp_path / "run.csv")) == 99
    feed(dec, [frames[40]], 40.0)                # ... and then it comes
    dec.finish()
    rec = read_recording(tmp_path / "run.csv")
    np.testing.assert_allclose(rec.t_s, np.arange(100) * 0.1, atol=1e-9)


def start_decoder(tmp_path, port, *extra):
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    return subprocess.Popen([sys.executable, "-m", "ground.decode", f"udpin:127.0.0.1:{port}", "--quiet",
                             "--csv", str(tmp_path / "live.csv"), "--tlog", str(tmp_path / "live.tlog"), *extra],
                            cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def send_until(sock, port, box, t0, pred, timeout_s=60.0):
    """Send a sample every 20 ms until pred() holds; the samples sent."""
    sent = 0
    deadline = time.monotonic() + timeout_s
    while not pred():
        assert time.monotonic() < deadline, "the decoder never wrote"
        sock.sendto(box.sample(t0 + 0.1 * box.seq), ("127.0.0.1", port))
        sent += 1
        time.sleep(0.02)
    return sent


def rows(path: Path) -> int:
    try:
        return sum(1 for line in path.read_text().splitlines() if line and line[0].isdigit())
    except FileNotFoundError:
        return 0


@pytest.mark.parametrize("how", [signal.SIGKILL, signal.SIGTERM])
def test_a_live_recording_survives_kill_and_terminate(tmp_path, how):
    port = free_udp_port()
    proc = start_decoder(tmp_path, port)
    box = Box()
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        try:
            send_until(sock, port, box, 0.0, lambda: rows(tmp_path / "live.csv") >= 20)
            last = box.seq
            time.sleep(0.5)                          # the last frames are in (UDP on loopback)
            proc.send_signal(how)
            out, err = proc.communicate(timeout=30)
        finally:
            proc.kill()
    rec = read_recording(tmp_path / "live.csv")    # readable, whatever the signal
    assert len(rec) >= 20 and (np.diff(rec.t_s) > 0).all()
    if how == signal.SIGTERM:
        assert proc.returncode == 0 and "terminated" in out and "Traceback" not in err
        seq0 = int(round(rec.t_s[0] * 10))         # the first sample the decoder was up for
        np.testing.assert_allclose(rec.t_s, np.arange(seq0, last) * 0.1, atol=1e-6)   # every one after it
        assert f"wrote recording: {tmp_path / 'live.csv'}" in out


def test_nothing_received_is_said_and_no_file_written(tmp_path, capsys):
    port = free_udp_port()
    rc = main([f"udpin:127.0.0.1:{port}", "--duration", "0.5", "--csv", str(tmp_path / "x.csv"), "--quiet"])
    assert rc == 1 and "nothing received" in capsys.readouterr().err
    assert not (tmp_path / "x.csv").exists()


def test_a_missing_file_is_named_not_taken_for_a_port(tmp_path, capsys):
    rc = main([str(tmp_path / "nope.tlog"), "--csv", str(tmp_path / "x.csv")])
    err = capsys.readouterr().err
    assert rc == 1 and "no such file" in err and "could not open port" not in err
    rc = main(["/dev/ttyNOPE9", "--csv", str(tmp_path / "x.csv")])
    assert rc == 1 and "no such serial device" in capsys.readouterr().err
