"""MAVLink frames out of a byte stream, with byte-wise resynchronisation, at bounded cost per byte.

pymavlink's robust parser, after a start byte (0xFD / 0xFE) whose frame fails its CRC, throws the
whole declared length away. A start byte inside line noise declares a random length (up to 280
bytes) and so swallows the good frames that follow it. :class:`Deframer` instead drops only that
one byte and looks again, so every intact frame in the stream is found, whatever noise precedes it.

MAVLink 2 only by default: the project's links speak nothing else (`fsw.telemetry.dialect`), and a
command must be signed, which MAVLink 1 cannot be; 0xFE is then an ordinary byte. `mavlink1=True`
accepts MAVLink 1 frames as well.

Cost. Hostile input must not be expensive: a regular expression finds the next place where a frame
can begin (C speed, no Python loop over bytes), and a candidate must pass cheap header checks before
any CRC is computed:

- MAVLink 2 (0xFD): payload length ≥ 1 (senders truncate trailing zero bytes but never the first),
  incompatibility flags none but "signed", a message id of the dialect, a payload length that message
  can have (at most its full length with extensions);
- MAVLink 1 (0xFE, with ``mavlink1=True``): a message id of the dialect and exactly its length
  (MAVLink 1 never truncates: the base fields, or with extensions as pymavlink packs them);
- an unknown message id has no CRC_EXTRA, so its CRC cannot be checked: the candidate is refused. A
  single flipped bit in the id of a real frame would otherwise let a damaged frame through; every
  message the box sends is in the dialect.

Then the CRC with the message's CRC_EXTRA (`fastcrc`, the C CRC pymavlink itself depends on: 0.3 µs
a frame against 2.4 µs through pymavlink's `x25crc` object), then pymavlink's `decode` builds the
message (signatures are not checked here: see `fsw.telemetry.signing`). A flood of 0xFE, 0xFD or
random bytes costs no CRC at all (`crc_checks` counts them) and a few ns a byte (1 MB: 0xFE 4 ms,
0xFD 30 ms, random 4 ms, against 7.6 s, 0.6 s and 0.2 s byte by byte); a crafted flood of
valid-looking headers costs one CRC per candidate (one per 5 bytes at most in a periodic pattern).
:meth:`Deframer.feed_frames` stops before decoding, so that a caller can check a frame's signature on
the raw bytes and decode only what it will use (`fsw.telemetry.uplink`).

Bytes that are not part of an accepted frame are reported in runs, as pymavlink's BAD_DATA: reason
"invalid MAVLink CRC" when the run is exactly one frame long as declared by its own header (a frame
damaged on the way), else "Bad prefix" (noise). `ground.link_stats` counts both.

A candidate cut off by the end of the data waits for more bytes, unless a complete good frame
follows inside the data already there (then the candidate was noise): line noise before a command
never holds the command back. At most one frame length (280 bytes) waits. The signature block of a
signed frame is not covered by its CRC: a frame cut inside it takes its "signature" from whatever
follows, so a signed candidate inside whose last 13 bytes a complete good frame starts is refused.
When a frame that has not arrived whole may start inside those 13 bytes, the signed frame is passed
on at once (a genuine one is not held back) and its last bytes from that start byte on are looked at
again with what follows: a command whose first bytes went into a cut frame's "signature" is still
found (they are then counted twice, in the frame and in the junk, when no frame starts there).
Two valid frames that overlap cannot both be real, and one CRC-16 in 65,536 matches by chance (a
flood of valid-looking headers in front of a frame makes it happen): a frame followed neither by a
start byte nor by the end of the data, inside which a complete good frame starts that runs past it and
is so followed, is refused for that later frame. When the later frame has not arrived whole, the
earlier one is passed on (nothing is held back on a guess).
Nothing raises, whatever the bytes.
"""
from __future__ import annotations

import re
import struct

from .dialect import mavlink

try:  # pymavlink's dependency for its own CRC: a C implementation of CRC-16/MCRF4XX
    from fastcrc.crc16 import mcrf4xx as _mcrf4xx
except ImportError:  # pragma: no cover - pymavlink falls back to pure Python too
    _mcrf4xx = None

STX_V2, STX_V1 = 0xFD, 0xFE
HEADER_V2, HEADER_V1 = 10, 6
SIGNATURE_LEN = 13
MAX_FRAME = HEADER_V2 + 255 + 2 + SIGNATURE_LEN
IFLAG_SIGNED = 0x01

_BAD_CRC = "invalid MAVLink CRC"
_NOISE = "Bad prefix"
_UNDECODABLE = "undecodable MAVLink frame"


def _payload_lengths(cls) -> tuple[int, int]:
    """(base, full) payload length of a generated message class: full with the MAVLink 2 extension
    fields, base without them (what MAVLink 1 carries). The extension fields are the last of the wire
    order and the constructor's arguments with defaults (pymavlink's mavgen)."""
    fmt = bytes(cls.native_format).decode("ascii")[1:]
    sizes = [struct.calcsize("<" + c) * max(1, n) for c, n in zip(fmt, cls.array_lengths, strict=True)]
    n_ext = len(cls.__init__.__defaults__ or ())
    full = cls.unpacker.size
    return full - sum(sizes[len(sizes) - n_ext:]) if n_ext else full, full


#: message id → (CRC_EXTRA, base payload length, full payload length)
MESSAGES: dict[int, tuple[int, int, int]] = {
    mid: (cls.crc_extra, *_payload_lengths(cls)) for mid, cls in mavlink.mavlink_map.items()}


def crc_x25(data, extra: int) -> int:
    """MAVLink's CRC (CRC-16/MCRF4XX) of `data` followed by the CRC_EXTRA byte."""
    if _mcrf4xx is not None:
        return _mcrf4xx(bytes((extra,)), _mcrf4xx(data, 0xFFFF))
    crc = mavlink.x25crc(bytes(data))
    crc.accumulate(bytes((extra,)))
    return crc.crc


def frame_header(b, i: int, n: int, mavlink1: bool = True):
    """The header at b[i] (a start byte) under the cheap checks: (frame length, CRC_EXTRA), or None
    while the header is incomplete in b[:n], or (0, 0) when it cannot begin a frame."""
    left = n - i
    if b[i] == STX_V2:
        if left >= 2 and b[i + 1] == 0:
            return 0, 0
        if left < 3:
            return None
        if b[i + 2] & ~IFLAG_SIGNED:
            return 0, 0
        if left < HEADER_V2:
            return None
        info = MESSAGES.get(b[i + 7] | (b[i + 8] << 8) | (b[i + 9] << 16))
        if info is None or b[i + 1] > info[2]:
            return 0, 0
        return HEADER_V2 + b[i + 1] + 2 + (SIGNATURE_LEN if b[i + 2] & IFLAG_SIGNED else 0), info[0]
    if b[i] != STX_V1 or not mavlink1:
        return 0, 0
    if left < HEADER_V1:
        return None
    info = MESSAGES.get(b[i + 5])
    if info is None or (b[i + 1] != info[1] and b[i + 1] != info[2]):
        return 0, 0
    return HEADER_V1 + b[i + 1] + 2, info[0]


def _byte_class(values) -> bytes:
    return b"[" + b"".join(b"\\x%02x" % v for v in sorted(values)) + b"]"


def candidate_pattern(mavlink1: bool = True) -> re.Pattern:
    """A regular expression that matches a complete header that can begin a frame, consistent with
    :func:`frame_header` (for MAVLink 2 the message id only byte-wise, the payload length not against
    the message). It skips floods of 0xFD, 0xFE or random bytes at C speed; :func:`frame_header` then
    checks each match exactly. (Headers cut off by the end of the data are looked at by
    :class:`Deframer` itself.)"""
    ids = list(MESSAGES)
    low, mid, high = ({(m >> s) & 0xFF for m in ids} for s in (0, 8, 16))
    v2 = rb"\xfd[\x01-\xff][\x00\x01][\s\S]{4}" + _byte_class(low) + _byte_class(mid) + _byte_class(high)
    if not mavlink1:
        return re.compile(v2)
    by_length: dict[int, set[int]] = {}
    for m in ids:
        if m < 256:
            for n in MESSAGES[m][1:]:
                by_length.setdefault(n, set()).add(m)
    v1 = rb"\xfe(?:" + b"|".join(b"\\x%02x[\\s\\S]{3}" % n + _byte_class(by_length[n])
                                 for n in sorted(by_length)) + b")"
    return re.compile(v2 + b"|" + v1)


def _whole_frame_header(data: bytes, mavlink1: bool):
    """(length, CRC extra) of the frame `data` is exactly, by its header; None if it is not one."""
    if not data:
        return None
    head = frame_header(data, 0, len(data), mavlink1)
    return head if head is not None and head[0] == len(data) else None


def whole_frame(data: bytes, mavlink1: bool = True) -> bool:
    """Whether `data` (one UDP datagram, say) is exactly one frame by its header (no CRC computed):
    the shape of every datagram a MAVLink sender writes. O(1)."""
    return _whole_frame_header(data, mavlink1) is not None


def intact_frame(data: bytes, mavlink1: bool = True) -> bool:
    """Whether `data` is exactly one frame by its header and its CRC is right: a datagram the deframer
    would give back whole, taken as it is without the deframer's search (a receiver's common case)."""
    head = _whole_frame_header(data, mavlink1)
    if head is None:
        return False
    end = head[0] - (SIGNATURE_LEN if data[0] == STX_V2 and data[2] & IFLAG_SIGNED else 0)
    return crc_x25(data[1:end - 2], head[1]) == data[end - 2] | (data[end - 1] << 8)


_PATTERNS = {True: candidate_pattern(True), False: candidate_pattern(False)}


class Deframer:
    """Feed bytes, get messages (and BAD_DATA for rejected bytes) in stream order.

    `mavlink1=False`: only MAVLink 2 frames (0xFE is then an ordinary byte). Counters: `frames`
    accepted, `junk_bytes` reported as BAD_DATA, `crc_checks` CRCs computed (the cost of hostile
    input: none for bytes that fail the header checks)."""

    def __init__(self, *, mavlink1: bool = False) -> None:
        self._buf = bytearray()
        self._junk = bytearray()
        self._parser = mavlink.MAVLink(None)
        self.mavlink1 = mavlink1
        self._search = _PATTERNS[mavlink1].search
        self.frames = 0
        self.junk_bytes = 0
        self.crc_checks = 0
        self._check_budget: int | None = None
        self.starved = False

    @property
    def check_budget(self) -> int | None:
        """CRCs the deframer may still compute (None: no limit). When a candidate needs one more, the
        deframer is `starved`: it stops where it is, and the caller can :meth:`discard` the rest."""
        return self._check_budget

    @check_budget.setter
    def check_budget(self, n: int | None) -> None:
        self._check_budget = n
        self.starved = False

    def discard(self) -> int:
        """Throw away the bytes not yet scanned (after starving): their number."""
        n = len(self._buf)
        self._buf.clear()
        return n

    # --- messages --------------------------------------------------------------------------------
    def feed(self, data: bytes, *, end: bool = False) -> list:
        """The messages (and BAD_DATA) in the stream so far; `end`: the stream ends with `data` (a
        datagram, a tlog record, a file), as :meth:`flush` after it, but nothing is looked at twice."""
        return [self.decode(x) if isinstance(x, bytes) else x for x in self.feed_frames(data, end=end)]

    def flush(self) -> list:
        """End of the stream: whatever is left is either a frame or junk."""
        return [self.decode(x) if isinstance(x, bytes) else x for x in self.flush_frames()]

    def decode(self, frame: bytes):
        """The pymavlink message of a frame from :meth:`feed_frames` (BAD_DATA if pymavlink cannot
        build it, which the header checks make impossible for the dialect's messages)."""
        try:
            return self._parser.decode(bytearray(frame))
        except Exception:  # noqa: BLE001 - a frame pymavlink cannot build is junk
            return mavlink.MAVLink_bad_data(bytearray(frame), _UNDECODABLE)

    # --- raw frames ------------------------------------------------------------------------------
    def feed_frames(self, data: bytes, *, end: bool = False) -> list:
        """Like :meth:`feed`, but intact frames come as their raw bytes (CRC checked, not decoded)."""
        self._buf += data
        return self.flush_frames() if end else self._scan(final=False)

    def flush_frames(self) -> list:
        out = self._scan(final=True)
        out += self._emit_junk()
        return out

    def _header(self, i: int, n: int):
        return frame_header(self._buf, i, n, self.mavlink1)

    def _candidate(self, i: int, n: int, stop: int | None = None) -> int:
        """The first position in [i, stop) (default: to n) where a frame can begin in b[:n]: a
        complete header that passes the regular expression, or a start byte within the last
        HEADER_V2 - 1 bytes whose partial header does not rule a frame out; -1 if there is none."""
        b = self._buf
        stop = n if stop is None else min(stop, n)
        tail = max(n - HEADER_V2 + 1, 0)  # from here on a MAVLink 2 header cannot be complete
        limit = min(stop, tail)
        if i < limit:
            m = self._search(b, i, limit + HEADER_V2 - 1)
            if m is not None and m.start() < limit:
                return m.start()
            i = limit
        while i < stop:
            j = self._find_stx(b, i, stop)
            if j < 0:
                return -1
            head = self._header(j, n)
            if head is None or head[0]:
                return j
            i = j + 1
        return -1

    def _find_stx(self, b, i: int, stop: int) -> int:
        j = b.find(STX_V2, i, stop)
        if self.mavlink1:
            k = b.find(STX_V1, i, stop)
            if k >= 0 and (j < 0 or k < j):
                return k
        return j

    def _crc_ok(self, i: int, length: int, extra: int) -> bool:
        if self._check_budget is not None:
            if self._check_budget <= 0:
                self.starved = True
                return False
            self._check_budget -= 1
        b = self._buf
        end = i + length - (SIGNATURE_LEN if b[i] == STX_V2 and b[i + 2] & IFLAG_SIGNED else 0)
        self.crc_checks += 1
        return crc_x25(b[i + 1:end - 2], extra) == b[end - 2] | (b[end - 1] << 8)

    def _scan(self, final: bool) -> list:
        out: list = []
        b = self._buf
        n = len(b)
        i = 0
        while i < n and not self.starved:
            j = self._candidate(i, n)
            if j < 0:
                self._junk += b[i:]
                i = n
                break
            if j > i:
                self._junk += b[i:j]
                i = j
            head = self._header(i, n)
            if head is None or (head[0] and i + head[0] > n):
                if not final and not self._complete_frame_after(i + 1):
                    break  # wait for more bytes
                head = (0, 0)  # at the end, or a good frame starts inside it: this start byte is noise
            length = head[0]
            signed = length and b[i] == STX_V2 and b[i + 2] & IFLAG_SIGNED
            ok = length and self._crc_ok(i, length, head[1]) and not (
                signed and self._complete_frame_after(i + length - SIGNATURE_LEN, i + length)) and not (
                not self._followed_well(i + length) and self._later_frame_overlaps(i + 1, i + length))
            # (a signed frame cut inside its signature block, not covered by the CRC, is refused: the
            # next frame starts there; so is a chance CRC match in noise that runs into a good frame)
            if self.starved:
                break  # out of CRCs: undecided, left for discard()
            if ok:
                out += self._emit_junk()
                out.append(bytes(b[i:i + length]))
                self.frames += 1
                # a frame whose rest has not arrived may start inside the signature block: those bytes are
                # looked at again (the frame may be one cut inside its signature, that frame the next)
                j = self._frame_may_start(i + length - SIGNATURE_LEN, i + length) if signed and not final else -1
                i = j if j >= 0 else i + length
                continue
            self._junk.append(b[i])
            i += 1
        del b[:i]
        if len(self._junk) > 2 * MAX_FRAME:  # a long run of noise: report it now
            out += self._emit_junk()
        return out

    def _frame_may_start(self, start: int, stop: int) -> int:
        """The first place in [start, stop) where a frame whose end has not arrived yet may start (a
        start byte whose header is incomplete, or passes the header checks and declares a frame longer
        than the data), or -1."""
        n = len(self._buf)
        j = start
        while j < stop:
            j = self._candidate(j, n, stop)
            if j < 0:
                return -1
            head = self._header(j, n)
            if head is None or (head[0] and j + head[0] > n):
                return j
            j += 1
        return -1

    def _followed_well(self, end: int) -> bool:
        """Whether a frame ending at `end` is followed as frames on a link are: by a start byte, or by
        the end of the data so far (a datagram, a chunk)."""
        b = self._buf
        return end >= len(b) or b[end] == STX_V2 or (self.mavlink1 and b[end] == STX_V1)

    def _later_frame_overlaps(self, start: int, end: int) -> bool:
        """Whether a complete, valid frame starts in [start, end), runs past `end` and is followed well.
        Two valid frames that overlap cannot both be real; the one whose end meets the next frame (or
        the end of the data) is, the other a CRC that matched by chance (1 in 65,536 a candidate: a
        flood of valid-looking headers in front of a frame makes it happen)."""
        return self._complete_frame_after(start, end, past=end)

    def _complete_frame_after(self, start: int, stop: int | None = None, past: int | None = None) -> bool:
        """Whether a complete, valid frame starts somewhere in [start, stop) (and, given `past`, ends after
        it and is followed well). Then an incomplete candidate before it is noise (a good frame does not
        sit inside another), and a command after line noise is not held up until more bytes arrive."""
        b = self._buf
        n = len(b)
        stop = n if stop is None else min(stop, n)
        j = start
        while j < stop:
            j = self._candidate(j, n, stop)
            if j < 0:
                return False
            head = self._header(j, n)
            if head is not None and head[0] and j + head[0] <= n and (past is None or j + head[0] > past) \
                    and self._crc_ok(j, *head) and (past is None or self._followed_well(j + head[0])):
                return True
            j += 1
        return False

    def _emit_junk(self) -> list:
        if not self._junk:
            return []
        junk = bytes(self._junk)
        self._junk.clear()
        self.junk_bytes += len(junk)
        return [mavlink.MAVLink_bad_data(junk, _BAD_CRC if self._declared_length(junk) == len(junk) else _NOISE)]

    def _declared_length(self, junk: bytes) -> int:
        """The length a run's first byte declares as a frame header, lenient (a damaged frame may have
        a damaged message id): 0 if it is no start byte."""
        if len(junk) < 3:
            return 0
        if junk[0] == STX_V2:
            return 0 if junk[2] & ~IFLAG_SIGNED else \
                HEADER_V2 + junk[1] + 2 + (SIGNATURE_LEN if junk[2] & IFLAG_SIGNED else 0)
        if junk[0] == STX_V1 and self.mavlink1:
            return HEADER_V1 + junk[1] + 2
        return 0
