"""The service: `fsw.main` under a stand-in for systemd (a real unix datagram socket as $NOTIFY_SOCKET)
says READY once its loop runs, feeds the watchdog from the loop's heartbeat and says STOPPING; the unit
shipped in deploy/ has what is asked of it."""
import configparser
import shutil
import socket
import subprocess
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import smbus2

from fsw import main as fsw_main
from hil.linux_buses import smbus_factory
from hil.mmc5983ma import EmulatedMmc5983ma
from support import free_udp_port

ROOT = Path(__file__).resolve().parents[2]
UNIT = ROOT / "deploy" / "debris-box.service"


def test_fsw_main_notifies_systemd_and_feeds_the_watchdog(tmp_path, monkeypatch, capsys):
    t0 = time.monotonic()
    chip = EmulatedMmc5983ma(lambda t: np.array([20e-6, -5e-6, 45e-6]), lambda: time.monotonic() - t0,
                             np.random.default_rng(5))
    monkeypatch.setattr(smbus2, "SMBus", smbus_factory(chip))
    path = str(tmp_path / "notify")
    systemd = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    systemd.bind(path)
    received = []
    stop = threading.Event()

    def listen():  # systemd reads its socket as datagrams come
        systemd.settimeout(0.05)
        while not stop.is_set():
            try:
                received.append((time.monotonic(), systemd.recv(4096).decode()))
            except socket.timeout:
                pass
    th = threading.Thread(target=listen)
    th.start()
    monkeypatch.setenv("NOTIFY_SOCKET", path)
    monkeypatch.setenv("WATCHDOG_USEC", "400000")  # 0.4 s: fed every 0.2 s of loop time
    try:
        status = fsw_main.main(["--mag-i2c", "/dev/i2c-1", "--link", f"udpout:127.0.0.1:{free_udp_port()}",
                                "--rate", "100", "--sample-rate", "50", "--duration", "3", "--quiet"])
    finally:
        time.sleep(0.1)
        stop.set()
        th.join()
        systemd.close()
    assert status == 0
    msgs = [m for _, m in received]
    assert msgs[0] == "READY=1\nSTATUS=flying" and msgs[-1] == "STOPPING=1\nSTATUS=stopping"
    feeds = [t for t, m in received if m == "WATCHDOG=1"]
    assert 13 <= len(feeds) <= 17                    # 3 s of loop time / 0.2 s, +1 at the start
    assert "magnetometer: " in capsys.readouterr().out


def test_the_unit_file():
    unit = configparser.ConfigParser(strict=False, interpolation=None)
    unit.optionxform = str
    unit.read(UNIT)
    service = unit["Service"]
    assert service["Type"] == "notify" and service["Restart"] == "on-failure"
    assert float(service["WatchdogSec"]) > 0 and service["RestartPreventExitStatus"] == "2"
    assert service["User"] not in ("", "root") and {"i2c", "gpio"} <= set(service["SupplementaryGroups"].split())
    assert "-m fsw.main --config /etc/debris-box/box.toml" in service["ExecStart"]
    assert service["StateDirectory"] == "debris-box"          # /var/lib/debris-box, deploy/box.toml's state_dir
    assert unit["Install"]["WantedBy"] == "multi-user.target"


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="no systemd-analyze here")
def test_systemd_accepts_the_unit():
    r = subprocess.run(["systemd-analyze", "verify", str(UNIT)], capture_output=True, text=True, timeout=60)
    problems = [line for line in (r.stdout + r.stderr).splitlines()
                if line.strip() and "/opt/debris-box/venv/bin/python" not in line]  # not installed here
    assert problems == []


@pytest.mark.skipif(shutil.which("make") is None, reason="no make here")
def test_make_install_target_is_spelled_out():
    r = subprocess.run(["make", "-n", "install-target"], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    for step in ("useradd", "pip install", "'.[target]'", "deploy/debris-box.service", "daemon-reload"):
        assert step in r.stdout
