"""Fault injection for soak runs: a seeded schedule of magnetometer and link faults, and the radio
link that suffers them.

Magnetometer faults act on the register-level emulator (`hil.mmc5983ma` hooks):

| kind           | what the chip does                                                          |
|----------------|-----------------------------------------------------------------------------|
| no_data_ready  | measurements finish without Meas_M_Done (and without new outputs)           |
| bus_errors     | a fraction (30–100 %) of transfers are not acknowledged (BusError)          |
| stuck          | outputs frozen while Meas_M_Done still comes                                |
| spike          | one measurement sees an extra 20–200 µT (a current pulse in the harness)    |
| saturation     | an extra 10–12 G on one axis: the outputs clip at ±8 G                      |
| chip_reset     | power cycle in flight: control registers lost, 10 ms without answer         |
| wrong_id       | the chip drops off the bus (NAKs for 1.5 sample periods, at least 0.3 s),   |
|                | then reads product id 0xFF (the SPI symptom of the fact sheet, section 5)   |

Link faults act on :class:`FaultyLink`, the radio between the flight software and the ground:

| kind        | what the link does                                                              |
|-------------|---------------------------------------------------------------------------------|
| loss        | frames vanish (5–30 %), both directions                                          |
| corruption  | one bit flipped in 5–20 % of the frames                                           |
| garbage     | bursts of 1–40 random bytes between frames (10–30 % of the frames)                |
| duplicates  | 10–30 % of the frames arrive twice                                                |
| reordering  | 10–30 % of the frames arrive after the next one                                   |
| disconnect  | the serial port goes away (writes fail, the frame in flight is cut), then returns |

Faults come one at a time, every kind in turn in a shuffled order, separated by quiet spells, so
that the recovery from each can be judged on its own (`bench.soak`). Everything random comes from the
`numpy.random.Generator` given.
"""
from __future__ import annotations

import errno
from collections import deque
from dataclasses import dataclass

import numpy as np

from fsw.telemetry.dialect import mavlink

MAG_KINDS = ("no_data_ready", "bus_errors", "stuck", "spike", "saturation", "chip_reset", "wrong_id")
LINK_KINDS = ("loss", "corruption", "garbage", "duplicates", "reordering", "disconnect")
ALL_KINDS = MAG_KINDS + LINK_KINDS

#: duration range (s) per kind; 0: instantaneous
DURATIONS_S = {
    "no_data_ready": (2.0, 10.0), "bus_errors": (2.0, 10.0), "stuck": (3.0, 10.0), "spike": (0.0, 0.0),
    "saturation": (2.0, 8.0), "chip_reset": (0.0, 0.0), "wrong_id": (4.0, 10.0),
    "loss": (10.0, 30.0), "corruption": (10.0, 30.0), "garbage": (10.0, 30.0), "duplicates": (10.0, 30.0),
    "reordering": (10.0, 30.0), "disconnect": (5.0, 120.0),
}
#: severity range per kind (probability, or field in tesla)
SEVERITY = {
    "bus_errors": (0.3, 1.0), "spike": (20e-6, 200e-6), "saturation": (1.0e-3, 1.2e-3),
    "loss": (0.05, 0.3), "corruption": (0.05, 0.2), "garbage": (0.1, 0.3), "duplicates": (0.1, 0.3),
    "reordering": (0.1, 0.3),
}
WRONG_ID_OFF_BUS_S = 0.3


@dataclass(frozen=True)
class Fault:
    kind: str
    start_s: float
    duration_s: float
    severity: float = 0.0

    @property
    def end_s(self) -> float:
        return self.start_s + self.duration_s

    @property
    def domain(self) -> str:
        return "magnetometer" if self.kind in MAG_KINDS else "link"


def make_schedule(rng: np.random.Generator, duration_s: float, *, kinds=ALL_KINDS, first_s: float = 30.0,
                  quiet_s: tuple[float, float] = (20.0, 60.0), tail_s: float = 60.0) -> list[Fault]:
    """Faults one after the other from `first_s`, each kind in turn (shuffled anew every round),
    `quiet_s` apart, none ending within `tail_s` of the end."""
    faults: list[Fault] = []
    t = first_s
    order: list[str] = []
    while True:
        if not order:
            order = list(rng.permutation(list(kinds)))
        kind = str(order.pop())
        lo, hi = DURATIONS_S[kind]
        dur = float(rng.uniform(lo, hi)) if hi > lo else lo
        sev = float(rng.uniform(*SEVERITY[kind])) if kind in SEVERITY else 0.0
        if t + dur > duration_s - tail_s:
            break
        faults.append(Fault(kind, t, dur, sev))
        t += dur + float(rng.uniform(*quiet_s))
    return faults


class FaultyLink:
    """A radio link with faults, in memory. Flight side, like a pymavlink connection: `mav` (the
    flight's packer), `write(buf)` (raises OSError while disconnected), `recv(n)`. Ground side:
    `ground_read()`, `ground_write(buf)`.

    `truth` counts what really happened to the flight's frames: `frames_written`, `frames_lost`
    (dropped, corrupted or cut by a disconnect), `frames_corrupted_in_signature` (of those, a bit
    flipped in the signature block, which the CRC does not cover), `frames_duplicated`,
    `frames_reordered`, `garbage_bytes`, `frames_delivered_intact` (every copy that reached the ground
    unchanged)."""

    def __init__(self, rng: np.random.Generator, *, src_system: int, src_component: int) -> None:
        self.mav = mavlink.MAVLink(self, srcSystem=src_system, srcComponent=src_component)
        self.rng = rng
        self.loss = 0.0
        self.corruption = 0.0
        self.garbage = 0.0
        self.duplicates = 0.0
        self.reordering = 0.0
        self.connected = True
        self.portdead = False
        self._down = bytearray()
        self._up = bytearray()
        self._held: list[tuple[bytes, bool]] | None = None
        self._last_frame_at: int | None = None  # where the last frame written starts in _down
        self.truth = dict.fromkeys(("frames_written", "frames_lost", "frames_duplicated", "frames_reordered",
                                    "garbage_bytes", "frames_delivered_intact", "writes_refused",
                                    "frames_corrupted_in_signature",
                                    "uplink_frames_lost"), 0)

    # --- flight side ----------------------------------------------------------------------------
    def write(self, buf: bytes) -> int:
        if not self.connected:
            self.truth["writes_refused"] += 1
            raise OSError(errno.EIO, "serial port disconnected")
        t = self.truth
        t["frames_written"] += 1
        r = self.rng.random(5)
        if r[0] < self.loss:
            t["frames_lost"] += 1
            return len(buf)
        frame, intact = bytes(buf), True
        if r[1] < self.corruption:
            b = bytearray(frame)
            i = int(self.rng.integers(len(b)))
            b[i] ^= 1 << int(self.rng.integers(8))
            frame, intact = bytes(b), False
            t["frames_lost"] += 1
            if b[0] == 0xFD and b[2] & 0x01 and i >= len(b) - 13:
                t["frames_corrupted_in_signature"] += 1  # not covered by the CRC: caught by the signature
        copies = [(frame, intact)]
        if r[2] < self.duplicates:
            copies.append((frame, intact))
            t["frames_duplicated"] += 1
        if r[3] < self.garbage:
            junk = self.rng.integers(0, 256, int(self.rng.integers(1, 41))).astype(np.uint8).tobytes()
            self._push(junk, None)
            t["garbage_bytes"] += len(junk)
        if self._held is not None:
            held, self._held = self._held, None
            for f, ok in copies + held:
                self._push(f, ok)
        elif r[4] < self.reordering:
            self._held = copies
            t["frames_reordered"] += 1
        else:
            for f, ok in copies:
                self._push(f, ok)
        return len(buf)

    def _push(self, data: bytes, intact: bool | None) -> None:
        if intact is not None:
            self._last_frame_at = len(self._down)
            if intact:
                self.truth["frames_delivered_intact"] += 1
        self._down += data

    def recv(self, n: int | None = None) -> bytes:
        if not self.connected or not self._up:
            return b""
        n = len(self._up) if n is None else n
        out = bytes(self._up[:n])
        del self._up[:n]
        return out

    # --- ground side ----------------------------------------------------------------------------
    def ground_read(self) -> bytes:
        out = bytes(self._down)
        self._down.clear()
        self._last_frame_at = None
        return out

    def ground_write(self, buf: bytes) -> None:
        if not self.connected or self.rng.random() < self.loss:
            self.truth["uplink_frames_lost"] += 1
            return
        self._up += buf

    # --- faults ---------------------------------------------------------------------------------
    def disconnect(self) -> None:
        """The port goes away: a frame still on its way is cut short (half the time)."""
        if self._held is not None:
            for f, ok in self._held:
                self._push(f, ok)
            self._held = None
        if self._last_frame_at is not None and self.rng.random() < 0.5:
            start = self._last_frame_at
            length = len(self._down) - start
            if length > 1:
                cut = int(self.rng.integers(1, length))
                del self._down[start + cut:]
                self.truth["frames_lost"] += 1
                self.truth["frames_delivered_intact"] -= 1
        self._last_frame_at = None
        self.connected = False
        self._up.clear()

    def reconnect(self) -> None:
        self.connected = True

    def flush_held(self) -> None:
        if self._held is not None:
            for f, ok in self._held:
                self._push(f, ok)
            self._held = None


#: the ground station's address on a datagram link
GROUND_ADDR = ("192.168.0.2", 14550)


class FaultyDatagramLink(FaultyLink):
    """A :class:`FaultyLink` whose uplink carries datagrams with source addresses, like UDP (SITL, an
    IP radio): so that floods and spoofed sources can reach the box (`bench.link_attacks`). The box reads
    it like `fsw.telemetry.udp_link.UdpLink` (`read_datagrams`, `os_dropped`); the downlink is the
    faulty byte stream of :class:`FaultyLink`. A receive buffer of `rcvbuf_bytes` (the kernel's
    default) holds what the box has not read yet; what does not fit is dropped and counted, as the
    kernel does. `truth["uplink_os_dropped"]`, `["uplink_datagrams"]`, `["uplink_bytes"]` count."""

    def __init__(self, rng: np.random.Generator, *, src_system: int, src_component: int,
                 rcvbuf_bytes: int = 212_992) -> None:
        super().__init__(rng, src_system=src_system, src_component=src_component)
        self.rcvbuf_bytes = rcvbuf_bytes
        self._datagrams: deque = deque()
        self._queued = 0
        self.truth.update(uplink_os_dropped=0, uplink_datagrams=0, uplink_bytes=0)

    def ground_write(self, buf: bytes, addr=GROUND_ADDR) -> bool:
        """A datagram from `addr` (the ground station by default): whether it reached the box's buffer
        (radio loss and a disconnected link lose it, a full buffer drops it)."""
        if not self.connected or self.rng.random() < self.loss:
            self.truth["uplink_frames_lost"] += 1
            return False
        return self.inject(buf, addr)

    def inject(self, buf: bytes, addr) -> bool:
        """A datagram that arrives whatever the radio does (an attacker on the network)."""
        if not self.connected:
            return False
        t = self.truth
        t["uplink_datagrams"] += 1
        t["uplink_bytes"] += len(buf)
        if self._queued + len(buf) > self.rcvbuf_bytes:
            t["uplink_os_dropped"] += 1
            return False
        self._datagrams.append((bytes(buf), addr, len(buf)))
        self._queued += len(buf)
        return True

    def read_datagrams(self, max_datagrams: int) -> list:
        out = []
        q = self._datagrams
        while q and len(out) < max_datagrams:
            d = q.popleft()
            self._queued -= d[2]
            out.append(d)
        return out

    @property
    def os_dropped(self) -> int:
        return self.truth["uplink_os_dropped"]

    def recv(self, n: int | None = None) -> bytes:
        return b""

    def disconnect(self) -> None:
        super().disconnect()
        self._datagrams.clear()
        self._queued = 0


class FaultInjector:
    """Starts and ends the scheduled faults on the chip (`hil.mmc5983ma.EmulatedMmc5983ma`) and the
    link; call :meth:`update` with the simulation time before each loop tick."""

    def __init__(self, schedule: list[Fault], chip, link: FaultyLink, rng: np.random.Generator, *,
                 sample_period_s: float = 0.0) -> None:
        """`sample_period_s`: the driver touches the chip about once per sample; a wrong-id fault keeps
        the chip off the bus for at least 1.5 sample periods so that the driver has to probe it again."""
        self.off_bus_s = max(WRONG_ID_OFF_BUS_S, 1.5 * sample_period_s)
        self.pending = sorted(schedule, key=lambda f: f.start_s)
        self.chip = chip
        self.link = link
        self.rng = rng
        self.active: list[Fault] = []
        self.started: list[Fault] = []
        self._spike_measurements: int | None = None
        self._wrong_id_bus_until: float | None = None

    def update(self, now_s: float) -> list[tuple[str, Fault]]:
        """Apply the faults due at `now_s`; returns the ('start' | 'end', fault) events."""
        events = []
        while self.pending and self.pending[0].start_s <= now_s:
            f = self.pending.pop(0)
            self._start(f)
            self.active.append(f)
            self.started.append(f)
            events.append(("start", f))
        if self._spike_measurements is not None and self.chip.measurements > self._spike_measurements:
            self.chip.fault_field_T[:] = 0.0  # the spike hit exactly one measurement
            self._spike_measurements = None
        if self._wrong_id_bus_until is not None and now_s >= self._wrong_id_bus_until:
            self.chip.fault_bus_error_rate = 0.0
            self._wrong_id_bus_until = None
        ended = [f for f in self.active if f.end_s <= now_s and (f.kind != "spike" or self._spike_measurements is None)]
        for f in ended:
            self._end(f)
            self.active.remove(f)
            events.append(("end", f))
        return events

    def _start(self, f: Fault) -> None:
        chip, link = self.chip, self.link
        k = f.kind
        if k == "no_data_ready":
            chip.fault_no_data_ready = True
        elif k == "bus_errors":
            chip.fault_bus_error_rate = f.severity
        elif k == "stuck":
            chip.fault_stuck = True
        elif k == "spike":
            d = self.rng.normal(size=3)
            chip.fault_field_T[:] = f.severity * d / np.linalg.norm(d)
            self._spike_measurements = chip.measurements
        elif k == "saturation":
            axis = int(self.rng.integers(3))
            chip.fault_field_T[:] = 0.0
            chip.fault_field_T[axis] = f.severity * (1 if self.rng.random() < 0.5 else -1)
        elif k == "chip_reset":
            chip.power_cycle()
        elif k == "wrong_id":
            chip.fault_wrong_id = True
            chip.fault_bus_error_rate = 1.0
            self._wrong_id_bus_until = f.start_s + self.off_bus_s
        elif k == "disconnect":
            link.disconnect()
        else:
            setattr(link, k, f.severity)

    def _end(self, f: Fault) -> None:
        chip, link = self.chip, self.link
        k = f.kind
        if k == "no_data_ready":
            chip.fault_no_data_ready = False
        elif k == "bus_errors":
            chip.fault_bus_error_rate = 0.0
        elif k == "stuck":
            chip.fault_stuck = False
        elif k in ("spike", "saturation"):
            chip.fault_field_T[:] = 0.0
        elif k == "wrong_id":
            chip.fault_wrong_id = False
            chip.fault_bus_error_rate = 0.0
            self._wrong_id_bus_until = None
        elif k == "disconnect":
            link.reconnect()
        elif k == "reordering":
            link.reordering = 0.0
            link.flush_held()
        elif k in LINK_KINDS:
            setattr(link, k, 0.0)
