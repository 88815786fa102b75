"""A register device (the emulated MMC5983MA) reachable over a pseudo-terminal.

`PtyBridge` plays the USB-I2C bridge of `fsw.drivers.serial_bus`: it opens a pty pair, serves the
bridge protocol on the master side from a background thread, and performs each request on the
device it wraps. The flight software opens `port_name` (the slave side) with `SerialBus` exactly
as it would open a real serial adapter.

Link faults for later fault-injection runs are plain attributes: `corrupt_rate` (probability that
a response has one bit flipped), `drop_rate` (probability that a response is not sent) and
`corrupt_next` (the next N responses are corrupted, for deterministic tests).
"""

from __future__ import annotations

import os
import select
import threading
import tty

import numpy as np

from fsw.bus import BusError, RegisterBus
from fsw.drivers.serial_bus import (
    OP_READ,
    OP_WRITE,
    REQUEST_LENGTH,
    REQUEST_SYNC,
    STATUS_BAD_REQUEST,
    STATUS_DEVICE_FAULT,
    STATUS_NAK,
    STATUS_OK,
    crc8,
    encode_response,
)

_POLL_S = 0.02  # how often the server thread looks at the stop flag


def split_requests(buffer: bytearray) -> list[bytes]:
    """Remove the complete, CRC-valid requests from the front of `buffer`; return their bodies.

    Bytes before a SYNC and frames whose CRC fails are dropped one byte at a time, so a corrupted
    frame cannot hide a good one that follows it. An incomplete frame is left in `buffer`.
    """
    bodies = []
    while buffer:
        start = buffer.find(REQUEST_SYNC)
        if start < 0:
            buffer.clear()
            break
        del buffer[:start]
        if len(buffer) < REQUEST_LENGTH:
            break
        body = bytes(buffer[1:4])
        if crc8(body) == buffer[4]:
            bodies.append(body)
            del buffer[:REQUEST_LENGTH]
        else:
            del buffer[:1]
    return bodies


def serve_request(device: RegisterBus, body: bytes) -> bytes:
    """Perform one request (op, address, arg) on `device` and build the response frame."""
    op, address, arg = body
    try:
        if op == OP_READ and arg >= 1:
            data = device.read_registers(address, arg)
            if len(data) != arg:
                return encode_response(body, STATUS_DEVICE_FAULT)
            return encode_response(body, STATUS_OK, bytes(data))
        if op == OP_WRITE:
            device.write_register(address, arg)
            return encode_response(body, STATUS_OK)
        return encode_response(body, STATUS_BAD_REQUEST)
    except BusError:
        return encode_response(body, STATUS_NAK)
    except Exception:  # noqa: BLE001 - the bridge must keep serving
        return encode_response(body, STATUS_DEVICE_FAULT)


class PtyBridge:
    """Serve `device` on a new pty; `port_name` is the path a serial client opens."""

    def __init__(self, device: RegisterBus, rng: np.random.Generator | None = None) -> None:
        self.device = device
        self._rng = rng if rng is not None else np.random.default_rng(0)
        self.corrupt_rate = 0.0
        self.drop_rate = 0.0
        self.corrupt_next = 0
        self.requests = 0
        self.corrupted = 0
        self.dropped = 0
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)  # no echo, no line editing, 8-bit clean
        self.port_name = os.ttyname(self._slave)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self) -> PtyBridge:
        if self._thread is None:
            self._stop.clear()
            self._thread = threading.Thread(target=self._serve, name="pty-bridge", daemon=True)
            self._thread.start()
        return self

    def stop(self) -> None:
        """Stop serving and close the pty."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
            self._thread = None
        for fd in (self._master, self._slave):
            try:
                os.close(fd)
            except OSError:
                pass
        self._master = self._slave = -1

    def __enter__(self) -> PtyBridge:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    def _serve(self) -> None:
        buffer = bytearray()
        while not self._stop.is_set():
            ready, _, _ = select.select([self._master], [], [], _POLL_S)
            if not ready:
                continue
            try:
                chunk = os.read(self._master, 4096)
            except OSError:
                continue
            buffer += chunk
            for body in split_requests(buffer):
                self.requests += 1
                response = self._link_faults(serve_request(self.device, body))
                if response:
                    try:
                        os.write(self._master, response)
                    except OSError:
                        pass

    def _link_faults(self, response: bytes) -> bytes:
        if self.drop_rate > 0.0 and self._rng.random() < self.drop_rate:
            self.dropped += 1
            return b""
        if self.corrupt_next > 0 or (self.corrupt_rate > 0.0 and self._rng.random() < self.corrupt_rate):
            self.corrupt_next = max(0, self.corrupt_next - 1)
            self.corrupted += 1
            frame = bytearray(response)
            i = int(self._rng.integers(len(frame)))
            frame[i] ^= 1 << int(self._rng.integers(8))
            return bytes(frame)
        return response


class RealTimeDevice:
    """The simulator's chip in wall-clock time: before each transfer the simulation is advanced to
    the time elapsed since `start`, so a driver on the other side of the pty sees a live sensor.

    The wall clock (`clock`, the machine's monotonic clock that the flight software on the other side
    reads too) is the box's clock: with a scenario's [clock] (`hil.box_clock`) the world runs on true
    time, the box's clock reading ``sim.clock.start_s`` when the world starts and gaining its drift, as
    in SITL (`hil.sitl.box_t0_s`): after a wall time e the world is at ``sim.clock.true_s(start_s + e)``."""

    def __init__(self, sim, clock=None, start: float | None = None) -> None:
        """`clock`: the wall clock (default `time.monotonic`); `start`: its reading at which the world is at
        true time 0 (default: now)."""
        import time

        self.sim = sim
        self._clock = clock or time.monotonic
        self._t0 = self._clock() if start is None else float(start)

    def _sync(self) -> None:
        c = self.sim.clock
        self.sim.advance_to(max(self.sim.t_s, c.true_s(c.start_s + self._clock() - self._t0)))

    def read_registers(self, address: int, count: int) -> bytes:
        self._sync()
        return self.sim.sensor.read_registers(address, count)

    def write_register(self, address: int, value: int) -> None:
        self._sync()
        self.sim.sensor.write_register(address, value)


def main(argv: list[str] | None = None) -> int:
    """`python -m hil.pty_link`: the simulated debris and its MMC5983MA behind a pty, in real time.

    Prints the pty path; run the flight software against it with
    `python -m fsw.main --mag-serial PATH`.
    """
    import signal
    import sys
    import time

    from fsw.argtypes import ArgumentParser, finite_float, int_range

    from .scenario import ScenarioError, load
    from .sim import Simulator

    ap = ArgumentParser(prog="python -m hil.pty_link", description=main.__doc__.splitlines()[0])
    ap.add_argument("--scenario", default="isoi", metavar="NAME|FILE", help="scenario (default isoi)")
    ap.add_argument("--seed", type=int_range(0), default=0, help="random seed (default 0)")
    ap.add_argument("--duration", type=finite_float(0, min_exclusive=True), default=None, metavar="S",
                    help="stop after S seconds")
    ap.add_argument("--corrupt-rate", type=finite_float(0, 1), default=0.0,
                    help="probability a response is corrupted (0 to 1)")
    ap.add_argument("--drop-rate", type=finite_float(0, 1), default=0.0,
                    help="probability a response is dropped (0 to 1)")
    ap.add_argument("--quiet", action="store_true", help="print only the pty path")
    args = ap.parse_args(argv)
    try:
        scn = load(args.scenario)
    except ScenarioError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    sim = Simulator(scn, seed=args.seed, max_step_s=0.005)
    bridge = PtyBridge(RealTimeDevice(sim), rng=np.random.default_rng(args.seed))
    bridge.corrupt_rate, bridge.drop_rate = args.corrupt_rate, args.drop_rate
    stop = threading.Event()
    signal.signal(signal.SIGINT, lambda *a: stop.set())
    signal.signal(signal.SIGTERM, lambda *a: stop.set())
    with bridge:
        print(bridge.port_name, flush=True)
        t0 = time.monotonic()
        while not stop.wait(1.0):
            if not args.quiet:
                w = np.degrees(sim.body.omega_radps)
                print(f"t={sim.t_s:7.1f} s  true w=[{w[0]:7.2f} {w[1]:7.2f} {w[2]:7.2f}] dps  "
                      f"requests={bridge.requests}", flush=True)
            if args.duration is not None and time.monotonic() - t0 >= args.duration:
                break
    return 0


if __name__ == "__main__":
    from fsw.startup import exit_with

    exit_with(main)
