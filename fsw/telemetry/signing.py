"""MAVLink 2 message signing: the mission key, the signing clock and a verifier that cannot be locked out.

Frame (https://mavlink.io/en/guide/message_signing.html): a signed MAVLink 2 frame has bit 0x01 of
its incompatibility flags set and ends in a 13-byte block ``link_id (1) | timestamp (6, little
endian) | signature (6)``, with

    signature = SHA-256(secret_key + frame_without_signature)[:6]

where ``frame_without_signature`` is everything from the 0xFD start byte up to and including the
timestamp. The timestamp counts 10 µs since 2015-01-01 00:00 GMT and must grow strictly within a
stream, a stream being (sysid, compid, link_id). A new stream is accepted only if its timestamp is at
most one minute behind the receiver's own; after an accepted frame the receiver's timestamp is
raised to the frame's.

pymavlink (2.4.x, `MAVLink.check_signature`) stores a stream's timestamp *before* it compares the
signature. One forged frame carrying a far-future timestamp and any signature is enough to make every
later genuine frame of that stream "old": the genuine ground station is locked out until the forger
stops (never). :class:`Verifier` checks the signature first and touches no state unless it matches;
it also refuses signed timestamps that run more than `max_future_s` ahead of its own clock (a ground
station with a wrong clock would otherwise move the box's clock forward and make its own later frames
look replayed), when that clock is known to be set.

Keys: 32 bytes, stored as 64 hexadecimal characters and a newline in a file of mode 0600, created by
``python -m ground.keys new FILE``. :func:`load_key` refuses a file that others can read, that is not a
regular file, or whose key is all one byte (all zero: a placeholder anyone could sign with).
"""
from __future__ import annotations

import enum
import errno
import hashlib
import hmac
import os
import stat
import struct
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from ..files import write_atomic

KEY_BYTES = 32
SIGNATURE_BLOCK = 13
IFLAG_SIGNED = 0x01
HEADER_V2 = 10
STX_V2 = 0xFD
#: 1970-01-01 → 2015-01-01, s
UNIX_TO_MAVLINK_EPOCH_S = 1_420_070_400
#: signing timestamp units per second (10 µs)
TICKS_PER_S = 100_000
#: how far behind our clock a new stream may start (spec: one minute)
NEW_STREAM_WINDOW = 60 * TICKS_PER_S
TIMESTAMP_MAX = (1 << 48) - 1


class KeyFileError(ValueError):
    """A key file that cannot be used (missing, wrong size, readable by others)."""


def key_fingerprint(key: bytes) -> str:
    """A short public name for a key (first 8 hex digits of SHA-256 of the key): safe to print."""
    return hashlib.sha256(b"debris-box key fingerprint" + key).hexdigest()[:8]


#: a key file is 64 hex digits and a newline; anything much longer is not one
KEY_FILE_MAX_BYTES = 4096


def check_key(key: bytes, where: str = "key") -> None:
    """Refuse (KeyFileError) a key of the wrong size or with all bytes equal (all zero: an empty or
    placeholder key, which anyone could sign with)."""
    if len(key) != KEY_BYTES:
        raise KeyFileError(f"{where}: key has {len(key)} bytes, expected {KEY_BYTES}")
    if len(set(key)) == 1:
        raise KeyFileError(f"{where}: all {KEY_BYTES} bytes of the key are 0x{key[0]:02x}: not a secret; "
                           "create a key with python -m ground.keys new FILE")


def load_key(path: str | os.PathLike) -> bytes:
    """Read a key file written by `ground.keys`: 64 hex digits; the file must be a regular file (a FIFO
    or device is refused, never waited on) not accessible to group or others (like ssh's private keys),
    and the key not all one byte."""
    p = Path(path)
    try:
        fd = os.open(p, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
    except OSError as e:
        raise KeyFileError(f"{p}: cannot read key file: {e.strerror or e}") from None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise KeyFileError(f"{p}: not a regular file (a directory, FIFO or device): not a key file")
        if stat.S_IMODE(st.st_mode) & 0o077:
            raise KeyFileError(f"{p}: key file is accessible by others (mode {stat.S_IMODE(st.st_mode):04o}); "
                               f"chmod 600 {p}")
        raw = os.read(fd, KEY_FILE_MAX_BYTES + 1)
    except OSError as e:
        raise KeyFileError(f"{p}: cannot read key file: {e.strerror or e}") from None
    finally:
        os.close(fd)
    if len(raw) > KEY_FILE_MAX_BYTES:  # the rest was never read: it is no key file, whatever it begins with
        raise KeyFileError(f"{p}: more than {KEY_FILE_MAX_BYTES} bytes: not a key file "
                           f"(expected {2 * KEY_BYTES} hex digits)")
    try:
        key = bytes.fromhex(raw.decode("ascii").strip())
    except (UnicodeDecodeError, ValueError):
        raise KeyFileError(f"{p}: not a key file (expected {2 * KEY_BYTES} hex digits)") from None
    check_key(key, str(p))
    return key


def write_key(path: str | os.PathLike, key: bytes, *, overwrite: bool = False) -> None:
    """Create a key file of mode 0600 (never world-readable, not even for a moment). An existing file
    is replaced only with `overwrite`, and only if it is a regular file: a symbolic link, FIFO or
    device there is refused (never written through, never waited on). Raises FileExistsError when
    the file exists and `overwrite` is not given."""
    check_key(key, str(path))
    try:
        st = os.lstat(path)
    except FileNotFoundError:
        st = None
    if st is not None:
        if stat.S_ISLNK(st.st_mode):
            raise KeyFileError(f"{path}: is a symbolic link: a key is not written through it (give the file itself)")
        if not stat.S_ISREG(st.st_mode):
            raise KeyFileError(f"{path}: is not a regular file (a directory, FIFO or device)")
        if not overwrite:
            raise FileExistsError(errno.EEXIST, "file exists", str(path))
        write_atomic(path, key.hex() + "\n", permissions=0o600)
        return
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_NOFOLLOW", 0), 0o600)
    try:
        os.fchmod(fd, 0o600)
        os.write(fd, key.hex().encode("ascii") + b"\n")
    finally:
        os.close(fd)


def unix_to_timestamp(unix_s: float) -> int:
    """Signing timestamp (10 µs since 2015-01-01 GMT) of a Unix time."""
    return max(0, int((unix_s - UNIX_TO_MAVLINK_EPOCH_S) * TICKS_PER_S))


def signature(key: bytes, signed_part: bytes) -> bytes:
    """The 6-byte signature of a frame whose bytes up to and including the timestamp are `signed_part`."""
    return hashlib.sha256(key + signed_part).digest()[:6]


def is_signed(frame: bytes) -> bool:
    return len(frame) >= HEADER_V2 + 2 + SIGNATURE_BLOCK and frame[0] == STX_V2 and bool(frame[2] & IFLAG_SIGNED)


def signature_fields(frame: bytes) -> tuple[int, int, int, int]:
    """(sysid, compid, link_id, timestamp) of a signed MAVLink 2 frame."""
    link_id = frame[-SIGNATURE_BLOCK]
    lo, hi = struct.unpack_from("<IH", frame, len(frame) - 12)
    return frame[5], frame[6], link_id, lo | (hi << 32)


def sign_frame(key: bytes, frame: bytes, link_id: int, timestamp: int) -> bytes:
    """Sign an unsigned MAVLink 2 frame of a message the dialect knows: sets the flag, recomputes the
    CRC (it covers the incompatibility flags), appends the signature block."""
    from .dialect import mavlink

    b = bytearray(frame)
    b[2] |= IFLAG_SIGNED
    msgid = b[7] | (b[8] << 8) | (b[9] << 16)
    crc = mavlink.x25crc(bytes(b[1:-2]))
    crc.accumulate(bytes([mavlink.mavlink_map[msgid].crc_extra]))
    b[-2:] = struct.pack("<H", crc.crc)
    b += struct.pack("<BQ", link_id, timestamp)[:7]
    return bytes(b + signature(key, bytes(b)))


class Verdict(enum.Enum):
    OK = "ok"
    UNSIGNED = "unsigned"
    BAD_SIGNATURE = "bad_signature"
    REPLAY = "replay"  # timestamp not after the stream's last, or a new stream too old
    FUTURE = "future"  # timestamp too far ahead of our clock (counted with replays in telemetry)


@dataclass
class SigningClock:
    """The local signing timestamp, never below anything already sent or accepted: either `epoch`
    (the timestamp at loop time 0) plus loop time — deterministic, for simulation and tests — or,
    when `unix_time` is given (the program's outermost edge passes `time.time`), the wall clock, so
    that a simulation run faster than real time still signs with real time. `clock_set`: whether the
    clock is known to be right (enables the far-future check of `Verifier`)."""

    epoch: int = 0
    clock_set: bool = False
    last: int = 0
    unix_time: Callable[[], float] | None = None

    def now(self, now_s: float) -> int:
        base = unix_to_timestamp(self.unix_time()) if self.unix_time is not None else \
            self.epoch + int(now_s * TICKS_PER_S)
        self.last = max(self.last, min(base, TIMESTAMP_MAX))
        return self.last

    def advance_to(self, timestamp: int) -> None:
        self.last = max(self.last, timestamp)


@dataclass
class Verifier:
    """Checks signed frames against the mission key; per stream (sysid, compid, link_id) the last
    accepted timestamp. State changes only on an accepted frame.

    `window` = 0 (commands): a timestamp must be after the stream's last, strictly. `window` = n > 0
    (telemetry on the ground, where UDP may reorder): a timestamp up to n accepted frames behind the
    newest is also accepted once (the anti-replay window of IPsec, RFC 4303 §3.4.3); an exact repeat
    never is."""

    key: bytes
    clock: SigningClock = field(default_factory=SigningClock)
    max_future_s: float = 600.0
    window: int = 0
    streams: dict = field(default_factory=dict)
    counts: dict = field(default_factory=lambda: {v: 0 for v in Verdict})

    def check(self, frame: bytes, now_s: float) -> Verdict:
        """Verdict on one raw frame (as received, CRC already checked by the parser)."""
        v = self._check(bytes(frame), now_s)
        self.counts[v] += 1
        return v

    def _check(self, frame: bytes, now_s: float) -> Verdict:
        if not is_signed(frame):
            return Verdict.UNSIGNED
        if not hmac.compare_digest(signature(self.key, frame[:-6]), frame[-6:]):
            return Verdict.BAD_SIGNATURE
        sysid, compid, link_id, ts = signature_fields(frame)
        local = self.clock.now(now_s)
        stream = (sysid, compid, link_id)
        recent = self.streams.get(stream)
        if recent is not None:
            newest = recent[-1]
            if ts <= newest and not (self.window and ts >= recent[0] and ts not in recent):
                return Verdict.REPLAY
        elif ts + NEW_STREAM_WINDOW < local:
            return Verdict.REPLAY
        if self.clock.clock_set and ts > local + self.max_future_s * TICKS_PER_S:
            return Verdict.FUTURE
        if recent is None:
            recent = self.streams[stream] = deque(maxlen=max(self.window, 1))
        if recent and ts < recent[-1]:  # a late frame inside the window: keep the deque sorted
            items = sorted([*recent, ts])[-recent.maxlen:]
            recent.clear()
            recent.extend(items)
        else:
            recent.append(ts)
        self.clock.advance_to(ts)
        return Verdict.OK

    def last_timestamp(self, sysid: int, compid: int, link_id: int) -> int | None:
        recent = self.streams.get((sysid, compid, link_id))
        return recent[-1] if recent else None


def setup_outgoing(mav, key: bytes, clock: SigningClock, link_id: int = 0) -> None:
    """Make a pymavlink MAVLink object sign what it packs with `key`.

    Use that object only to pack: with a key set, its parser would run pymavlink's own
    `check_signature` (the lock-out above). Incoming frames go through a separate parser and
    :class:`Verifier`."""
    mav.signing.secret_key = key
    mav.signing.link_id = link_id
    mav.signing.sign_outgoing = True
    mav.signing.timestamp = max(mav.signing.timestamp, clock.last)


def sign_ready(mav, clock: SigningClock, now_s: float) -> None:
    """Before packing at `now_s`: the outgoing timestamp is at least the clock's (strictly increasing:
    pymavlink adds 1 per frame)."""
    ts = max(mav.signing.timestamp, clock.now(now_s))
    mav.signing.timestamp = ts
    clock.advance_to(ts)


def unix_clock(**kwargs) -> SigningClock:
    """A signing clock whose time argument is Unix time (the ground tools pass the wall clock or a
    tlog's time stamps)."""
    return SigningClock(epoch=-UNIX_TO_MAVLINK_EPOCH_S * TICKS_PER_S, **kwargs)
