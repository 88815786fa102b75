"""The sample messages decoded in bulk: for the recordings' export of an archive's interval and for the
ground station's ingest.

An hour of a box is about 110,000 sample frames (DEBRIS_MAG_SAMPLE, DEBRIS_RATE_ESTIMATE,
DEBRIS_SIM_STATE, HIGHRES_IMU: `ground.decode.SAMPLE_MESSAGES`); ten boxes at 100 samples/s send 3,000 a
second. Decoding them one by one with pymavlink (an object a frame), then rounding each float to its
float32 decimal (`ground.decode.f32`) one value at a time, was most of the time of both. Here the frames of
one message id are grouped by length and start byte, checked at once (length; CRC-16/MCRF4XX with the
message's CRC extra, as pymavlink checks it, computed byte column by byte column over all the frames; not
again for frames the deframer checked) and unpacked at once with NumPy (a structured dtype made from the
bindings' own struct format, truncated MAVLink 2 payloads padded with zeros as the protocol says); for the
export the fields `ground.decode.F32_FIELDS` names are rounded at once (NumPy's float32 text, the same
shortest decimal `f32` gives; the distinct values only). Each frame becomes a named tuple of its message
(`_message_class`): the fields as attributes, its frame and header, pymavlink's accessors. The decoder
takes them as they are (`Decoder(rounded=True)`), the station's views and archive as pymavlink's messages
(`decode_frames`). A frame that fails a check is left to pymavlink (`decode` gives BAD_DATA), as before.
"""
from __future__ import annotations

import re
from collections import namedtuple

import numpy as np
from fsw.telemetry.dialect import mavlink

from ..decode import F32_FIELDS, SAMPLE_MESSAGES

_NUMPY = {"Q": "u8", "q": "i8", "I": "u4", "i": "i4", "H": "u2", "h": "i2", "B": "u1", "b": "i1",
          "f": "f4", "d": "f8"}


class Sample:
    """A decoded message: its fields as attributes, its header (read from its frame) and bytes through
    pymavlink's accessors (without fields: a frame the export only counts)."""

    def __init__(self, frame: bytes, msg_type: str, msgid: int, fields: dict) -> None:
        self.__dict__.update(fields)
        self._frame, self._type, self._id = frame, msg_type, msgid
        self._seq, self._sys, self._comp = frame[4:7] if frame[0] == 0xFD else frame[2:5]

    def get_type(self) -> str:
        return self._type

    def get_msgbuf(self) -> bytes:
        return self._frame

    def get_seq(self) -> int:
        return self._seq

    def get_srcSystem(self) -> int:
        return self._sys

    def get_srcComponent(self) -> int:
        return self._comp

    def get_msgId(self) -> int:
        return self._id


def _message_class(name: str, msgid: int, fields: list[str]) -> type:
    """A decoded message of one type as a named tuple: its fields, then its frame and header; pymavlink's
    accessors (as `Sample`)."""
    base = namedtuple(name, [*fields, "frame_", "seq_", "sysid_", "compid_"])

    class Message(base):
        __slots__ = ()

        def get_type(self) -> str:
            return name

        def get_msgId(self) -> int:
            return msgid

        def get_msgbuf(self) -> bytes:
            return self.frame_

        def get_seq(self) -> int:
            return self.seq_

        def get_srcSystem(self) -> int:
            return self.sysid_

        def get_srcComponent(self) -> int:
            return self.compid_

    Message.__name__ = Message.__qualname__ = name
    return Message


class _Layout:
    """One message's wire layout as a NumPy dtype, and what the decoder reads of it."""

    def __init__(self, msgid: int, cls) -> None:
        fmt = cls.unpacker.format
        if fmt[0] != "<":
            raise ValueError(f"{cls.msgname}: not a little-endian layout")
        items = re.findall(r"(\d*)([A-Za-z])", fmt[1:])
        if len(items) != len(cls.ordered_fieldnames) or any(code not in _NUMPY for _, code in items):
            raise ValueError(f"{cls.msgname}: a field NumPy cannot read in bulk")
        self.name = cls.msgname
        self.size = cls.unpacker.size
        self.crc_extra = cls.crc_extra
        self.fields = list(cls.ordered_fieldnames)
        self.arrays = {n: int(count) for (count, _), n in zip(items, self.fields) if count}
        self.dtype = np.dtype([(n, "<" + _NUMPY[code], (int(count),)) if count else (n, "<" + _NUMPY[code])
                               for (count, code), n in zip(items, self.fields)])
        self.rounded = F32_FIELDS.get(self.name, ())
        self.floats = {n for (_, code), n in zip(items, self.fields) if code in "fd"}
        self.message = _message_class(self.name, msgid, self.fields)


def _layouts() -> dict[int, _Layout]:
    return {msgid: _Layout(msgid, cls) for msgid, cls in mavlink.mavlink_map.items() if cls.msgname in SAMPLE_MESSAGES}


#: the sample messages by id
LAYOUTS = _layouts()


def _f32_decimals_by_text(values: np.ndarray) -> np.ndarray:
    """`ground.decode.f32` of every value: float32's shortest decimal (NumPy's text of it), as float64. Each
    distinct bit pattern is written once (by bits, not by value: −0.0 stays −0.0 beside +0.0)."""
    bits = np.ascontiguousarray(values, dtype=np.float32).ravel().view(np.uint32)
    unique, inverse = np.unique(bits, return_inverse=True)
    with np.errstate(invalid="ignore"):
        return unique.view(np.float32).astype(str).astype(np.float64)[inverse].reshape(np.shape(values))


#: 10⁻²² … 10²², each exact in float64
_P10 = 10.0 ** np.arange(-22, 23)


def _f32_decimals(values: np.ndarray) -> np.ndarray:
    """`_f32_decimals_by_text` without the text, for values of magnitude 10⁻¹² … 10¹³: for p = 1 … 9 digits,
    the two p-digit decimals m·10⁻ˢ around the value (m = ⌊|x|·10ˢ⌋ and m + 1) are made as float64 with one
    rounding each (|s| ≤ 22, m < 2⁵³: the float64 nearest the decimal, as reading its text gives), and the
    first p at which one of them reads back as the same float32 gives it (the nearer of the two if both do):
    the shortest decimal that identifies the float32, which is what NumPy writes. Zeros, non-finite values,
    magnitudes outside that range and near-ties between the two go through the text (tests/ground/
    test_archive_bulk.py compares the two on millions of values)."""
    x32 = np.asarray(values).astype(np.float32).ravel()
    x = x32.astype(np.float64)
    a = np.abs(x)
    out = np.empty(x.shape)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        e = np.floor(np.log10(a))
    slow = ~(np.isfinite(e) & (e >= -12) & (e <= 12))
    e = np.where(slow, 0.0, e).astype(np.int64)
    e += a >= _P10[e + 23]                  # exactly 10^e <= |x| < 10^(e+1)
    e -= a < _P10[e + 22]
    todo = np.flatnonzero(~slow)
    for p in range(1, 10):
        if not todo.size:
            break
        s = p - 1 - e[todo]                 # |x|·10^s has p digits before the point; |s| <= 22 here
        up = s >= 0
        scale = _P10[np.abs(s) + 22]
        ax = a[todo]
        v = np.where(up, ax * scale, ax / scale)
        m0 = np.floor(v)
        m1 = m0 + 1.0
        val0 = np.where(up, m0 / scale, m0 * scale)
        val1 = np.where(up, m1 / scale, m1 * scale)
        f32 = ax.astype(np.float32)
        ok0 = val0.astype(np.float32) == f32
        ok1 = val1.astype(np.float32) == f32
        frac = v - m0
        tie = ok0 & ok1 & (np.abs(frac - 0.5) < 1e-6)
        slow[todo[tie]] = True
        found = (ok0 | ok1) & ~tie
        pick = np.where(ok0 & ~(ok1 & (frac > 0.5)), val0, val1)
        out[todo[found]] = np.copysign(pick[found], x[todo[found]])
        todo = todo[~(found | tie)]
    slow[todo] = True                       # none of 9 digits read back (not a float32 value)
    rest = np.flatnonzero(slow)
    if rest.size:
        out[rest] = _f32_decimals_by_text(x32[rest])
    return out.reshape(np.shape(values))


def _crc_table() -> np.ndarray:
    """CRC-16/MCRF4XX (MAVLink's X.25) by byte: reflected polynomial 0x8408."""
    crc = np.arange(256, dtype=np.uint16)
    for _ in range(8):
        crc = np.where(crc & 1, (crc >> 1) ^ 0x8408, crc >> 1).astype(np.uint16)
    return crc


_CRC_TABLE = _crc_table()


def _crc(columns: np.ndarray, extra: int) -> np.ndarray:
    """The CRC of each row of `columns` (k × n bytes) followed by the byte `extra`, all rows at once."""
    crc = np.full(len(columns), 0xFFFF, dtype=np.uint16)
    for j in range(columns.shape[1]):
        crc = (crc >> 8) ^ _CRC_TABLE[(crc ^ columns[:, j]) & 0xFF]
    return (crc >> 8) ^ _CRC_TABLE[(crc ^ extra) & 0xFF]


def _checked(frames: list[bytes], places: list[int], layout: _Layout, crc: bool = True):
    """Frames of one length and start byte, checked at once: (places that pass, their payloads padded to
    the message's size, seq, sysid, compid) — a frame whose length or CRC is wrong is left out."""
    table = np.frombuffer(b"".join(frames), dtype=np.uint8).reshape(len(frames), -1)
    length = table.shape[1]
    if table[0, 0] == 0xFD:
        header, signed = 10, (table[:, 2] & 1).astype(bool)
        n = length - 12 - 13 * signed
        hdr = table[:, 4:7]
    else:
        header, signed = 6, np.zeros(len(frames), bool)
        n = np.full(len(frames), length - 8)
        hdr = table[:, 2:5]
    ok = (table[:, 1] == n) & (n >= 0) & (n <= layout.size)
    out = []
    for sig in (False, True):   # each its payload length: one CRC pass per
        rows = np.flatnonzero(ok & (signed == sig))
        if not rows.size:
            continue
        end = header + int(n[rows[0]])
        good = rows
        if crc:
            sent = table[rows, end].astype(np.uint16) | table[rows, end + 1].astype(np.uint16) << 8
            good = rows[_crc(table[rows, 1:end], layout.crc_extra) == sent]
        payload = np.zeros((good.size, layout.size), dtype=np.uint8)
        payload[:, :end - header] = table[good, header:end]
        out.append((good, payload))
    if not out:
        return [], None, None
    good = np.concatenate([g for g, _ in out])
    payload = np.concatenate([p for _, p in out])
    return [places[i] for i in good], payload, hdr[good]


def decode_samples(frames: list[bytes], msgid: int, *, rounded: bool = True,
                   crc_checked: bool = False) -> list:
    """The frames (all of message `msgid`, one of `LAYOUTS`) decoded; None where a frame fails a check
    (length, CRC). The checks and the unpacking are done on the frames' bytes as NumPy arrays, the frames
    of one length and start byte together. `rounded`: the `F32_FIELDS` as `ground.decode.f32` gives them
    (the decoder's recordings); else every float as pymavlink gives it (float32's exact value).
    `crc_checked`: the frames' CRCs were checked already (by the deframer): not again."""
    layout = LAYOUTS[msgid]
    out: list = [None] * len(frames)
    if not frames:
        return out
    # frames by length and start byte (an empty frame: length 0, refused with the other bad starts)
    key = np.fromiter(map(len, frames), dtype=np.int64, count=len(frames)) * 256 + np.fromiter(
        (f[0] if f else 0 for f in frames), dtype=np.int64, count=len(frames))
    kinds, group = np.unique(key, return_inverse=True)
    parts = []
    for g, k in enumerate(kinds.tolist()):
        if k % 256 in (0xFD, 0xFE):
            places = np.flatnonzero(group == g).tolist()
            parts.append(_checked([frames[i] for i in places], places, layout, not crc_checked))
    parts = [p for p in parts if p[0]]
    if not parts:
        return out
    ok = [i for p in parts for i in p[0]]
    table = np.concatenate([p[1] for p in parts]).view(layout.dtype).ravel()
    hdr = np.concatenate([p[2] for p in parts])
    columns = []
    for name in layout.fields:
        col = table[name]
        round_it = rounded and name in layout.rounded
        if round_it:
            col = _f32_decimals(col)
        elif name in layout.floats:
            col = col.astype(np.float64)
        values = col.tolist()
        if name in layout.arrays and round_it:
            values = list(map(tuple, values))
        columns.append(values)
    columns += [[frames[i] for i in ok], hdr[:, 0].tolist(), hdr[:, 1].tolist(), hdr[:, 2].tolist()]
    decoded = list(map(layout.message._make, zip(*columns)))
    if len(ok) == len(frames) and ok == sorted(ok):
        return decoded
    for i, msg in zip(ok, decoded):
        out[i] = msg
    return out


def msgid_of(frame: bytes) -> int:
    """The message id in a raw MAVLink 2 or 1 frame's header (-1: too short for one)."""
    if len(frame) >= 10 and frame[0] == 0xFD:
        return frame[7] | frame[8] << 8 | frame[9] << 16
    if len(frame) >= 6 and frame[0] == 0xFE:
        return frame[5]
    return -1


def decode_frames(items: list, decode_one) -> list:
    """Messages of a batch of intact raw frames, CRC checked (what `fsw.telemetry.framing.Deframer.feed_frames` gives;
    anything else in `items`, e.g. its BAD_DATA, passes through): the sample messages decoded in bulk as
    pymavlink gives them (`decode_samples`, not rounded), every other frame, and any the bulk decoding
    refuses, by `decode_one` (pymavlink), in the batch's order."""
    out = list(items)
    where: dict[int, list[int]] = {}
    for i, item in enumerate(items):
        if isinstance(item, (bytes, bytearray)):
            msgid = msgid_of(item)
            if msgid in LAYOUTS:
                where.setdefault(msgid, []).append(i)
            else:
                out[i] = decode_one(item)
    for msgid, places in where.items():
        for i, msg in zip(places, decode_samples([items[i] for i in places], msgid, rounded=False,
                                                    crc_checked=True)):
            out[i] = msg if msg is not None else decode_one(items[i])
    return out
