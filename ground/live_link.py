"""The ground station's live link (`ground.decode`): a UDP socket of its own or a pymavlink link, read as raw
bytes and framed by `fsw.telemetry.framing.Deframer`; a serial port that goes away is reopened."""
from __future__ import annotations

import select
import time
from typing import Callable

from fsw.telemetry import dialect
from fsw.telemetry.framing import Deframer, intact_frame
from fsw.telemetry.udp_link import UDP_MAX_PAYLOAD, UdpLink


class LiveLink:
    """A live link read as raw bytes and framed by the Deframer.

    A listening UDP link (`udpin:`) is our own socket (`fsw.telemetry.udp_link.UdpLink`), not
    pymavlink's: each pass waits up to 0.1 s, then drains every datagram waiting (up to
    `UDP_DRAIN_DATAGRAMS`), each read whole and deframed on its own (MAVLink over UDP never splits a
    frame, so a flood datagram cannot hold a genuine one back); the receive buffer asks for
    `UDP_RCVBUF_BYTES` (the kernel caps it at net.core.rmem_max) to ride out the time spent decoding.
    A flood of 0xFE, 0xFD or random bytes costs the deframer a few ns a byte. Other links (serial,
    tcp, udpout) through pymavlink; serial ports that fail are reopened (once a second)."""

    UDP_DRAIN_DATAGRAMS = 4096
    UDP_RCVBUF_BYTES = 4 << 20

    def __init__(self, url: str, baud: int, say: Callable[[str], None], *, raw: bool = False) -> None:
        """`raw`: `read` gives the intact frames as their bytes (CRC checked, not decoded: the caller decodes
        them, e.g. in bulk) and the junk as BAD_DATA messages; else pymavlink's messages."""
        self.url, self.baud, self.say, self.raw = url, baud, say, raw
        self.udp = url.startswith(("udpin:", "udp:"))
        self.conn = self._open()
        self.deframer = Deframer()
        self._retry_at = 0.0
        self.reconnects = 0

    def _open(self):
        if self.udp:
            return UdpLink(self.url, source_system=dialect.GCS_SYSID, source_component=dialect.GCS_COMPID,
                           input=True, max_datagram_bytes=UDP_MAX_PAYLOAD, rcvbuf_bytes=self.UDP_RCVBUF_BYTES)
        conn = dialect.open_link(self.url, source_system=dialect.GCS_SYSID, source_component=dialect.GCS_COMPID,
                                 input=True, baud=self.baud)
        conn.first_byte = False  # the dialect is bound already: no protocol auto-switch by pymavlink
        return conn

    def read(self) -> list:
        if self.udp:
            return self._read_udp()
        if self.conn is None:  # the port went away: try it again now and then
            if time.monotonic() < self._retry_at:
                time.sleep(0.1)
                return []
            try:
                self.conn = self._open()
                self.reconnects += 1
                self.say(f"{self.url}: reconnected")
            except OSError:
                self._retry_at = time.monotonic() + 1.0
                return []
        data = bytearray()
        try:
            self.conn.select(0.1)
            for _ in range(64):
                chunk = self.conn.recv(4096)
                if not chunk:
                    break
                data += chunk.encode("latin-1") if isinstance(chunk, str) else chunk
        except OSError as e:  # serial adapter unplugged: keep what came, reopen later
            self.say(f"{self.url}: {e}; reconnecting")
            try:
                self.conn.close()
            except OSError:
                pass
            self.conn = None
            self._retry_at = time.monotonic() + 1.0
        if not data:
            return []
        return self.deframer.feed_frames(bytes(data)) if self.raw else self.deframer.feed(bytes(data))

    def _read_udp(self) -> list:
        out: list = []
        try:
            ready, _, _ = select.select([self.conn.sock], [], [], 0.1)
            if not ready:
                return out
            datagrams = self.conn.read_datagrams(self.UDP_DRAIN_DATAGRAMS)
        except (OSError, ValueError) as e:  # interrupted, or a socket error the kernel reports
            self.say(f"{self.url}: {e}")
            time.sleep(0.1)
            return out
        if self.raw:
            feed = self.deframer.feed_frames
            for data, _addr, _size in datagrams:
                if intact_frame(data, self.deframer.mavlink1):
                    out.append(bytes(data))  # what the deframer finds in it, without its search
                else:
                    out += feed(data, end=True)
            return out
        for data, _addr, _size in datagrams:
            out += self.deframer.feed(data, end=True)  # a datagram holds whole frames
        return out

    def flush(self) -> list:
        return self.deframer.flush_frames() if self.raw else self.deframer.flush()

    def write(self, frame: bytes) -> None:
        """Send a frame back on the link (requests for missing samples); dropped while it is down."""
        if self.conn is None:
            return
        try:
            self.conn.write(frame)
        except OSError:
            pass

    def close(self) -> None:
        if self.conn is not None:
            self.conn.close()

