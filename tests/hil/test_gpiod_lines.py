"""The kit's lines through libgpiod v2's request API (`fsw.drivers.gpiod_lines`), the emulated kit behind a
stand-in of the `gpiod` package (`hil.gpiod_fake`): outputs requested and released at their safe levels,
step bursts timed by a thread at the stepper's profile, inputs debounced, failures counted as GpioError."""
import errno
import sys
import time

import pytest

from fsw.drivers.gpio import GpioError
from fsw.drivers.gpiod_lines import QUEUE_BURSTS, SAFE_LEVELS, GpiodLines, require_gpiod
from fsw.drivers.stepper import MagnetState, Stepper, StepperLimits
from hil.deorbit_kit import DeorbitKitEmulator
from hil.gpiod_fake import FakeGpiod

LINES = {f"{ch}.{kind}": f"KIT{ch}_{kind.upper()}" for ch in (0, 1)
         for kind in ("step", "dir", "enable", "home", "shutter_drive", "shutter_release", "closed", "open")}
SAFE = {line: SAFE_LEVELS[line.split(".")[1]] for line in LINES if line.split(".")[1] in SAFE_LEVELS}


class Clock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


@pytest.fixture
def kit(monkeypatch):
    emu = DeorbitKitEmulator()
    fake = FakeGpiod(emu, {chip: logical for logical, chip in LINES.items()})
    monkeypatch.setitem(sys.modules, "gpiod", fake)
    return emu, fake


def test_outputs_requested_at_their_safe_levels_and_released_at_them(kit):
    emu, fake = kit
    lines = GpiodLines("/dev/gpiochip0", LINES)
    (req,) = fake.requests
    assert req.consumer == "debris-box" and req.levels == SAFE
    lines.write_output("0.enable", True)
    lines.write_output("1.shutter_drive", True)
    lines.write_output("1.shutter_release", False)
    assert emu.channels[0].enable and emu.channels[1].drive
    lines.close()
    assert req.released and req.levels_at_release == SAFE
    assert not emu.channels[0].enable and not emu.channels[1].drive and emu.channels[1].release
    lines.close()  # idempotent
    with pytest.raises(GpioError):
        lines.write_output("0.enable", True)


def test_safe_state_after_an_exception_mid_move(kit):
    emu, fake = kit
    with pytest.raises(RuntimeError):
        with GpiodLines("/dev/gpiochip0", LINES, burst_period_s=0.1) as lines:
            stepper = Stepper(lines, 0)
            stepper.move(100, time.monotonic())
            stepper.update(time.monotonic())
            raise RuntimeError("the loop failed")
    (req,) = fake.requests
    assert req.levels_at_release == SAFE and not emu.channels[0].enable
    pulses = emu.channels[0].pulses
    time.sleep(0.15)
    assert emu.channels[0].pulses == pulses  # the pulse thread has stopped with the lines


def test_step_bursts_keep_the_steppers_profile(kit):
    """300 steps at the default profile (125 steps/s, 0.2 s ramps) from the kit's 10 Hz updates: every step
    emitted, the cruise's pulses per second within 2 % of 125, the loop never waiting for a pulse."""
    emu, fake = kit
    limits = StepperLimits()
    emu.channels[0].rotor_steps = -3  # just before the home switch's window: homing takes a second
    with GpiodLines("/dev/gpiochip0", LINES, burst_period_s=0.1) as lines:
        stepper = Stepper(lines, 0, limits)

        def run_while(state, t0):
            k, worst_s = 0, 0.0
            while stepper.state is state and k < 60:
                k += 1
                time.sleep(max(0.0, t0 + 0.1 * k - time.monotonic()))
                a = time.monotonic()
                stepper.update(a)
                worst_s = max(worst_s, time.monotonic() - a)
            return worst_s

        assert stepper.home(time.monotonic())
        run_while(MagnetState.HOMING, time.monotonic())
        assert stepper.state is MagnetState.IDLE and emu.channels[0].rotor_steps == 0  # the switch's centre
        homing_pulses = emu.channels[0].pulses
        fake.requests[0].rising["0.step"].clear()
        t0 = time.monotonic()
        assert stepper.move(300, t0)
        worst_update_s = run_while(MagnetState.TURNING, t0)
        time.sleep(0.15)
        refused = sum(t.refused for t in lines._trains.values())
    req = fake.requests[0]
    assert stepper.state is MagnetState.IDLE and stepper.position_steps == 300 % 200 and stepper.fault == 0
    assert emu.channels[0].rotor_steps == 300 and emu.channels[0].pulses - homing_pulses == 300 and refused == 0
    rising = req.rising["0.step"]
    t_start = rising[0]
    ramp_s = limits.speed_sps / limits.accel_sps2
    cruise = [t for t in rising if t_start + ramp_s + 0.15 <= t <= rising[-1] - ramp_s - 0.15]
    rate_sps = (len(cruise) - 1) / (cruise[-1] - cruise[0])
    assert abs(rate_sps / limits.speed_sps - 1) < 0.02, rate_sps
    # the whole move's pulses in the profile's time (1.0 s per 180 degrees plus the cruise), to one period
    assert abs((rising[-1] - t_start) - stepper.move_duration_s(300)) < 0.1 + 1e-9
    print(f"cruise {rate_sps:.2f} steps/s (profile {limits.speed_sps:g}), slowest update {worst_update_s * 1e3:.2f} ms")


def test_a_full_pulse_queue_refuses_the_burst_without_waiting(kit):
    with GpiodLines("/dev/gpiochip0", LINES, burst_period_s=10.0) as lines:
        lines.write_output("0.enable", True)
        for _ in range(QUEUE_BURSTS + 1):  # one being emitted, QUEUE_BURSTS waiting
            lines.pulse_output("0.step", 5)
            time.sleep(0.01)
        with pytest.raises(GpioError, match="queue full"):
            lines.pulse_output("0.step", 5)


def test_inputs_are_debounced_on_the_clock(kit):
    emu, fake = kit
    clock = Clock()
    lines = GpiodLines("/dev/gpiochip0", LINES, debounce_s=0.005, input_period_s=None, clock=clock)
    req = fake.requests[0]
    assert lines.read_input("0.closed") is True          # shutters closed at start (first sample)

    def sample(raw):
        req.bounce["0.closed"] = [raw]
        clock.t += 0.002
        lines.sample_inputs()
        return lines.read_input("0.closed")

    assert [sample(raw) for raw in (False, True, False, True, False, True)] == [True] * 6  # a bounce
    assert [sample(False) for _ in range(4)] == [True, True, True, False]  # stable for 6 ms: accepted
    assert [sample(True) for _ in range(2)] == [False, False]


def test_the_sampler_thread_sees_a_change_within_the_debounce_time(kit):
    emu, fake = kit
    with GpiodLines("/dev/gpiochip0", LINES, debounce_s=0.005, input_period_s=0.002) as lines:
        assert lines.read_input("1.open") is False
        emu.channels[1].switch_lies.update(open=True, closed=False)  # the end switches change over
        deadline = time.monotonic() + 1.0
        while not lines.read_input("1.open") and time.monotonic() < deadline:
            time.sleep(0.001)
        assert lines.read_input("1.open") is True and lines.read_input("1.closed") is False


def test_misuse_and_failures_are_gpio_errors(kit, monkeypatch):
    emu, fake = kit
    lines = GpiodLines("/dev/gpiochip0", {"0.home": "KIT0_HOME", "0.step": "KIT0_STEP"})
    for call in (lambda: lines.read_input("0.closed"), lambda: lines.write_output("0.step", True),
                 lambda: lines.write_output("0.home", True), lambda: lines.pulse_output("0.home", 1),
                 lambda: lines.pulse_output("0.step", -1)):
        with pytest.raises(GpioError):
            call()
    fake.requests[0].fail_get = OSError(errno.EIO, "I/O error")
    lines.close()
    lines = GpiodLines("/dev/gpiochip0", {"0.home": "KIT0_HOME"}, input_period_s=None)
    fake.requests[-1].fail_get = OSError(errno.EIO, "I/O error")
    with pytest.raises(GpioError, match="I/O error"):
        lines.read_input("0.home")
    fake.requests[-1].fail_get = None
    lines.sample_inputs()
    assert lines.read_input("0.home") is True
    with pytest.raises(GpioError, match="not a line of the kit"):
        GpiodLines("/dev/gpiochip0", {"0.brake": "X"})
    with pytest.raises(FileNotFoundError):
        GpiodLines("/dev/gpiochip7", {"0.home": "KIT0_HOME"})
    monkeypatch.setitem(sys.modules, "gpiod", None)
    with pytest.raises(GpioError, match="gpiod.*target"):
        require_gpiod()
