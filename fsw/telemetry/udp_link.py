"""UDP links read with bounded work: the box's `udpin:` / `udpout:` links, and the ground decoder's.

pymavlink's UDP connection (`mavutil.mavudp`) reads a whole datagram, up to 64 KB, whatever its
caller asks for, and in `udpin` mode copies everything it writes to every address that ever sent it a
datagram. :class:`UdpLink` instead

- reads into one preallocated buffer (`recvfrom_into`, no allocation but the datagram's own bytes),
  with MSG_TRUNC so that a datagram longer than the buffer is cut and its true size still known: the
  uplink drops it as a whole and counts its bytes;
- reads at most `max_datagrams` per call (:meth:`read_datagrams`): called once a loop tick, that bounds
  the cost of a packet flood; the kernel drops what overflows its receive buffer, and that count
  (Linux `SO_MEMINFO`) is :attr:`os_dropped`;
- writes `udpout:HOST:PORT` to HOST:PORT, and `udpin:HOST:PORT` only to :attr:`peer`, the one address
  the uplink found to be the ground station (`fsw.telemetry.peers`); before there is one a frame
  written goes nowhere and is counted in `unaddressed_writes` (UDP has no carrier: a datagram to
  nobody is not an error).

It offers what the flight software uses of a pymavlink connection (`mav`, `write`, `close`).
"""
from __future__ import annotations

import errno
import socket
import struct
import sys

from .dialect import mavlink, open_link

#: Linux: getsockopt(SOL_SOCKET, SO_MEMINFO) → 9 × u32, the last the socket's drop count
SO_MEMINFO = 55
_MEMINFO_LEN = 9 * 4
#: the largest payload of a UDP datagram over IPv4
UDP_MAX_PAYLOAD = 65507
#: the box reads datagrams up to this size; a ground station writes one frame (≤ 280 B) per datagram
BOX_DATAGRAM_BYTES = 2048
BOX_RCVBUF_BYTES = 256 * 1024


def is_udp_url(url: str) -> bool:
    return url.startswith(("udpin:", "udpout:", "udp:"))


def parse_udp_url(url: str, *, input: bool = False) -> tuple[bool, str, int]:
    """(listen, host, port) of `udpin:HOST:PORT`, `udpout:HOST:PORT` or `udp:HOST:PORT` (pymavlink's
    meaning: listens when `input`). ValueError for anything else."""
    scheme, _, rest = url.partition(":")
    host, sep, port = rest.rpartition(":")
    if scheme not in ("udpin", "udpout", "udp") or not sep or not host:
        raise ValueError(f"not a UDP link: {url!r} (udpin:HOST:PORT or udpout:HOST:PORT)")
    try:
        p = int(port)
    except ValueError:
        raise ValueError(f"{url}: port {port!r} is not a number") from None
    listen = scheme == "udpin" or (scheme == "udp" and input)
    if not (0 if listen else 1) <= p <= 65535:
        raise ValueError(f"{url}: port {p} out of range")
    return listen, host, p


class UdpLink:
    def __init__(self, url: str, *, source_system: int = 0, source_component: int = 0, input: bool = False,
                 max_datagram_bytes: int = BOX_DATAGRAM_BYTES, rcvbuf_bytes: int | None = BOX_RCVBUF_BYTES) -> None:
        """`url`: see :func:`parse_udp_url`; `max_datagram_bytes`: the read buffer; `rcvbuf_bytes`: the
        socket's receive buffer to ask for (the kernel caps it; None: the system default)."""
        self.url = url
        self.listening, host, port = parse_udp_url(url, input=input)
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            if rcvbuf_bytes:
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, int(rcvbuf_bytes))
            if self.listening:
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
                sock.bind((host, port))
                self.destination = None
            else:
                self.destination = (socket.gethostbyname(host), port)
            sock.setblocking(False)
        except OSError as e:
            sock.close()
            raise OSError(e.errno, f"{url}: {e.strerror or e}") from None
        self.sock = sock
        self.peer = None  # udpin: where writes go (set by the uplink)
        self._buf = bytearray(max(1, int(max_datagram_bytes)))
        self._view = memoryview(self._buf)
        self.mav = mavlink.MAVLink(self, srcSystem=source_system, srcComponent=source_component)
        self.datagrams = 0
        self.bytes = 0
        self.truncated = 0
        self.read_errors = 0
        self.unaddressed_writes = 0
        self._meminfo = sys.platform.startswith("linux")

    @property
    def rcvbuf_bytes(self) -> int:
        return self.sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF)

    def fileno(self) -> int:
        return self.sock.fileno()

    def read_datagrams(self, max_datagrams: int) -> list[tuple[bytes, tuple, int]]:
        """Up to `max_datagrams` datagrams waiting on the socket, oldest first, as (data, source
        address, true size); `data` is cut to the buffer when the size is larger. Never blocks."""
        out = []
        buf, view, size = self._buf, self._view, len(self._buf)
        recv = self.sock.recvfrom_into
        for _ in range(max_datagrams):
            try:
                n, addr = recv(buf, size, socket.MSG_TRUNC)
            except (BlockingIOError, InterruptedError):
                break
            except ConnectionRefusedError:  # an ICMP error for an earlier send: not a datagram
                self.read_errors += 1
                continue
            self.datagrams += 1
            self.bytes += n
            if n > size:
                self.truncated += 1
            out.append((bytes(view[:n if n < size else size]), addr, n))
        return out

    @property
    def os_dropped(self) -> int:
        """Datagrams the kernel dropped because the receive buffer was full (Linux; else 0)."""
        if not self._meminfo:
            return 0
        try:
            return struct.unpack("9I", self.sock.getsockopt(socket.SOL_SOCKET, SO_MEMINFO, _MEMINFO_LEN))[8]
        except OSError:  # an older kernel
            self._meminfo = False
            return 0

    def write(self, buf: bytes) -> int:
        """Send one frame to the destination (udpout) or the peer (udpin). OSError when the network
        refuses it (the caller counts it); 0 when there is nobody to send to yet (counted here)."""
        addr = self.destination if self.destination is not None else self.peer
        if addr is None:
            self.unaddressed_writes += 1
            return 0
        return self.send_to(buf, addr)

    def send_to(self, buf: bytes, addr) -> int:
        try:
            return self.sock.sendto(buf, addr)
        except BlockingIOError:  # the send buffer is full: the frame is lost like on a busy network
            raise OSError(errno.ENOBUFS, "UDP send buffer full") from None

    def close(self) -> None:
        self._view.release()
        self.sock.close()


def open_box_link(url: str, *, source_system: int, source_component: int, input: bool = False, **kwargs):
    """The flight software's link: :class:`UdpLink` for UDP, any other pymavlink connection string
    (serial, tcp) through `fsw.telemetry.dialect.open_link`."""
    if is_udp_url(url):
        return UdpLink(url, source_system=source_system, source_component=source_component, input=input)
    return open_link(url, source_system=source_system, source_component=source_component, input=input, **kwargs)
