"""The box's configuration file (fsw.box_config): the shipped example read, every key checked with the key
named in one line."""
from pathlib import Path

import pytest

from fsw.box_config import BoxConfigError, load_box_config
from fsw.drivers.mag_bus import MagBus

EXAMPLE = Path(__file__).resolve().parents[2] / "deploy" / "box.toml"


def write(tmp_path, text):
    path = tmp_path / "box.toml"
    path.write_text(text)
    return str(path)


def test_the_shipped_example_is_a_whole_box():
    box = load_box_config(str(EXAMPLE))
    assert (box.system_id, box.key_file, box.state_dir) == (1, "/etc/debris-box/mission.key", "/var/lib/debris-box")
    assert (box.rate_hz, box.sample_rate_hz, box.link, box.baud) == (100, 50, "/dev/serial0", 57600)
    assert box.mag == MagBus("i2c", "/dev/i2c-1", 0x30)
    assert box.kit.chip == "/dev/gpiochip0" and box.kit.debounce_s == pytest.approx(0.005)
    assert sorted(box.kit.lines) == sorted(f"{c}.{k}" for c in "01" for k in (
        "step", "dir", "enable", "home", "shutter_drive", "shutter_release", "closed", "open"))
    assert box.defaults() == {"system_id": 1, "key": "/etc/debris-box/mission.key",
                              "state_dir": "/var/lib/debris-box", "rate": 100, "sample_rate": 50,
                              "link": "/dev/serial0", "baud": 57600, "rate_filter": "euler"}


def test_relative_paths_are_the_files_directory(tmp_path):
    box = load_box_config(write(tmp_path, 'key_file = "keys/m.key"\nstate_dir = "state"\n'
                                          '[magnetometer]\nbus = "spi"\ndevice = "/dev/spidev1.0"\n'))
    assert box.key_file == str(tmp_path / "keys" / "m.key") and box.state_dir == str(tmp_path / "state")
    assert box.mag == MagBus("spi", "/dev/spidev1.0", 0x30, 4_000_000) and box.kit is None


KIT = "[kit]\nchip = \"/dev/gpiochip0\"\n[kit.lines]\n\"0.step\" = 1\n"


def test_the_mission_on_the_kit(tmp_path):
    box = load_box_config(write(tmp_path, KIT + "[kit.mission]\ninertia_guess_kgm2 = [18, 20.7, 15.3]\n"))
    assert box.kit.mission_inertia_guess_kgm2 == (18.0, 20.7, 15.3)
    assert load_box_config(write(tmp_path, KIT)).kit.mission_inertia_guess_kgm2 is None


@pytest.mark.parametrize("text, words", [
    ("system_id = 0", ["system_id", "<= 255"]),
    ("system_id = 1.5", ["system_id", "integer"]),
    ("sytem_id = 1", ["sytem_id", "unknown key"]),
    ("[loop]\nrate_hz = 2000", ["[loop] rate_hz", "1000"]),
    ("[loop]\nrate_hz = \"fast\"", ["[loop] rate_hz", "number"]),
    ("[loop]\nsample_rate_hz = nan", ["[loop] sample_rate_hz", "finite"]),
    ("[loop]\nrat_hz = 10", ["[loop] rat_hz", "unknown key"]),
    ("[loop]\nrate_filter = \"best\"", ["[loop] rate_filter", "euler"]),
    ("[magnetometer]\ndevice = \"/dev/i2c-1\"", ["[magnetometer] bus", "missing"]),
    ("[magnetometer]\nbus = \"can\"\ndevice = \"x\"", ["[magnetometer] bus", "serial, i2c, spi"]),
    ("[magnetometer]\nbus = \"i2c\"\ndevice = \"\"", ["[magnetometer] device", "empty"]),
    ("[magnetometer]\nbus = \"spi\"\ndevice = \"/dev/i2c-1\"", ["[magnetometer] device", "spidev"]),
    ("[magnetometer]\nbus = \"i2c\"\ndevice = \"/dev/i2c-1\"\ni2c_address = 0x80", ["i2c_address", "119"]),
    ("[magnetometer]\nbus = \"spi\"\ndevice = \"/dev/spidev0.0\"\nspi_speed_hz = 20_000_000",
     ["spi_speed_hz", "10000000"]),
    ("[magnetometer]\nbus = \"i2c\"\ndevice = \"/dev/i2c-1\"\nspi_speed_hz = 1000", ["spi_speed_hz", "only for"]),
    ("[radio]\nport = \"udpout:host:99999\"", ["[radio] port"]),
    ("[radio]\nbaud = 0", ["[radio] baud"]),
    ("loop = 3", ["[loop]", "table"]),
    ("[kit]\n[kit.lines]\n\"0.step\" = \"GPIO17\"", ["[kit] chip", "missing"]),
    ("[kit]\nchip = \"/dev/gpiochip0\"", ["[kit] lines", "missing"]),
    ("[kit]\nchip = \"/dev/gpiochip0\"\n[kit.lines]\n\"2.step\" = \"GPIO17\"", ['[kit.lines] "2.step"']),
    ("[kit]\nchip = \"/dev/gpiochip0\"\n[kit.lines]\n\"0.step\" = 1\n\"0.dir\" = 1", ['"0.dir"', "two lines"]),
    ("[kit]\nchip = \"/dev/gpiochip0\"\n[kit.lines]\n\"0.step\" = true", ['"0.step"', "offset"]),
    ("[kit]\nchip = \"/dev/gpiochip0\"\ndebounce_ms = -1\n[kit.lines]\n\"0.step\" = 1", ["[kit] debounce_ms"]),
    ("system_id = ", ["not valid TOML"]),
    (KIT + "[kit.mission]\n", ["[kit.mission] inertia_guess_kgm2", "missing"]),
    (KIT + "[kit.mission]\ninertia_guess_kgm2 = [18.0, 20.7]", ["inertia_guess_kgm2", "three numbers"]),
    (KIT + "[kit.mission]\ninertia_guess_kgm2 = [18.0, true, 15]", ["inertia_guess_kgm2", "three numbers"]),
    (KIT + "[kit.mission]\ninertia_guess_kgm2 = [18.0, -20.7, 15.3]", ["inertia_guess_kgm2", "> 0"]),
    (KIT + "[kit.mission]\ninertia_guess_kgm2 = [18.0, nan, 15.3]", ["inertia_guess_kgm2", "finite"]),
    (KIT + "[kit.mission]\ninertia_guess_kgm2 = [1.0, 1.0, 5.0]", ["inertia_guess_kgm2", "principal moments"]),
    (KIT + "[kit.mission]\ninertia_guess_kgm2 = [18, 20, 15]\nguess = 1", ["[kit.mission] guess", "unknown key"]),
])
def test_a_bad_key_is_named_in_one_line(tmp_path, text, words):
    path = write(tmp_path, text)
    with pytest.raises(BoxConfigError) as e:
        load_box_config(path)
    message = str(e.value)
    assert "\n" not in message and message.startswith(path)
    for w in words:
        assert w in message, (w, message)


def test_a_missing_file(tmp_path):
    with pytest.raises(BoxConfigError, match="no such file"):
        load_box_config(str(tmp_path / "none.toml"))
