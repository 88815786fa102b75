"""MAVLink frames out of a byte stream, with byte-wise resynchronisation.

pymavlink's robust parser, after a start byte (0xFD / 0xFE) whose frame fails its CRC, throws the
whole declared length away. A start byte inside line noise declares a random length (up to 280
bytes) and so swallows the good frames that follow it. :class:`Deframer` instead drops only that
one byte and looks again, so every intact frame in the stream is found, whatever noise precedes it.
Each candidate is checked before it is accepted:

- MAVLink 2 (0xFD): incompatibility flags other than "signed" → not a frame; known message id → the
  CRC with the message's CRC_EXTRA must match; then pymavlink's `decode` builds the message
  (signatures are not checked here: see `fsw.telemetry.signing`);
- MAVLink 1 (0xFE): the same without flags;
- an unknown message id has no CRC_EXTRA, so its CRC cannot be checked: the candidate is refused.
  A single flipped bit in the id of a real frame would otherwise let a damaged frame through; every
  message the box sends is in the dialect.

Bytes that are not part of an accepted frame are reported in runs, as pymavlink's BAD_DATA: reason
"invalid MAVLink CRC" when the run is exactly one frame long as declared by its own header (a frame
damaged on the way), else "Bad prefix" (noise). `ground.link_stats` counts both.

A candidate cut off by the end of the data waits for more bytes, unless a complete good frame
follows inside the data already there (then the candidate was noise): line noise before a command
never holds the command back. The signature block of a signed frame is not covered by its CRC: a
frame cut inside it takes its "signature" from whatever follows, so a signed candidate inside whose
last 13 bytes a complete good frame starts is refused. Nothing raises, whatever the bytes.
"""
from __future__ import annotations

from .dialect import mavlink

STX_V2, STX_V1 = 0xFD, 0xFE
HEADER_V2, HEADER_V1 = 10, 6
SIGNATURE_LEN = 13
MAX_FRAME = HEADER_V2 + 255 + 2 + SIGNATURE_LEN


def _x25(data: bytes, extra: int) -> int:
    crc = mavlink.x25crc(data)
    crc.accumulate(bytes([extra]))
    return crc.crc


class Deframer:
    """Feed bytes, get messages (and BAD_DATA for rejected bytes) in stream order."""

    def __init__(self) -> None:
        self._buf = bytearray()
        self._junk = bytearray()
        self._parser = mavlink.MAVLink(None)
        self.frames = 0
        self.junk_bytes = 0

    def feed(self, data: bytes) -> list:
        self._buf += data
        return self._scan(final=False)

    def flush(self) -> list:
        """End of the stream: whatever is left is either a frame or junk."""
        out = self._scan(final=True)
        out += self._emit_junk()
        return out

    def _frame_length(self, i: int) -> int | None:
        """Declared length of a frame starting at i; 0: not a frame; None: header incomplete."""
        b = self._buf
        stx = b[i]
        if stx == STX_V2:
            if len(b) - i < 3:
                return None
            if b[i + 2] & ~0x01:
                return 0
            return HEADER_V2 + b[i + 1] + 2 + (SIGNATURE_LEN if b[i + 2] & 0x01 else 0)
        if len(b) - i < 2:
            return None
        return HEADER_V1 + b[i + 1] + 2

    def _check(self, frame: bytes):
        """A message for an acceptable frame, else None."""
        v2 = frame[0] == STX_V2
        if v2:
            if len(frame) < HEADER_V2 + 2:
                return None
            msgid = frame[7] | (frame[8] << 8) | (frame[9] << 16)
            sig = SIGNATURE_LEN if frame[2] & 0x01 else 0
        else:
            msgid, sig = frame[5], 0
        cls = mavlink.mavlink_map.get(msgid)
        if cls is None:
            return None
        end = len(frame) - sig
        crc = frame[end - 2] | (frame[end - 1] << 8)
        if _x25(frame[1:end - 2], cls.crc_extra) != crc:
            return None
        try:
            return self._parser.decode(bytearray(frame))
        except Exception:  # noqa: BLE001 - a frame pymavlink cannot build is junk
            return None

    def _scan(self, final: bool) -> list:
        out: list = []
        b = self._buf
        i = 0
        n = len(b)
        while i < n:
            c = b[i]
            if c != STX_V2 and c != STX_V1:
                self._junk.append(c)
                i += 1
                continue
            length = self._frame_length(i)
            if length is None or (length and i + length > n):
                if not final and not self._complete_frame_after(i + 1):
                    break  # wait for more bytes
                length = 0  # at the end, or a good frame starts inside it: this start byte is noise
            if length:
                msg = self._check(bytes(b[i:i + length]))
                if msg is not None and c == STX_V2 and b[i + 2] & 0x01 \
                        and self._complete_frame_after(i + length - SIGNATURE_LEN, i + length):
                    msg = None  # cut inside its signature block (not covered by the CRC): the next frame starts there
                if msg is not None:
                    out += self._emit_junk()
                    out.append(msg)
                    self.frames += 1
                    i += length
                    continue
            self._junk.append(c)
            i += 1
        del b[:i]
        if len(self._junk) > 2 * MAX_FRAME:  # a long run of noise: report it now
            out += self._emit_junk()
        return out

    def _complete_frame_after(self, start: int, stop: int | None = None) -> bool:
        """Whether a complete, valid frame starts somewhere in [start, stop). Then an incomplete
        candidate before it is noise (a good frame does not sit inside another), and a command after
        line noise is not held up until more bytes arrive."""
        b = self._buf
        n = len(b)
        for j in range(start, n if stop is None else min(stop, n)):
            if b[j] != STX_V2 and b[j] != STX_V1:
                continue
            length = self._frame_length(j)
            if length and j + length <= n and self._check(bytes(b[j:j + length])) is not None:
                return True
        return False

    def _emit_junk(self) -> list:
        if not self._junk:
            return []
        junk = bytes(self._junk)
        self._junk.clear()
        self.junk_bytes += len(junk)
        reason = "Bad prefix"
        if junk[0] in (STX_V2, STX_V1) and len(junk) >= 3:
            self._buf, saved = bytearray(junk), self._buf
            declared = self._frame_length(0)
            self._buf = saved
            if declared == len(junk):
                reason = "invalid MAVLink CRC"
        return [mavlink.MAVLink_bad_data(junk, reason)]
