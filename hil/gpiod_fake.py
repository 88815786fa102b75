"""A stand-in for the `gpiod` package (libgpiod v2) whose lines are the emulated de-orbit kit's.

`FakeGpiod(kit, chip_lines)` has what `fsw.drivers.gpiod_lines` uses of the package — `request_lines(path,
consumer=, config=)`, `LineSettings`, `line.Direction`, `line.Value` — and is installed in its place by a
test (`monkeypatch.setitem(sys.modules, "gpiod", fake)`). `chip_lines` maps the chip's line names (or
offsets) to the kit's logical lines (``"GPIO17": "0.step"``). The request it returns drives
`hil.deorbit_kit.DeorbitKitEmulator` at the boundary a GPIO chip has: a rising edge on a step line is one
step pulse (`pulse_output(line, 1)`), a level on the other outputs is `write_output`, a read is
`read_input`; the emulator is advanced to `clock()` (seconds) before every operation.

What the request records, for the tests: `rising` (line -> the times of its rising edges), `levels`
(line -> the last level driven), `log` of every set, `released` and `levels_at_release`; `bounce` (line
-> a list of raw levels returned by the next reads, a switch that bounces); `fail_get` (an OSError
raised by the next reads).
"""
from __future__ import annotations

import threading
import time
import types
from dataclasses import dataclass, field
from datetime import timedelta
from enum import Enum
from typing import Callable, Mapping

from .deorbit_kit import DeorbitKitEmulator


class Direction(Enum):
    AS_IS = 1
    INPUT = 2
    OUTPUT = 3


class Value(Enum):
    INACTIVE = 0
    ACTIVE = 1


@dataclass
class LineSettings:
    direction: Direction = Direction.AS_IS
    output_value: Value = Value.INACTIVE
    active_low: bool = False
    debounce_period: timedelta = field(default_factory=timedelta)


class FakeLineRequest:
    def __init__(self, gpiod: FakeGpiod, path: str, consumer: str | None, config: dict) -> None:
        self._g = gpiod
        self.path, self.consumer = path, consumer
        self.settings: dict = {}
        for key, settings in config.items():
            for line_id in (key if isinstance(key, tuple) else (key,)):
                if line_id not in gpiod.chip_lines:
                    raise ValueError(f"unknown line name: {line_id}")
                self.settings[line_id] = settings
        self.rising: dict[str, list[float]] = {}
        self.levels: dict[str, bool] = {}
        self.log: list[tuple[float, str, bool]] = []
        self.bounce: dict[str, list[bool]] = {}
        self.fail_get: OSError | None = None
        self.released = False
        self.levels_at_release: dict[str, bool] | None = None
        for line_id, s in self.settings.items():
            if s.direction is Direction.OUTPUT:
                self._drive(line_id, s.output_value is Value.ACTIVE)

    def get_value(self, line_id) -> Value:
        with self._g.lock:
            self._check(line_id, Direction.INPUT)
            logical = self._g.chip_lines[line_id]
            if self.fail_get is not None:
                raise self.fail_get
            self._g.kit.advance_to(self._g.clock())
            if self.bounce.get(logical):
                return Value.ACTIVE if self.bounce[logical].pop(0) else Value.INACTIVE
            return Value.ACTIVE if self._g.kit.read_input(logical) else Value.INACTIVE

    def get_values(self, lines=None) -> list[Value]:
        return [self.get_value(i) for i in (lines or list(self.settings))]

    def set_value(self, line_id, value: Value) -> None:
        with self._g.lock:
            self._check(line_id, Direction.OUTPUT)
            self._drive(line_id, value is Value.ACTIVE)

    def set_values(self, values: Mapping) -> None:
        for line_id, value in values.items():
            self.set_value(line_id, value)

    def release(self) -> None:
        if self.released:
            raise RuntimeError("request already released")  # gpiod raises RequestReleasedError
        self.released = True
        self.levels_at_release = dict(self.levels)

    def _check(self, line_id, direction: Direction) -> None:
        if self.released:
            raise RuntimeError("request released")
        s = self.settings.get(line_id)
        if s is None:
            raise ValueError(f"unknown line name: {line_id}")
        if s.direction is not direction:
            raise OSError(1, f"line {line_id} is not an {direction.name.lower()}")  # EPERM, as the kernel says

    def _drive(self, line_id, level: bool) -> None:
        g = self._g
        now = g.clock()
        g.kit.advance_to(now)
        logical = g.chip_lines[line_id]
        was = self.levels.get(logical, False)
        self.levels[logical] = level
        self.log.append((now, logical, level))
        if logical.endswith(".step"):
            if level and not was:
                self.rising.setdefault(logical, []).append(now)
                g.kit.pulse_output(logical, 1)
        else:
            g.kit.write_output(logical, level)


class FakeGpiod(types.ModuleType):
    """The `gpiod` module, its lines the emulator `kit`'s (see the module docstring)."""

    def __init__(self, kit: DeorbitKitEmulator, chip_lines: Mapping, clock: Callable[[], float] | None = None,
                 chip: str = "/dev/gpiochip0") -> None:
        super().__init__("gpiod")
        self.kit = kit
        self.chip_lines = dict(chip_lines)
        t0 = time.monotonic()
        self.clock = clock or (lambda: time.monotonic() - t0)
        self.chip = chip
        self.lock = threading.RLock()
        self.requests: list[FakeLineRequest] = []
        self.line = types.SimpleNamespace(Direction=Direction, Value=Value)
        self.LineSettings = LineSettings

    def request_lines(self, path: str, consumer: str | None = None, config: dict | None = None, **kw):
        if path != self.chip:
            raise FileNotFoundError(2, "No such file or directory", path)
        with self.lock:
            req = FakeLineRequest(self, path, consumer, config or {})
        self.requests.append(req)
        return req
