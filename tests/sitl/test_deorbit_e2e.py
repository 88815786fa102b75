"""End to end: the de-orbit kit commanded from the ground's command-line tool (`python -m ground.command`,
signed COMMAND_LONG → COMMAND_ACK) against SITL (`fsw.main --scenario amds_deorbit`: simulator, kit
emulator, flight software) over UDP, the kit's telemetry (DEBRIS_DEORBIT_STATUS, STATUSTEXT) received
and verified on the ground."""
import io
import socket
import threading
import time

import pytest

from hil import sitl
from fsw.telemetry.dialect import mavlink
from fsw.telemetry.signing import Verdict, write_key
from ground import command as ground_command
from ground.command import Session

pytestmark = pytest.mark.sitl

KEY = bytes(range(7, 39))


def free_udp_port():
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def key_file(tmp_path):
    path = tmp_path / "mission.key"
    write_key(path, KEY)
    return str(path)


def test_kit_commands_from_the_ground_tool_and_its_telemetry(key_file, capsys):
    tlm_port, up_port = free_udp_port(), free_udp_port()
    listener = Session(f"udpin:127.0.0.1:{tlm_port}", KEY)
    frames, stop = [], threading.Event()

    def listen():
        while not stop.is_set():
            frames.extend(listener.receive())
            time.sleep(0.01)

    rx = threading.Thread(target=listen)
    rx.start()
    args = sitl.parse_args(["--scenario", "amds_deorbit", "--rate", "10", "--speed", "5",
                                "--duration", "30", "--quiet", "--key", key_file,
                                "--link", f"udpout:127.0.0.1:{tlm_port}", "--uplink", f"udpin:127.0.0.1:{up_port}"])
    out = {}
    box = threading.Thread(target=lambda: out.setdefault("run", sitl.run(args, out=io.StringIO())))
    box.start()
    url = f"udpout:127.0.0.1:{up_port}"

    def send(*words):
        return ground_command.main([url, "--key", key_file, *words, "--timeout", "0.5"])

    try:
        t_end = time.monotonic() + 20.0
        while not frames and time.monotonic() < t_end:  # the box is up when its telemetry arrives
            time.sleep(0.05)
        assert send("capsule", "channel=0", "open=1") == 1  # FAILED: the magnet is not homed yet
        assert send("magnet_home", "channel=0") == 0
        assert send("magnet_home", "channel=1") == 0
        time.sleep(0.8)  # 4 s of loop time: both homed
        assert send("capsule", "channel=0", "open=1") == 0
        assert send("magnet_turn", "channel=0", "angle=180") == 1  # TEMPORARILY_REJECTED: capsule not closed
        assert send("magnet_polarity", "channel=1", "polarity=0") == 1  # DENIED
        assert send("magnet_turn", "channel=1", "angle=1") == 1  # DENIED: not a whole step
        assert send("magnet_polarity", "channel=1", "polarity=-1") == 0
        time.sleep(0.8)
        assert send("safe_mode", "enter=1") == 0
        assert send("capsule", "channel=1", "open=1") == 1  # FAILED in safe mode
        time.sleep(0.4)
        assert send("safe_mode", "enter=0") == 0
        assert send("controller", "run=1") == 0
        assert ground_command.main([url, "capsule", "channel=0", "open=0", "--retries", "0",
                                    "--timeout", "0.3"]) == 3  # unsigned: ignored
        time.sleep(1.0)
    finally:
        box.join()
        time.sleep(0.3)
        stop.set()
        rx.join()
        listener.close()
    text = capsys.readouterr().out
    for result in ("ACCEPTED", "TEMPORARILY_REJECTED", "DENIED", "FAILED"):
        assert result in text
    run = out["run"]
    kit = run.fsw.apps["deorbit"]
    assert kit is not None and kit.sequencer.interlock_violations == 0
    assert run.fsw.uplink.counters.unsigned == 1
    # the ground saw the kit: signed, verified status and transitions
    assert frames and all(f.verdict is Verdict.OK for f in frames)
    status = [f.msg for f in frames if f.msg.get_type() == "DEBRIS_DEORBIT_STATUS"]
    texts = [f.msg.text for f in frames if f.msg.get_type() == "STATUSTEXT"]
    assert len(status) >= 25
    assert any(s.capsule_state[0] == mavlink.DEBRIS_CAPSULE_STATE_OPEN for s in status)
    assert any(s.polarity[1] == -1 for s in status)
    assert any(s.controller_state == mavlink.DEBRIS_CONTROLLER_STATE_SAFE for s in status)
    assert status[-1].controller_state == mavlink.DEBRIS_CONTROLLER_STATE_RUNNING
    assert all(s.interlock_violations == 0 for s in status)
    assert status[-1].capsule_openings[0] >= 1 and status[-1].energy[0] > 0
    assert any("deorbit pitch capsule CLOSED->OPENING" in t for t in texts)
    assert any("mode RUNNING->SAFE" in t or "mode OFF->SAFE" in t for t in texts)
