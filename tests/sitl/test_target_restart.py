"""A restart of the box on target: `fsw.main --state-dir` is killed (SIGKILL) after it accepted signed
commands, a time set and a TLE, and started again: the commands replayed are refused, the time and the TLE
are back (and the TLE in use), the host calibration and the inertia estimate it had are applied and sent
again, the samples the first run took while nobody received them are sent when the ground asks for
them, and a torn TLE file the first run found was refused, never used."""
import signal
import socket
import subprocess
import sys
import time
from datetime import datetime, timedelta, timezone
from pathlib import Path

import numpy as np
import pytest

from fsw.estimation import magcal as mc
from fsw.state_files import save_state
from fsw.telemetry.dialect import FSW_COMPID, FSW_SYSID, mavlink
from fsw.telemetry.sample_store import _HEADER, _RECORD
from fsw.telemetry.signing import SigningClock, write_key
from ground.command import GroundLink
from hil.mmc5983ma import EmulatedMmc5983ma
from hil.pty_link import PtyBridge
from fsw.timeorbit import tle_crc
from support import circular_tle, free_udp_port, tle_epoch_field

ROOT = Path(__file__).resolve().parents[2]
KEY = bytes(range(7, 39))


class Ground:
    def __init__(self, port: int, link_id: int = 0) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.2)
        self.port = port
        self.link = GroundLink(lambda b: self.sock.sendto(b, ("127.0.0.1", port)), key=KEY,
                               clock=SigningClock(clock_set=True, unix_time=time.time), link_id=link_id)
        self.sent: list[bytes] = []

    def acked(self) -> bool:
        try:
            data = self.sock.recv(4096)
        except socket.timeout:
            return False
        return any(r.msg.get_type() == "COMMAND_ACK" for r in self.link.feed(data, 0.0))  # signed, verified

    def ack(self, command: int, limit_s: float = 20.0) -> int:
        """The result of the box's COMMAND_ACK of `command` (signed, verified)."""
        deadline = time.monotonic() + limit_s
        while time.monotonic() < deadline:
            try:
                data = self.sock.recv(4096)
            except socket.timeout:
                continue
            for r in self.link.feed(data, 0.0):
                if r.msg.get_type() == "COMMAND_ACK" and r.msg.command == command:
                    return r.msg.result
        raise AssertionError(f"no COMMAND_ACK of {command}")

    def command_until_acked(self, limit_s: float = 120.0) -> None:
        deadline = time.monotonic() + limit_s
        while time.monotonic() < deadline:
            self.sent.append(self.link.command_long(mavlink.MAV_CMD_REQUEST_MESSAGE, [1], 0.0))
            for _ in range(3):
                if self.acked():
                    return
        raise AssertionError("the box never answered")


def _pending(sock) -> bool:
    """Drop one datagram still waiting on `sock`; False when there is none."""
    try:
        sock.recv(4096)
    except socket.timeout:
        return False
    return True


def start_box(bridge, key, state, up, down=None):
    return subprocess.Popen([sys.executable, "-m", "fsw.main", "--mag-serial", bridge.port_name, "--key", str(key),
                             "--state-dir", str(state), "--link", f"udpout:127.0.0.1:{down or free_udp_port()}",
                             "--uplink", f"udpin:127.0.0.1:{up}", "--quiet"],
                            cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


HARD_IRON_UT = np.array([6.0, -9.0, 4.0])
INERTIA = [180.0, 220.0, 260.0, 1.5, -2.0, 0.7]


def seed_results(state: Path) -> None:
    """What an earlier run of this box left: a host calibration (its drift's terms, no UTC then) and an
    inertia estimate, as `fsw.persist` writes them."""
    theta = np.concatenate([HARD_IRON_UT, [0.02, -0.01, 0.03, 0.0, 0.0, 0.0], [0.5, -0.4, 0.6, 0.1, 0.2, -0.1]])
    D = mc._sym(theta[3:9])
    cov = np.diag([0.05e-6 ** 2] * 3 + [1e-4 ** 2] * 6)
    save_state(state / "calibration.json", "calibration", {"system_id": FSW_SYSID, "snapshot": {
        "theta_uT": theta.tolist(), "b_T": (HARD_IRON_UT * 1e-6).tolist(), "D": D.tolist(), "cov": cov.tolist(),
        "published_at_s": 3000.0, "drift_period_s": 5670.0, "state": mc.CONVERGED}})
    save_state(state / "ident.json", "ident", {"system_id": FSW_SYSID, "snapshot": {
        "samples": 4321, "inertia": INERTIA, "ci95": [4.0] * 6, "ci99": [5.0] * 6, "state": 4, "flags": 7,
        "cov": np.diag([4.0] * 6).tolist()}})


def stored_samples(path: Path) -> np.ndarray:
    """The samples a (killed) box's sample store file counts, read as they are on disk."""
    head = np.fromfile(path, dtype=_HEADER, count=1)[0]
    return np.fromfile(path, dtype=_RECORD, count=int(head["next_seq"]), offset=_HEADER.itemsize)


def downlinked_until(sock, done, limit_s: float) -> list:
    """The box's telemetry on `sock` until `done(messages)` or `limit_s`."""
    parser = mavlink.MAVLink(None)
    out: list = []
    deadline = time.monotonic() + limit_s
    while time.monotonic() < deadline and not done(out):
        try:
            out += parser.parse_buffer(sock.recv(65536)) or []
        except socket.timeout:
            pass
    return out


def downlinked(sock) -> list:
    parser = mavlink.MAVLink(None)
    out = []
    while True:
        try:
            data = sock.recv(65536)
        except socket.timeout:
            return out
        out += parser.parse_buffer(data) or []


MIN_FIRST_RUN_SAMPLES = 4


@pytest.mark.slow  # two start-ups of the flight software in their own processes
def test_killed_and_started_again(tmp_path):
    key = tmp_path / "mission.key"
    write_key(key, KEY)
    state = tmp_path / "state"
    state.mkdir()
    seed_results(state)
    l1, l2 = circular_tle(epoch=tle_epoch_field(datetime.now(timezone.utc) - timedelta(days=1)))
    (state / "tle.txt").write_text(f"{l1}\n{l2[:40]}")  # what a crash while it was written left: cut short
    down = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    down.bind(("127.0.0.1", 0))
    down.settimeout(0.5)
    t0 = time.monotonic()
    emu = EmulatedMmc5983ma(lambda t: np.array([20e-6, -5e-6, 45e-6]), lambda: time.monotonic() - t0,
                            np.random.default_rng(5))
    up = free_udp_port()
    ground = Ground(up)
    with PtyBridge(emu, rng=np.random.default_rng(6)) as bridge:
        box = start_box(bridge, key, state, up)  # its telemetry goes to a port nobody reads
        try:
            ground.command_until_acked()
            utc_us = int(time.time() * 1e6)
            ground.sent.append(ground.link.send(mavlink.MAVLink_system_time_message(utc_us, 0), 0.0))
            ground.sent.append(ground.link.send(mavlink.MAVLink_debris_tle_message(
                FSW_SYSID, FSW_COMPID, l1.encode("latin-1"), l2.encode("latin-1")), 0.0))
            ground.sent.append(ground.link.command_long(mavlink.MAV_CMD_DEBRIS_TLE_LOAD, [float(tle_crc(l1, l2))], 0.0))
            assert ground.ack(mavlink.MAV_CMD_DEBRIS_TLE_LOAD) == mavlink.MAV_RESULT_ACCEPTED
            deadline = time.monotonic() + 30.0
            while len(stored_samples(state / "samples.store")) < MIN_FIRST_RUN_SAMPLES:
                assert time.monotonic() < deadline, "the first run stored no samples"
                time.sleep(0.2)
            time.sleep(1.0)
            assert (state / "signing.json").exists() and (state / "time.json").exists()
        finally:
            box.send_signal(signal.SIGKILL)
            box.wait(timeout=30)
        assert box.returncode == -signal.SIGKILL
        first_out = box.stdout.read()
        box.stdout.close()
        box.stderr.close()
        first = stored_samples(state / "samples.store")   # what the killed run left on disk
        assert (state / "tle.txt").read_text() == f"{l1}\n{l2}\n"   # the torn file replaced by the TLE put in force
        old = list(ground.sent)
        while _pending(ground.sock):  # the first box's answers
            pass
        box = start_box(bridge, key, state, up, down.getsockname()[1])
        probe = Ground(up, link_id=1)  # another signing stream: the replayed one's newest stays the saved one
        n = len(first)

        def all_resent(msgs) -> bool:
            return {m.seq for m in msgs if m.get_type() == "DEBRIS_MAG_SAMPLE" and m.seq < n} == set(range(n))
        try:
            probe.command_until_acked()                # the new box is up and takes a new command
            for frame in old:                          # every frame the first box was sent, replayed
                ground.sock.sendto(frame, ("127.0.0.1", up))
            # the ground asks for the first run's samples, which nobody received
            probe.link.send(mavlink.MAVLink_debris_sample_request_message(FSW_SYSID, FSW_COMPID, 0, n), 0.0)
            sent = downlinked_until(down, all_resent, 20.0)
            time.sleep(1.0)
            sent += downlinked(down)
        finally:
            box.send_signal(signal.SIGTERM)
            out, err = box.communicate(timeout=60)
            down.close()
    assert box.returncode == 0, err
    # the torn TLE file was refused by the first run, never used
    assert f"TLE file {state / 'tle.txt'}: not a valid TLE" in first_out and "no TLE on board" in first_out
    # the calibration and the inertia estimate survived the SIGKILL, applied and sent again
    assert "calibration: restored from before the restart (its drift's terms dropped (no UTC before and after))" \
        in out
    assert "ident: restored from before the restart (applied)" in out
    magcal = [m for m in sent if m.get_type() == "DEBRIS_MAGCAL"]
    assert magcal and all(m.restored == mc.RESTORED for m in magcal)
    np.testing.assert_allclose(magcal[0].hard_iron, HARD_IRON_UT, atol=1e-4)
    ident = [m for m in sent if m.get_type() == "DEBRIS_INERTIA_ESTIMATE"]
    assert ident and ident[0].samples == 4321 and ident[0].state == 4
    np.testing.assert_allclose(ident[0].inertia, INERTIA, rtol=1e-6)
    assert "signing state: 1 command streams restored" in out
    assert "time: restored from before the restart (same boot)" in out
    uplink = next(line for line in out.splitlines() if line.startswith("uplink:"))
    replayed = int(uplink.split(" replayed")[0].rsplit(" ", 1)[-1])
    assert replayed >= len(old), uplink
    assert "time and orbit: UTC" in out
    # the TLE survived the SIGKILL: read back, sent down with the same lines, in use (the time is back too)
    assert f"TLE from {state / 'tle.txt'}: satellite 99999" in out
    tle = [m for m in sent if m.get_type() == "DEBRIS_TLE"]
    assert tle and all((m.line1, m.line2) == (l1, l2) for m in tle)
    orbit = [m for m in sent if m.get_type() == "DEBRIS_TIME_ORBIT"]
    assert orbit and orbit[-1].tle_state == mavlink.DEBRIS_TLE_STATE_OK and orbit[-1].tle_persisted == 1
    assert orbit[-1].tle_loaded == 0 and orbit[-1].tle_refused == 0   # from the file, not from the replay
    # the first run's samples, sent to nobody, delivered after the restart as the first run stored them
    assert n >= MIN_FIRST_RUN_SAMPLES and (first["seq"] == np.arange(n)).all()
    store = [m for m in sent if m.get_type() == "DEBRIS_SAMPLE_STORE"]
    assert store and store[-1].run_first_seq >= n and store[-1].stored_first_seq == 0
    resent = {m.seq: m for m in sent if m.get_type() == "DEBRIS_MAG_SAMPLE" and m.seq < n}
    assert sorted(resent) == list(range(n))
    assert all(m.run_id == int(first["run_id"][0]) != store[-1].run_id for m in resent.values())
    np.testing.assert_allclose([resent[k].mag for k in range(n)], first["b_T"] * 1e4, atol=1e-6)  # gauss
    np.testing.assert_allclose([resent[k].time_usec for k in range(n)], first["t_us"], atol=0)
    live = [m.seq for m in sent if m.get_type() == "DEBRIS_MAG_SAMPLE" and m.run_id == store[-1].run_id]
    assert live and min(live) >= store[-1].run_first_seq
