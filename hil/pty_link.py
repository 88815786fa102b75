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
