"""`fsw.main --config box.toml` on target: the box's file with the command line over it; the magnetometer
through the real smbus2 code path and the de-orbit kit through gpiod's request API, both answered by the
emulators (`hil.linux_buses`, `hil.gpiod_fake`); the kit's lines left at their safe levels and released
after SIGTERM and after an exception in the loop."""
import io
import os
import signal
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import smbus2

from fsw import main as fsw_main
from fsw.box_config import load_box_config
from fsw.drivers import gpiod_lines
from fsw.drivers.gpiod_lines import SAFE_LEVELS
from fsw.flight import FlightSoftware
from fsw.telemetry.signing import write_key
from hil.deorbit_kit import DeorbitKitEmulator
from hil.gpiod_fake import FakeGpiod
from hil.linux_buses import smbus_factory
from hil.mmc5983ma import EmulatedMmc5983ma
from support import free_udp_port

EXAMPLE = Path(__file__).resolve().parents[2] / "deploy" / "box.toml"
SAFE = {f"{c}.{k}": level for c in "01" for k, level in SAFE_LEVELS.items()}


@pytest.fixture
def box(tmp_path, monkeypatch):
    """The shipped example with this machine's paths, the chip and the kit emulated behind the libraries."""
    write_key(tmp_path / "mission.key", bytes(range(1, 33)))
    (tmp_path / "state").mkdir()
    text = EXAMPLE.read_text().replace("/etc/debris-box/mission.key", "mission.key") \
        .replace("/var/lib/debris-box", "state") \
        .replace('port = "/dev/serial0"', f'port = "udpout:127.0.0.1:{free_udp_port()}"')
    path = tmp_path / "box.toml"
    path.write_text(text)
    t0 = time.monotonic()
    chip = EmulatedMmc5983ma(lambda t: np.array([20e-6, -5e-6, 45e-6]), lambda: time.monotonic() - t0,
                             np.random.default_rng(5))
    smbuses = []
    monkeypatch.setattr(smbus2, "SMBus", smbus_factory(chip, opened=smbuses))
    lines = load_box_config(str(path)).kit.lines
    fake = FakeGpiod(DeorbitKitEmulator(), {chip_line: logical for logical, chip_line in lines.items()})
    monkeypatch.setitem(sys.modules, "gpiod", fake)
    made = []

    class Recorded(gpiod_lines.GpiodLines):
        def __init__(self, *a, **kw):
            super().__init__(*a, **kw)
            made.append(self)
    monkeypatch.setattr(gpiod_lines, "GpiodLines", Recorded)
    return str(path), tmp_path, smbuses, fake, made


def test_the_file_and_the_command_line_over_it(box):
    path, tmp, *_ = box
    cfg, mag, kit = fsw_main.parse_args(["--config", path])
    assert (cfg.rate_hz, cfg.sample_rate_hz, cfg.system_id, cfg.baud) == (100, 50, 1, 57600)
    assert cfg.key_file == str(tmp / "mission.key") and cfg.link.startswith("udpout:127.0.0.1:")
    assert cfg.tle_file == str(tmp / "state" / "tle.txt") and cfg.sample_store == str(tmp / "state" / "samples.store")
    assert (mag.kind, mag.device, mag.i2c_address) == ("i2c", "/dev/i2c-1", 0x30) and kit.chip == "/dev/gpiochip0"
    cfg, mag, _ = fsw_main.parse_args(["--config", path, "--rate", "200", "--system-id", "7", "--mag-serial",
                                       "/dev/ttyUSB0", "--tle-file", str(tmp / "other.tle")])
    assert (cfg.rate_hz, cfg.sample_rate_hz, cfg.system_id) == (200, 50, 7)
    assert (mag.kind, mag.device) == ("serial", "/dev/ttyUSB0") and cfg.tle_file == str(tmp / "other.tle")


@pytest.mark.parametrize("edit, words", [
    (("rate_hz = 100", "rate_hz = 0"), ["[loop] rate_hz", "box.toml"]),
    (("system_id = 1", "system_id = 300"), ["system_id", "255"]),
    (('bus = "i2c"', 'bus = "usb"'), ["[magnetometer] bus"]),
    (("mission.key", "missing.key"), ["key_file"]),
    (('state_dir = "state"', 'state_dir = "nowhere"'), ["--state-dir", "not a directory"]),
])
def test_a_bad_file_is_one_line_and_exit_2(box, capsys, edit, words):
    path = box[0]
    Path(path).write_text(Path(path).read_text().replace(*edit))
    with pytest.raises(SystemExit) as e:
        fsw_main.main(["--config", path, "--quiet"])
    err = capsys.readouterr().err
    assert e.value.code == 2 and "Traceback" not in err
    for w in words:
        assert w in err.strip().splitlines()[-1]


def test_no_gpiod_is_one_line(box, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "gpiod", None)
    with pytest.raises(SystemExit) as e:
        fsw_main.main(["--config", box[0], "--quiet"])
    assert e.value.code == 2 and "gpiod" in capsys.readouterr().err.strip().splitlines()[-1]


def drive_the_kit_then(made, smbuses, action):
    """Once the loop is sampling: the kit's drivers mid-motion (winding on, shutter motor on, bursts of
    steps queued), then `action()`."""
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and not (smbuses and sum(len(t) == 2 for t in smbuses[0].log) > 20):
        time.sleep(0.05)
    lines = made[0]
    lines.write_output("0.enable", True)
    lines.write_output("1.shutter_release", False)
    lines.write_output("1.shutter_drive", True)
    for _ in range(4):
        lines.pulse_output("0.step", 12)  # 0.4 s of steps queued
    time.sleep(0.03)
    action()


def test_sigterm_leaves_the_kit_safe(box, capsys):
    path, _, smbuses, fake, made = box
    th = threading.Thread(target=drive_the_kit_then, args=(made, smbuses, lambda: os.kill(os.getpid(), signal.SIGTERM)))
    th.start()
    status = fsw_main.main(["--config", path, "--quiet", "--duration", "60"])
    th.join()
    assert status == 0
    out = capsys.readouterr().out
    assert "magnetometer: " in out and "de-orbit kit: " in out
    (req,) = fake.requests
    assert req.released and req.levels_at_release == SAFE
    kit = fake.kit.channels
    assert not kit[0].enable and not kit[1].drive and kit[1].release
    assert 0 < kit[0].pulses < 48                       # the bursts were cut short, not finished after the stop
    assert smbuses[0].closed


def test_an_exception_in_the_loop_leaves_the_kit_safe(box, monkeypatch):
    path, _, smbuses, fake, made = box
    tick = FlightSoftware.tick
    failing = threading.Event()

    def tick_or_fail(self, t):
        if failing.is_set():
            raise RuntimeError("a bug in the loop")
        return tick(self, t)
    monkeypatch.setattr(FlightSoftware, "tick", tick_or_fail)
    th = threading.Thread(target=drive_the_kit_then, args=(made, smbuses, failing.set))
    th.start()
    with pytest.raises(RuntimeError, match="a bug in the loop"):
        fsw_main.main(["--config", path, "--quiet", "--duration", "60"])
    th.join()
    (req,) = fake.requests
    assert req.released and req.levels_at_release == SAFE
    assert not fake.kit.channels[0].enable and fake.kit.channels[1].release and smbuses[0].closed


def test_the_mission_flies_on_target_from_the_kit_table(box, monkeypatch):
    """[kit.mission] in the box's file: the mission composed on target as in SITL — over the kit, the
    experiment's magnets the kit's, the flown rate filter its rates — ticked by the loop and reported."""
    from fsw.deorbit.mission import KitMagnets, Phase
    from fsw.telemetry.telemetry import Telemetry

    path, _, _, fake, _ = box
    with open(path, "a") as f:
        f.write("\n[kit.mission]\ninertia_guess_kgm2 = [18.0, 20.7, 15.3]\n")
    sent = []
    send = Telemetry._send

    def recording(self, msg):
        sent.append(msg.get_type())
        return send(self, msg)
    monkeypatch.setattr(Telemetry, "_send", recording)
    cfg, mag, kit = fsw_main.parse_args(["--config", path, "--quiet", "--duration", "4"])
    out = io.StringIO()
    fsw, _, _ = fsw_main.run(cfg, mag, kit, out=out)
    mission = fsw.apps["mission"]
    assert mission.rates is fsw.estimators["kalman"] and mission.phase is Phase.TUMBLING
    assert isinstance(fsw.apps["ident"].magnets, KitMagnets) and fsw.apps["ident"].magnets.kit is fsw.apps["deorbit"]
    assert mission.inertia_guess.tolist() == [18.0, 20.7, 15.3]
    assert sent.count("DEBRIS_MISSION_STATUS") >= 2
    assert "mission: from a tumble" in out.getvalue()
    (req,) = fake.requests
    assert req.released and req.levels_at_release == SAFE
