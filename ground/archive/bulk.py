"""The sample messages of an archive's interval decoded in bulk, for the recordings' export.

An hour of a box is about 110,000 sample frames (DEBRIS_MAG_SAMPLE, DEBRIS_RATE_ESTIMATE,
DEBRIS_SIM_STATE, HIGHRES_IMU: `ground.decode.SAMPLE_MESSAGES`). Decoding them one by one with
pymavlink, then rounding each float to its float32 decimal (`ground.decode.f32`) one value at a time,
was most of the export's time. Here a batch of frames of one message id is checked (length, CRC with
the message's CRC extra, as pymavlink checks it) and unpacked at once with NumPy (a structured dtype
made from the bindings' own struct format, truncated MAVLink 2 payloads padded with zeros as the
protocol says), the fields `ground.decode.F32_FIELDS` names are rounded at once (NumPy's float32
text, the same shortest decimal `f32` gives; the distinct values only), and each frame becomes a
`Sample`: the message's fields as attributes, its header read from its bytes. The decoder takes them
as they are (`Decoder(rounded=True)`). A frame that fails a check is left to pymavlink (`decode` gives
BAD_DATA), as the export did before.
"""
from __future__ import annotations

import re

import numpy as np
from fastcrc import crc16

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


class _Layout:
    """One message's wire layout as a NumPy dtype, and what the decoder reads of it."""

    def __init__(self, cls) -> None:
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


def _layouts() -> dict[int, _Layout]:
    return {msgid: _Layout(cls) for msgid, cls in mavlink.mavlink_map.items() if cls.msgname in SAMPLE_MESSAGES}


#: the sample messages by id
LAYOUTS = _layouts()


def _f32_decimals(values: np.ndarray) -> np.ndarray:
    """`ground.decode.f32` of every value at once: float32's shortest decimal, as float64."""
    unique, inverse = np.unique(values.astype(np.float32).ravel(), return_inverse=True)
    with np.errstate(invalid="ignore"):
        return unique.astype(str).astype(np.float64)[inverse].reshape(values.shape)


def _payload(frame: bytes, layout: _Layout) -> bytes | None:
    """The frame's payload padded to the message's size, None if its length or CRC is wrong."""
    if frame[0] == 0xFD:
        header, n, sig = 10, frame[1], 13 if frame[2] & 1 else 0
    elif frame[0] == 0xFE:
        header, n, sig = 6, frame[1], 0
    else:
        return None
    end = header + n
    if len(frame) != end + 2 + sig or n > layout.size:
        return None
    crc = frame[end] | frame[end + 1] << 8
    if crc16.mcrf4xx(frame[1:end] + bytes((layout.crc_extra,)), 0xFFFF) != crc:
        return None
    return frame[header:end] + bytes(layout.size - n)


def decode_samples(frames: list[bytes], msgid: int) -> list[Sample | None]:
    """The frames (all of message `msgid`, one of `LAYOUTS`) decoded; None where a frame fails a check."""
    layout = LAYOUTS[msgid]
    payloads = [_payload(f, layout) for f in frames]
    ok = [i for i, p in enumerate(payloads) if p is not None]
    out: list[Sample | None] = [None] * len(frames)
    if not ok:
        return out
    table = np.frombuffer(b"".join(payloads[i] for i in ok), dtype=layout.dtype)
    columns = []
    for name in layout.fields:
        col = table[name]
        if name in layout.rounded:
            col = _f32_decimals(col)
        elif name in layout.floats:
            col = col.astype(np.float64)
        values = col.tolist()
        if name in layout.arrays:
            values = [tuple(v) if name in layout.rounded else v for v in values]
        columns.append(values)
    names, kind = layout.fields, layout.name
    for i, row in zip(ok, zip(*columns)):
        out[i] = Sample(frames[i], kind, msgid, dict(zip(names, row)))
    return out
