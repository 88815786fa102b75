"""Structure check of a telemetry log (.tlog) before it is decoded.

A tlog (pymavlink, MAVProxy, QGroundControl) is a sequence of records: an 8-byte big-endian time stamp
in µs since 1970 (pymavlink keeps the link id in its two low bits), then the frame's bytes as
received. Line noise recorded from a link may sit where a frame should be; the next record is then
found, as pymavlink does, at the next time stamp within three days of the last one that is followed
by a start byte.

:func:`check_tlog` walks the records and raises :class:`TlogError` (file, record number, byte
offset) for what cannot be a tlog: an empty file, a first time stamp outside 2000–2100 (not a tlog,
e.g. a CSV given by mistake), a time stamp that goes back, a record cut short by the end of the file,
or bytes after the last record that lead nowhere.
"""
from __future__ import annotations

import os
import struct
from datetime import datetime, timezone
from pathlib import Path

STX = (0xFD, 0xFE)
YEAR_MIN, YEAR_MAX = 2000, 2100
RESYNC_S = 3 * 24 * 3600
_T_MIN_US = int(datetime(YEAR_MIN, 1, 1, tzinfo=timezone.utc).timestamp() * 1e6)
_T_MAX_US = int(datetime(YEAR_MAX, 1, 1, tzinfo=timezone.utc).timestamp() * 1e6)


class TlogError(ValueError):
    """A .tlog that is not one, or is damaged; `path`, `record` (1-based) and `offset` say where."""

    def __init__(self, path, record: int | None, offset: int | None, reason: str) -> None:
        self.path, self.record, self.offset, self.reason = str(path), record, offset, reason
        where = self.path
        if record is not None:
            where += f": record {record} (byte {offset})"
        super().__init__(f"{where}: {reason}")


def _frame_length(data: bytes, i: int) -> int | None:
    """Declared length of the frame at i, None if the header itself is cut off."""
    if data[i] == 0xFD:
        if len(data) - i < 3:
            return None
        return 10 + data[i + 1] + 2 + (13 if data[i + 2] & 0x01 else 0)
    if len(data) - i < 2:
        return None
    return 6 + data[i + 1] + 2


def _when(t_us: int) -> str:
    try:
        return datetime.fromtimestamp(t_us * 1e-6, tz=timezone.utc).strftime("%Y-%m-%d %H:%M:%S UTC")
    except (OverflowError, OSError, ValueError):
        return f"{t_us} µs"


def check_tlog(path: str | os.PathLike) -> int:
    """Number of records of a well-formed tlog; raises TlogError otherwise (OSError if unreadable)."""
    data = Path(path).read_bytes()
    if not data:
        raise TlogError(path, None, None, "empty file")
    n = len(data)
    offset = 0
    record = 0
    last_us: int | None = None
    while offset < n:
        record += 1
        if n - offset < 8:
            raise TlogError(path, record, offset, f"truncated: {n - offset} bytes left, a time stamp needs 8")
        t_us = struct.unpack_from(">Q", data, offset)[0] & ~3
        if last_us is None and not _T_MIN_US <= t_us < _T_MAX_US:
            raise TlogError(path, record, offset, f"not a tlog: the first time stamp reads {_when(t_us)}")
        if last_us is not None and t_us < last_us:
            raise TlogError(path, record, offset,
                            f"time goes back from {_when(last_us)} to {_when(t_us)} ({(last_us - t_us) * 1e-6:.6f} s)")
        last_us = t_us
        body = offset + 8
        if body >= n:
            raise TlogError(path, record, offset, "truncated: a time stamp without a frame")
        if data[body] in STX:
            length = _frame_length(data, body)
            if length is None or body + length > n:
                need = "a header" if length is None else f"{length} bytes"
                raise TlogError(path, record, offset, f"truncated frame: needs {need}, the file has {n - body}")
            offset = body + length
            continue
        nxt = _next_record(data, body, last_us)
        if nxt is None:
            raise TlogError(path, record, offset, "not a frame, and no record follows")
        offset = nxt
    return record


def _next_record(data: bytes, start: int, last_us: int) -> int | None:
    """Offset of the next record after line noise: a time stamp within RESYNC_S of the last one (and
    not before it), followed by a start byte."""
    for p in range(start, len(data) - 8):
        if data[p + 8] not in STX:
            continue
        t_us = struct.unpack_from(">Q", data, p)[0] & ~3
        if last_us <= t_us <= last_us + RESYNC_S * 1_000_000:
            return p
    return None
