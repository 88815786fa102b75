"""A restart of the box on target: `fsw.main --state-dir` is killed (SIGKILL) after it accepted signed
commands and a time set, and started again: the commands replayed are refused, the time is back, the host
calibration and the inertia estimate it had are applied and sent again."""
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from fsw.estimation import magcal as mc
from fsw.state_files import save_state
from fsw.telemetry.dialect import FSW_SYSID, mavlink
from fsw.telemetry.signing import SigningClock, write_key
from ground.command import GroundLink
from hil.mmc5983ma import EmulatedMmc5983ma
from hil.pty_link import PtyBridge
from support import free_udp_port

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


def downlinked(sock) -> list:
    parser = mavlink.MAVLink(None)
    out = []
    while True:
        try:
            data = sock.recv(65536)
        except socket.timeout:
            return out
        out += parser.parse_buffer(data) or []


@pytest.mark.slow  # two start-ups of the flight software in their own processes
def test_killed_and_started_again(tmp_path):
    key = tmp_path / "mission.key"
    write_key(key, KEY)
    state = tmp_path / "state"
    state.mkdir()
    seed_results(state)
    down = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    down.bind(("127.0.0.1", 0))
    down.settimeout(0.5)
    t0 = time.monotonic()
    emu = EmulatedMmc5983ma(lambda t: np.array([20e-6, -5e-6, 45e-6]), lambda: time.monotonic() - t0,
                            np.random.default_rng(5))
    up = free_udp_port()
    ground = Ground(up)
    with PtyBridge(emu, rng=np.random.default_rng(6)) as bridge:
        box = start_box(bridge, key, state, up)
        try:
            ground.command_until_acked()
            utc_us = int(time.time() * 1e6)
            ground.sent.append(ground.link.send(mavlink.MAVLink_system_time_message(utc_us, 0), 0.0))
            time.sleep(1.0)
            assert (state / "signing.json").exists() and (state / "time.json").exists()
        finally:
            box.send_signal(signal.SIGKILL)
            box.wait(timeout=30)
        assert box.returncode == -signal.SIGKILL
        old = list(ground.sent)
        while _pending(ground.sock):  # the first box's answers
            pass
        box = start_box(bridge, key, state, up, down.getsockname()[1])
        probe = Ground(up, link_id=1)  # another signing stream: the replayed one's newest stays the saved one
        try:
            probe.command_until_acked()                # the new box is up and takes a new command
            for frame in old:                          # every frame the first box was sent, replayed
                ground.sock.sendto(frame, ("127.0.0.1", up))
            time.sleep(1.0)
            sent = downlinked(down)
        finally:
            box.send_signal(signal.SIGTERM)
            out, err = box.communicate(timeout=60)
            down.close()
    assert box.returncode == 0, err
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
