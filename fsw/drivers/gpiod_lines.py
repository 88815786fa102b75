"""`DigitalLines` on a Linux GPIO chip through libgpiod v2 (the `gpiod` package's request API).

Lines: the kit's logical lines (`fsw.drivers.gpio`: ``0.step``, ``1.home`` ...) are mapped to the chip's
lines by the box's configuration (`fsw.box_config`: a line name such as ``"GPIO17"`` or an offset), and
requested once, at start, in one `gpiod.request_lines` call: inputs as inputs, outputs as outputs
already at their safe level (:data:`SAFE_LEVELS`), so that no output glitches on start. A logical line
that is not mapped is a `GpioError` at its first use, which the drivers count.

Step bursts (`pulse_output(line, count)`): a `PulseTrain` per step line, a thread with a bounded queue
(:data:`QUEUE_BURSTS` bursts). The loop only enqueues (`put_nowait`: it never blocks nor waits for a
pulse); the thread emits each burst's pulses evenly over `burst_period_s` (the calling task's period, 0.1
s for the kit at 10 Hz), each pulse `pulse_width_s` high, on absolute deadlines from the monotonic clock
so that sleeping late once does not slow the train down (the stepper's profile rate is kept over a
burst, to the scheduler's jitter). A full queue (the thread has fallen more than `QUEUE_BURSTS` periods
behind) is a `GpioError`: the burst is refused whole, the stepper counts it and retries. The stepper
driver (`fsw.drivers.stepper`) checks its position on the home switch after every move, so a burst that
was not emitted cannot go unnoticed.

Inputs are debounced by a sampler thread: every `input_period_s` (2 ms) it reads all the inputs in one
`get_values` call and accepts a level that differs from the accepted one once it has been read the same
for `debounce_s` (5 ms); `read_input` returns the accepted level at once. A change thus reaches the
loop `debounce_s` to `debounce_s + input_period_s` after it settled, well inside one kit period (0.1 s),
so the stepper's homing, which steps one step per update through the home switch's window, sees each
edge at the update it would without debouncing; a bounce shorter than `debounce_s` is never seen. (A
debounce that counted the loop's own reads would delay every edge by a whole update and shift the
homed centre by a step.) Done here rather than with the kernel's `debounce_period`, which not every
GPIO controller supports (I2C expanders often do not) and which a test cannot drive. A failing read is
a `GpioError` from `read_input` until a sample succeeds again. `input_period_s=None`: no thread, the
caller samples (`sample_inputs`, the tests with an injected clock).

Safe state (:meth:`GpiodLines.close`, called on exit, on an exception in the loop and after SIGTERM,
which ends the loop normally): the pulse threads are stopped and their queued bursts dropped, every
output is set to its safe level (steppers disabled, shutter motors off, the shutter latch released so
that the springs close the capsules) and the request is released. A SIGKILL or a power cut cannot run
this: the board's pull resistors must hold the same levels (docs/target.md).

`gpiod` needs libgpiod and a compiler: it is in the `target` extra, imported when the lines are opened.
"""
from __future__ import annotations

import queue
import threading
import time
from typing import Callable, Mapping

from .gpio import GpioError

#: the level each output is left at when the lines are requested and released
SAFE_LEVELS = {"step": False, "dir": False, "enable": False, "shutter_drive": False, "shutter_release": True}
INPUTS = ("home", "closed", "open")
QUEUE_BURSTS = 4
DEFAULT_PULSE_WIDTH_S = 50e-6
DEFAULT_DEBOUNCE_S = 5e-3
DEFAULT_INPUT_PERIOD_S = 2e-3
CONSUMER = "debris-box"


def require_gpiod():
    """The `gpiod` module (libgpiod v2), or GpioError with a one-line explanation."""
    try:
        import gpiod  # noqa: PLC0415 - the target extra, imported only when lines are opened
    except ImportError:
        raise GpioError("GPIO lines need the gpiod package (libgpiod v2), not installed: "
                        "pip install '.[target]' in the repository on the flight computer") from None
    if not hasattr(gpiod, "request_lines"):
        raise GpioError("the gpiod package installed is libgpiod v1's; v2 (gpiod >= 2.1) is needed")
    return gpiod


def kind_of(line: str) -> str:
    """The kind of a logical line (``"0.step"`` -> ``"step"``); GpioError if it is not a kit line."""
    kind = line.split(".", 1)[-1]
    if kind not in SAFE_LEVELS and kind not in INPUTS:
        raise GpioError(f"{line!r} is not a line of the kit")
    return kind


class PulseTrain:
    """Step bursts on one output, emitted by a thread from a bounded queue."""

    def __init__(self, set_level: Callable[[bool], None], burst_period_s: float, pulse_width_s: float,
                 name: str) -> None:
        self._set = set_level
        self.burst_period_s = burst_period_s
        self.pulse_width_s = pulse_width_s
        self._queue: queue.Queue[int] = queue.Queue(maxsize=QUEUE_BURSTS)
        self._stop = threading.Event()
        self.pulses = 0
        self.refused = 0
        self.errors = 0
        self._thread = threading.Thread(target=self._run, name=f"pulses {name}", daemon=True)
        self._thread.start()

    def burst(self, count: int) -> None:
        try:
            self._queue.put_nowait(count)
        except queue.Full:
            self.refused += 1
            raise GpioError(f"step pulse queue full ({QUEUE_BURSTS} bursts waiting)") from None

    def stop(self) -> None:
        """Stop emitting (a pulse in progress ends low) and drop the queued bursts."""
        self._stop.set()
        self._thread.join(timeout=1.0)

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                count = self._queue.get(timeout=0.05)
            except queue.Empty:
                continue
            interval = self.burst_period_s / count
            t0 = time.monotonic()
            for i in range(count):
                if self._wait_until(t0 + i * interval):
                    return
                try:
                    self._set(True)
                    time.sleep(self.pulse_width_s)
                    self._set(False)
                    self.pulses += 1
                except Exception:  # noqa: BLE001 - counted; the stepper finds missed steps on its switch
                    self.errors += 1

    def _wait_until(self, deadline: float) -> bool:
        """Sleep until `deadline` (monotonic); True if stopped meanwhile."""
        wait = deadline - time.monotonic()
        return self._stop.wait(wait) if wait > 0 else self._stop.is_set()


class GpiodLines:
    """The kit's lines on the GPIO chip `chip` (e.g. /dev/gpiochip0), `lines` mapping each logical line to
    the chip's line name or offset."""

    def __init__(self, chip: str, lines: Mapping[str, str | int], *, burst_period_s: float = 0.1,
                 pulse_width_s: float = DEFAULT_PULSE_WIDTH_S, debounce_s: float = DEFAULT_DEBOUNCE_S,
                 input_period_s: float | None = DEFAULT_INPUT_PERIOD_S,
                 clock: Callable[[], float] = time.monotonic) -> None:
        if not (burst_period_s > 0 and 0 < pulse_width_s and debounce_s >= 0
                and (input_period_s is None or input_period_s > 0)):
            raise ValueError("burst period, pulse width and input period > 0 s, debounce >= 0 s")
        kinds = {name: kind_of(name) for name in lines}
        gpiod = require_gpiod()
        Direction, Value = gpiod.line.Direction, gpiod.line.Value
        self._active, self._inactive = Value.ACTIVE, Value.INACTIVE
        config = {}
        for name, kind in kinds.items():
            if kind in INPUTS:
                config[lines[name]] = gpiod.LineSettings(direction=Direction.INPUT)
            else:
                config[lines[name]] = gpiod.LineSettings(
                    direction=Direction.OUTPUT, output_value=Value.ACTIVE if SAFE_LEVELS[kind] else Value.INACTIVE)
        self.chip = chip
        self._ids = dict(lines)
        self._kinds = kinds
        self._clock = clock
        self.debounce_s = float(debounce_s)
        self._request = gpiod.request_lines(chip, consumer=CONSUMER, config=config)
        self._lock = threading.Lock()  # the request is shared with the pulse threads
        self._inputs = [name for name, kind in kinds.items() if kind in INPUTS]
        self._debounce: dict[str, list] = {}  # line -> [accepted, candidate, candidate since]
        self._input_error: str | None = None
        self._trains = {name: PulseTrain(lambda level, i=self._ids[name]: self._set(i, level), burst_period_s,
                                         pulse_width_s, name)
                        for name, kind in kinds.items() if kind == "step"}
        self.released = False
        self._stop = threading.Event()
        self._sampler = None
        if input_period_s is not None and self._inputs:
            self.sample_inputs()
            self._sampler = threading.Thread(target=self._sample_forever, args=(input_period_s,),
                                             name="gpio inputs", daemon=True)
            self._sampler.start()

    # --- DigitalLines ---------------------------------------------------------------------------
    def read_input(self, line: str) -> bool:
        if self._kinds.get(line) not in INPUTS:
            raise GpioError(f"{line!r} is not an input of this box's lines")
        if self._sampler is None and line not in self._debounce:
            self.sample_inputs()
        if self._input_error is not None:
            raise GpioError(self._input_error)
        return self._debounce[line][0]

    def sample_inputs(self) -> None:
        """Read every input once and advance its debouncing (the sampler thread's step)."""
        with self._lock:
            if self.released:
                self._input_error = "lines released"
                return
            try:
                raw = [v == self._active for v in self._request.get_values([self._ids[n] for n in self._inputs])]
            except (OSError, ValueError) as error:
                self._input_error = f"GPIO inputs: {error}"
                return
        now = self._clock()
        for name, level in zip(self._inputs, raw):
            state = self._debounce.get(name)
            if state is None:
                self._debounce[name] = [level, level, now]
            elif level == state[0]:
                state[1] = level
            elif level != state[1]:
                state[1], state[2] = level, now
            elif now - state[2] >= self.debounce_s:
                state[0] = level
        self._input_error = None

    def _sample_forever(self, period_s: float) -> None:
        while not self._stop.wait(period_s):
            self.sample_inputs()

    def write_output(self, line: str, level: bool) -> None:
        kind = self._kinds.get(line)
        if kind is None or kind in INPUTS or kind == "step":
            raise GpioError(f"{line!r} is not a level output of this box's lines")
        self._set(self._ids[line], bool(level))

    def pulse_output(self, line: str, count: int) -> None:
        train = self._trains.get(line)
        if train is None:
            raise GpioError(f"{line!r} is not a step output of this box's lines")
        if count < 0:
            raise GpioError(f"negative pulse count {count}")
        if self.released:
            raise GpioError("lines released")
        if count:
            train.burst(int(count))

    # --- safe state -----------------------------------------------------------------------------
    def close(self) -> None:
        """Every output to its safe level, then the request released (idempotent; never raises)."""
        if self.released:
            return
        self._stop.set()
        if self._sampler is not None:
            self._sampler.join(timeout=1.0)
        for train in self._trains.values():
            train.stop()
        with self._lock:
            try:
                self._request.set_values({self._ids[name]: self._active if SAFE_LEVELS[kind] else self._inactive
                                          for name, kind in self._kinds.items() if kind in SAFE_LEVELS})
            except Exception:  # noqa: BLE001 - release anyway: the kernel then holds the lines as they are
                pass
            try:
                self._request.release()
            except Exception:  # noqa: BLE001
                pass
        self.released = True

    def __enter__(self) -> GpiodLines:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    @property
    def pulses(self) -> int:
        return sum(t.pulses for t in self._trains.values())

    # --- the request ----------------------------------------------------------------------------
    def _set(self, line_id, level: bool) -> None:
        with self._lock:
            if self.released:
                raise GpioError("lines released")
            try:
                self._request.set_value(line_id, self._active if level else self._inactive)
            except (OSError, ValueError) as error:
                raise GpioError(f"GPIO {line_id}: {error}") from error

