"""The box's configuration file: one TOML file for a flight computer (`fsw.main --config box.toml`).

What a box needs that does not change from run to run, in one place (an example: `deploy/box.toml`):

    system_id = 1                          # MAVLink system id of the box (1...255)
    key_file = "mission.key"               # mission key (python -m ground.keys new FILE)
    state_dir = "/var/lib/debris-box"      # what survives a restart: the TLE, the numbered samples

    [loop]
    rate_hz = 100                          # loop rate (--rate)
    sample_rate_hz = 50                    # magnetometer sample rate (--sample-rate)
    rate_filter = "euler"                  # the rate filter flown (--rate-filter; fsw/estimation/flown_filter.py)

    [magnetometer]
    bus = "i2c"                            # "i2c", "spi" or "serial"
    device = "/dev/i2c-1"
    i2c_address = 0x30                     # i2c only (default 0x30)
    spi_speed_hz = 4_000_000               # spi only (default 4 MHz, at most 10 MHz)

    [radio]
    port = "/dev/ttyAMA0"                  # the telemetry link: a serial device or a URL (--link)
    baud = 57600
    uplink = "udpin:0.0.0.0:14551"         # optional: commands on a link of their own (--uplink)

    [kit]                                  # optional: the de-orbit kit on GPIO lines (libgpiod v2)
    chip = "/dev/gpiochip0"
    debounce_ms = 5
    [kit.lines]                            # the kit's lines (fsw.drivers.gpio) -> the chip's line names
    "0.step" = "GPIO17"                    # (or offsets)
    [kit.mission]                          # optional: the whole mission on the kit (fsw/deorbit/mission.py)
    inertia_guess_kgm2 = [18.0, 20.7, 15.3]  # the box's rough guess of the host's principal moments

Every key is checked when the file is read, with the same rules as its command-line option; a key that
is wrong, of the wrong type, out of range or unknown (a typo) is a `BoxConfigError` naming the file,
the table and the key in one line (`fsw.main` turns it into a usage error, exit status 2). Relative
paths are taken from the file's directory. The command line overrides the file: `defaults()` gives
the options' values for `argparse`'s `set_defaults`, so an option given on the command line wins;
`--mag-i2c/--mag-spi/--mag-serial` replace the whole [magnetometer] table.
"""
from __future__ import annotations

import argparse
import os
import stat
import tomllib
from dataclasses import dataclass, field

from .argtypes import finite_float, int_range, link_url
from .config import MAX_RATE_HZ
from .drivers.gpiod_lines import INPUTS, SAFE_LEVELS
from .drivers.mag_bus import KINDS, MagBus
from .drivers.spi_bus import DEFAULT_SPEED_HZ, MAX_SPEED_HZ, spidev_numbers
from .estimation.flown_filter import FILTERS

MAX_DEBOUNCE_MS = 1000.0


class BoxConfigError(ValueError):
    """A configuration file that cannot be used; the message names the key."""


@dataclass(frozen=True)
class KitLines:
    """The de-orbit kit on a GPIO chip: the chip, logical line -> chip line (name or offset), debounce."""

    chip: str
    lines: dict = field(default_factory=dict)
    debounce_s: float = 0.005
    #: [kit.mission]: the box's guess of the host's principal moments [kg·m²] (3,): the mission is flown on
    #: the kit (`fsw.deorbit.mission`); None: no mission, the kit's controller alone
    mission_inertia_guess_kgm2: tuple | None = None


@dataclass(frozen=True)
class BoxConfig:
    path: str
    system_id: int | None = None
    key_file: str | None = None
    state_dir: str | None = None
    rate_hz: float | None = None
    sample_rate_hz: float | None = None
    mag: MagBus | None = None
    link: str | None = None
    baud: int | None = None
    uplink: str | None = None
    kit: KitLines | None = None
    rate_filter: str | None = None

    def defaults(self) -> dict:
        """argparse destinations -> values, for the options this file sets."""
        pairs = {"system_id": self.system_id, "key": self.key_file, "state_dir": self.state_dir,
                 "rate": self.rate_hz, "sample_rate": self.sample_rate_hz, "link": self.link, "baud": self.baud,
                 "uplink": self.uplink, "rate_filter": self.rate_filter}
        return {k: v for k, v in pairs.items() if v is not None}


class _Table:
    """One table of the file, its keys taken one by one; what is left at the end is unknown."""

    def __init__(self, path: str, name: str, data) -> None:
        self.path, self.name = path, name
        if not isinstance(data, dict):
            raise BoxConfigError(f"{path}: [{name}] must be a table")
        self.data = dict(data)

    def where(self, key: str) -> str:
        return f"{self.path}: {'[' + self.name + '] ' if self.name else ''}{key}"

    def error(self, key: str, message: str) -> BoxConfigError:
        return BoxConfigError(f"{self.where(key)}: {message}")

    def take(self, key: str, kinds: tuple, check=None, required: bool = False):
        if key not in self.data:
            if required:
                raise self.error(key, "missing")
            return None
        value = self.data.pop(key)
        if isinstance(value, bool) or not isinstance(value, kinds):
            names = " or ".join({int: "an integer", float: "a number", str: "a string"}[k] for k in kinds)
            raise self.error(key, f"must be {names}, got {value!r}")
        if check is not None:
            try:
                value = check(str(value)) if not isinstance(value, str) else check(value)
            except (argparse.ArgumentTypeError, ValueError) as e:
                raise self.error(key, str(e)) from None
        return value

    def path_value(self, key: str, base: str, required: bool = False) -> str | None:
        value = self.take(key, (str,), required=required)
        if value is None:
            return None
        if not value.strip():
            raise self.error(key, "empty")
        return value if os.path.isabs(value) else os.path.normpath(os.path.join(base, value))

    def finish(self, known: tuple[str, ...] = ()) -> None:
        unknown = [k for k in self.data if k not in known]
        if unknown:
            raise self.error(unknown[0], "unknown key")


#: the largest principal moment the mission's guess may name [kg·m²] (a spacecraft of a few tonnes)
MAX_MOMENT_KGM2 = 1e5


def _moments(table: _Table, key: str) -> tuple[float, float, float]:
    """Three principal moments [kg·m²]: finite, > 0, each at most the sum of the other two."""
    value = table.data.pop(key, None)
    if value is None:
        raise table.error(key, "missing")
    if not (isinstance(value, list) and len(value) == 3
            and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)):
        raise table.error(key, f"must be three numbers [Ixx, Iyy, Izz], got {value!r}")
    check = finite_float(0, MAX_MOMENT_KGM2, min_exclusive=True)
    try:
        moments = tuple(check(str(v)) for v in value)
    except argparse.ArgumentTypeError as e:
        raise table.error(key, str(e)) from None
    if 2 * max(moments) > sum(moments):
        raise table.error(key, f"{list(moments)} cannot be a body's principal moments: the largest exceeds the "
                               "sum of the other two")
    return moments


def _nonempty(text: str) -> str:
    if not text.strip():
        raise ValueError("empty")
    return text


def load_box_config(path: str) -> BoxConfig:
    """Read and check the box's configuration file (BoxConfigError, one line, naming the key)."""
    try:
        if not stat.S_ISREG(os.stat(path).st_mode):  # a FIFO would block the start, a directory cannot be read
            raise BoxConfigError(f"{path}: not a regular file")
        with open(path, "rb") as f:
            data = tomllib.load(f)
    except FileNotFoundError:
        raise BoxConfigError(f"{path}: no such file") from None
    except OSError as e:
        raise BoxConfigError(f"{path}: {e.strerror or e}") from None
    except tomllib.TOMLDecodeError as e:
        raise BoxConfigError(f"{path}: not valid TOML: {e}") from None
    base = os.path.dirname(os.path.abspath(path))
    top = _Table(path, "", data)
    system_id = top.take("system_id", (int,), int_range(1, 255))
    key_file = top.path_value("key_file", base)
    state_dir = top.path_value("state_dir", base)

    loop = _Table(path, "loop", top.data.pop("loop", {}))
    rate = finite_float(0, MAX_RATE_HZ, min_exclusive=True)
    rate_hz = loop.take("rate_hz", (int, float), rate)
    sample_rate_hz = loop.take("sample_rate_hz", (int, float), rate)
    rate_filter = loop.take("rate_filter", (str,))
    if rate_filter is not None and rate_filter not in FILTERS:
        raise loop.error("rate_filter", f"must be one of {', '.join(FILTERS)}, got {rate_filter!r}")
    loop.finish()

    mag = None
    if "magnetometer" in top.data:
        m = _Table(path, "magnetometer", top.data.pop("magnetometer"))
        kind = m.take("bus", (str,), required=True)
        if kind not in KINDS:
            raise m.error("bus", f"must be one of {', '.join(KINDS)}, got {kind!r}")
        device = m.take("device", (str,), _nonempty, required=True)
        address = m.take("i2c_address", (int,), int_range(0x08, 0x77))
        speed = m.take("spi_speed_hz", (int,), int_range(1, MAX_SPEED_HZ))
        if kind == "spi":
            try:
                spidev_numbers(device)
            except ValueError as e:
                raise m.error("device", str(e)) from None
        if address is not None and kind != "i2c":
            raise m.error("i2c_address", f"only for bus = \"i2c\", not {kind!r}")
        if speed is not None and kind != "spi":
            raise m.error("spi_speed_hz", f"only for bus = \"spi\", not {kind!r}")
        m.finish()
        mag = MagBus(kind, device, 0x30 if address is None else address,
                     DEFAULT_SPEED_HZ if speed is None else speed)

    radio = _Table(path, "radio", top.data.pop("radio", {}))
    link = radio.take("port", (str,), link_url)
    baud = radio.take("baud", (int,), int_range(1))
    uplink = radio.take("uplink", (str,), link_url)
    radio.finish()

    kit = None
    if "kit" in top.data:
        k = _Table(path, "kit", top.data.pop("kit"))
        chip = k.path_value("chip", base, required=True)
        debounce_ms = k.take("debounce_ms", (int, float), finite_float(0, MAX_DEBOUNCE_MS))
        lines_table = _Table(path, "kit.lines", k.data.pop("lines", {}))
        lines = {}
        for name, chip_line in lines_table.data.items():
            channel, _, kind = name.partition(".")
            if channel not in ("0", "1") or (kind not in SAFE_LEVELS and kind not in INPUTS):
                raise lines_table.error(f'"{name}"', "not a line of the kit (0.step, 1.home ... fsw/drivers/gpio.py)")
            if isinstance(chip_line, bool) or not isinstance(chip_line, (str, int)) or chip_line == "" \
                    or (isinstance(chip_line, int) and chip_line < 0):
                raise lines_table.error(f'"{name}"', f"must be a line name or an offset >= 0, got {chip_line!r}")
            lines[name] = chip_line
        taken = [n for n, v in lines.items() if list(lines.values()).count(v) > 1]
        if taken:
            raise lines_table.error(f'"{taken[-1]}"', f"chip line {lines[taken[-1]]!r} given to two lines")
        if not lines:
            raise k.error("lines", "missing: name the kit's lines")
        guess = None
        if "mission" in k.data:
            m = _Table(path, "kit.mission", k.data.pop("mission"))
            guess = _moments(m, "inertia_guess_kgm2")
            m.finish()
        k.finish()
        kit = KitLines(chip, lines, 5e-3 if debounce_ms is None else debounce_ms * 1e-3, guess)
    top.finish()
    return BoxConfig(path, system_id, key_file, state_dir, rate_hz, sample_rate_hz, mag, link, baud, uplink, kit,
                     rate_filter)
