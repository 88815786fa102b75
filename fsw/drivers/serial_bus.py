"""Register bus over a serial line: a small framed bridge protocol, like a USB-I2C bridge.

The host (this module) sends one request and waits for its response; the bridge at the other end
(`hil.pty_link.PtyBridge` in simulation, a microcontroller on hardware) performs the register
transfer on its I2C/SPI bus.

Request, 5 bytes:

    0xA5  op  address  arg  crc

    op   0x52 'R': burst read of `arg` (1...255) registers from `address`
         0x57 'W': write the byte `arg` to register `address`
    crc  CRC-8 of op, address, arg

Response:

    0x5A  status  data...  crc

    status  0x00 OK, 0x01 NAK (device did not acknowledge / transfer failed),
            0x02 BAD_REQUEST (unknown op or count 0), 0x03 DEVICE_FAULT (bridge-side failure)
    data    `arg` bytes for an OK read, nothing otherwise
    crc     CRC-8 of op, address, arg (of the request being answered), status, data

The response CRC covers the request it answers although those bytes are not resent, so a late or
stray response to another request fails the check instead of being taken for this one's answer.
CRC-8 is the SMBus PEC polynomial x^8 + x^2 + x + 1 (0x07), initial value 0, no reflection
(check value 0xF4 for b"123456789").

A request whose CRC fails is dropped silently by the bridge (its header cannot be trusted); the
host then times out. After any failure the host discards whatever is left in its input buffer
before the next request, which resynchronises the stream. Every failure is a `BusError`.
"""

from __future__ import annotations

import serial

from fsw.bus import BusError

REQUEST_SYNC = 0xA5
RESPONSE_SYNC = 0x5A
OP_READ = 0x52
OP_WRITE = 0x57
STATUS_OK = 0x00
STATUS_NAK = 0x01
STATUS_BAD_REQUEST = 0x02
STATUS_DEVICE_FAULT = 0x03
STATUS_NAMES = {
    STATUS_OK: "OK",
    STATUS_NAK: "NAK",
    STATUS_BAD_REQUEST: "BAD_REQUEST",
    STATUS_DEVICE_FAULT: "DEVICE_FAULT",
}
REQUEST_LENGTH = 5
MAX_SYNC_HUNT = 64
"""Bytes the host skips looking for a response SYNC before declaring the response lost."""


def _crc8_table() -> bytes:
    table = bytearray(256)
    for i in range(256):
        c = i
        for _ in range(8):
            c = ((c << 1) ^ 0x07) & 0xFF if c & 0x80 else (c << 1) & 0xFF
        table[i] = c
    return bytes(table)


_CRC8_TABLE = _crc8_table()


def crc8(data: bytes, crc: int = 0) -> int:
    """CRC-8/SMBus (poly 0x07, init 0): `crc8(b"123456789") == 0xF4`; chain with `crc`."""
    table = _CRC8_TABLE
    for byte in data:
        crc = table[crc ^ byte]
    return crc


def encode_request(op: int, address: int, arg: int) -> bytes:
    body = bytes((op, address, arg))
    return bytes((REQUEST_SYNC,)) + body + bytes((crc8(body),))


def encode_response(request_body: bytes, status: int, data: bytes = b"") -> bytes:
    """Response frame to the request whose op, address, arg are `request_body`."""
    payload = bytes((status,)) + data
    return bytes((RESPONSE_SYNC,)) + payload + bytes((crc8(payload, crc8(request_body)),))


class SerialBus:
    """`RegisterBus` over the bridge protocol on a serial port (pyserial)."""

    def __init__(self, port: str, baudrate: int = 115200, timeout_s: float = 0.05) -> None:
        self._port = serial.Serial(port, baudrate=baudrate, timeout=timeout_s, write_timeout=timeout_s)
        self.timeouts = 0
        self.crc_errors = 0
        self.status_errors = 0

    def read_registers(self, address: int, count: int) -> bytes:
        if not (0 <= address <= 0xFF and 1 <= count <= 0xFF):
            raise ValueError(f"bad read of {count} registers at {address}")
        return self._transfer(OP_READ, address, count, count)

    def write_register(self, address: int, value: int) -> None:
        if not (0 <= address <= 0xFF and 0 <= value <= 0xFF):
            raise ValueError(f"bad write of {value} at {address}")
        self._transfer(OP_WRITE, address, value, 0)

    def close(self) -> None:
        self._port.close()

    def __enter__(self) -> SerialBus:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _transfer(self, op: int, address: int, arg: int, n_data: int) -> bytes:
        port = self._port
        request = encode_request(op, address, arg)
        try:
            port.reset_input_buffer()  # drop anything left from a failed exchange
            port.write(request)
            for _ in range(MAX_SYNC_HUNT):
                sync = port.read(1)
                if not sync:
                    break
                if sync[0] == RESPONSE_SYNC:
                    break
            else:
                sync = b""
            if not sync or sync[0] != RESPONSE_SYNC:
                self.timeouts += 1
                raise BusError(f"bridge timeout: no response to op {op:#04x} at {address:#04x}")
            status = port.read(1)
            if not status:
                self.timeouts += 1
                raise BusError("bridge timeout in response header")
            n = n_data if status[0] == STATUS_OK else 0
            rest = port.read(n + 1)
            if len(rest) != n + 1:
                self.timeouts += 1
                raise BusError(f"bridge timeout: {len(rest)} of {n + 1} response bytes")
        except serial.SerialException as error:
            raise BusError(f"serial port: {error}") from error
        payload = status + rest[:n]
        if crc8(payload, crc8(request[1:4])) != rest[n]:
            self.crc_errors += 1
            port.reset_input_buffer()
            raise BusError("bridge response CRC error")
        if status[0] != STATUS_OK:
            self.status_errors += 1
            name = STATUS_NAMES.get(status[0], f"{status[0]:#04x}")
            raise BusError(f"bridge status {name} for op {op:#04x} at {address:#04x}")
        return bytes(rest[:n])
