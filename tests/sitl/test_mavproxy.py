"""Stock MAVProxy (the registry's, `mavproxy.py` beside the interpreter) against a SITL box, driven as an
operator would type it: it sees the box online, lists its parameters, signs with the key a passphrase
makes (`signing key PASSPHRASE`; the box's key file from `python -m ground.keys from-passphrase`), sets
a parameter and commands the box, which answers ACCEPTED. MAVProxy runs with the project's dialect
(`--dialect debris`, the bindings where pymavlink looks for dialects: docs/ground.md)."""
from __future__ import annotations

import os
import queue
import re
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from support import free_udp_port, pymavlink_with_debris

pytestmark = [pytest.mark.sitl, pytest.mark.slow]  # ~40 s: MAVProxy's start, the box's, the parameter fetch

ROOT = Path(__file__).resolve().parents[2]
MAVPROXY = Path(sys.executable).with_name("mavproxy.py")
PASSPHRASE = "tumbling-debris-2026"
DIALECT = os.environ.get("TEST_MAVPROXY_DIALECT", "debris")   # (another: to see what it changes)
WAIT_S = 120.0      # for each answer (a loaded machine: MAVProxy alone takes ~10 s to start)


class Console:
    """MAVProxy's console: commands written to its stdin, its output read line by line in a thread."""

    def __init__(self, proc: subprocess.Popen) -> None:
        self.proc, self.lines, self.seen = proc, queue.Queue(), []
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        for line in self.proc.stdout:
            self.lines.put(line.rstrip("\n"))

    def send(self, command: str) -> None:
        self.proc.stdin.write(command + "\n")
        self.proc.stdin.flush()

    def expect(self, text: str) -> str:
        """The first line from now on that holds `text` (fails after WAIT_S, showing what came)."""
        deadline = time.monotonic() + WAIT_S
        while time.monotonic() < deadline:
            try:
                line = self.lines.get(timeout=0.2)
            except queue.Empty:
                if self.proc.poll() is not None:
                    break
                continue
            self.seen.append(line)
            if text in line:
                return line
        raise AssertionError(f"MAVProxy never said {text!r}; it said:\n" + "\n".join(self.seen[-40:]))


def after(line: str, label: str) -> str:
    """The word after `label` in a console line."""
    return line.split(label, 1)[1].split()[0]


@pytest.mark.skipif(not MAVPROXY.exists(),
                    reason="MAVProxy is not installed (make test-slow installs it: pip install -e '.[tools]')")
def test_stock_mavproxy_sees_lists_signs_and_commands_the_box(tmp_path):
    key = tmp_path / "mission.key"
    made = subprocess.run([sys.executable, "-m", "ground.keys", "from-passphrase", str(key)], cwd=ROOT,
                          input=PASSPHRASE + "\n", capture_output=True, text=True, timeout=120)
    assert made.returncode == 0, made.stderr
    port = free_udp_port()
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(pymavlink_with_debris(tmp_path / "py")), str(ROOT)]))
    box = subprocess.Popen([sys.executable, "-m", "hil.sitl", "--quiet", "--duration", "600", "--key", str(key),
                            "--link", f"udpout:127.0.0.1:{port}"], cwd=ROOT, env=env,
                           stdout=subprocess.DEVNULL, stderr=(tmp_path / "box.err").open("w"))
    mavproxy = subprocess.Popen([sys.executable, str(MAVPROXY), f"--master=udpin:127.0.0.1:{port}",
                                 f"--dialect={DIALECT}", "--no-state", "--nowait"],
                                cwd=tmp_path, env=env, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                stderr=subprocess.STDOUT, text=True, bufsize=1)
    console = Console(mavproxy)
    try:
        console.expect("Detected vehicle 1:191")
        console.expect("online system 1")                   # a vehicle, not just a MAVLink node
        console.send(f"signing key {PASSPHRASE}")      # (not `signing setup`: docs/ground.md)
        console.expect("Setup signing key")
        console.send("param fetch")
        assert after(console.expect("Received "), "Received") == "4"   # "Received 4 parameters"
        console.send("param show TLM_SAMPLE_HZ")
        assert after(console.expect("TLM_SAMPLE_HZ"), "TLM_SAMPLE_HZ") == "1.0"   # (after MAVProxy's prompt)
        # changes need the key: a parameter set and a message rate, each answered by the box
        console.send("param set TLM_SAMPLE_HZ 0.5")
        deadline = time.monotonic() + WAIT_S
        while True:                                         # read back until the box has taken it
            console.send("param fetch TLM_SAMPLE_HZ")
            value = float(after(console.expect("TLM_SAMPLE_HZ = "), "TLM_SAMPLE_HZ ="))
            if value == 0.5 or time.monotonic() > deadline:
                break
            time.sleep(0.5)
        assert value == 0.5
        console.send("long SET_MESSAGE_INTERVAL 1 500000")   # SYS_STATUS every 0.5 s
        assert console.expect("Got COMMAND_ACK: SET_MESSAGE_INTERVAL") \
            .endswith("SET_MESSAGE_INTERVAL: ACCEPTED")
        console.send("long NAV_TAKEOFF")                     # what the box cannot do: said, not silence
        assert console.expect("Got COMMAND_ACK: NAV_TAKEOFF").endswith("NAV_TAKEOFF: UNSUPPORTED")
        # with the dialect MAVProxy counts every frame's sequence number: no loss on a local link (without
        # it, the DEBRIS_ messages it cannot decode read as lost)
        console.send("link")
        status = re.search(r"\((\d+) packets, .*, (\d+) lost, ([\d.]+)% loss", console.expect("% loss"))
        assert status is not None and int(status[1]) > 10 and int(status[2]) == 0, status
    finally:
        for proc in (mavproxy, box):
            proc.kill()
            proc.wait(timeout=60)
    assert "Traceback" not in "\n".join(console.seen)
