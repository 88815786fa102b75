"""Reading a telemetry log (.tlog) record by record, keeping every intact record of a damaged one.

A tlog (pymavlink, MAVProxy, QGroundControl) is a sequence of records: an 8-byte big-endian time stamp
in µs since 1970 (pymavlink keeps the link id in its two low bits), then the frame's bytes as
received. Line noise recorded from a link may sit where a frame should be: such a record runs to the
next record, found as pymavlink finds it — a time stamp within three days of the last one, followed by
a start byte. Both are data (the decoder counts the noise as the link's garbage).

Damage to the file itself is skipped, counted and reported (:class:`TlogReport`), never fatal while
anything intact is left:

- bytes in no record (inserted, or a record whose time stamp is damaged): skipped up to the next
  record that can be trusted — a time stamp of 2000-2100, a start byte and a frame that is intact
  (its CRC checks with the dialect), or, with a time stamp within three days of the last record's, a
  frame that ends exactly where another record or the file does;
- a record whose frame is not intact and does not end where a record follows (a damaged length
  byte, bytes lost inside it): skipped to the next record that can be trusted;
- the last record cut short by the end of the file: skipped;
- a time stamp earlier than the previous record's: the record is kept (its frame is intact) and the
  step back counted; so is a step forward of more than three days (`time_jumps`). A damaged time
  stamp read as another date of 2000-2100 (the first record's above all) never costs the records after
  it: an intact frame is a record whatever its date, and where no record follows within three days of
  the last one, reading goes on at the next that can be trusted of any date.

:func:`read_tlog` yields the records with their parsed messages (`fsw.telemetry.framing.Deframer`: the
message of an intact frame, pymavlink's BAD_DATA for anything else) and fills its report as it goes;
:func:`check_tlog` reads a whole file and raises :class:`TlogError` (file, and where) only when there
is nothing to keep: an empty file, or no record at all (not a tlog, e.g. a CSV given by mistake).
"""
from __future__ import annotations

import os
import re
import struct
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Iterator

from fsw.telemetry.framing import Deframer

STX = (0xFD, 0xFE)
YEAR_MIN, YEAR_MAX = 2000, 2100
RESYNC_S = 3 * 24 * 3600
_RESYNC_US = RESYNC_S * 1_000_000
_T_MIN_US = int(datetime(YEAR_MIN, 1, 1, tzinfo=timezone.utc).timestamp() * 1e6)
_T_MAX_US = int(datetime(YEAR_MAX, 1, 1, tzinfo=timezone.utc).timestamp() * 1e6)
_STX_RE = re.compile(rb"[\xfd\xfe]")
_SIGNATURE_LEN = 13
#: problems listed one by one in the report (all are counted)
MAX_EVENTS = 5


class TlogError(ValueError):
    """A .tlog that is not one, or has nothing intact; `path`, `record` (1-based) and `offset` say where."""

    def __init__(self, path, record: int | None, offset: int | None, reason: str) -> None:
        self.path, self.record, self.offset, self.reason = str(path), record, offset, reason
        where = self.path
        if record is not None:
            where += f": record {record} (byte {offset})"
        super().__init__(f"{where}: {reason}")


@dataclass
class TlogRecord:
    """One record kept: its time stamp (µs, link bits cleared), byte offset in the file, the bytes
    after the time stamp, and their messages (one for an intact frame, else BAD_DATA)."""

    t_us: int
    offset: int
    data: bytes
    messages: list


@dataclass
class TlogReport:
    """What reading a tlog kept and skipped."""

    path: str
    size: int = 0
    records: int = 0          # records kept (frames, and line noise recorded in place of a frame)
    noise_records: int = 0    # of them: line noise recorded from the link
    junk_bytes: int = 0       # bytes in no record, skipped
    junk_runs: int = 0
    damaged_records: int = 0  # records whose frame is damaged and does not end where a record follows
    damaged_bytes: int = 0
    cut_bytes: int = 0        # the last record, cut short by the end of the file
    time_back: int = 0        # records whose time stamp is before the previous record's (kept)
    time_jumps: int = 0       # records whose time stamp is more than three days after the previous one's (kept)
    events: list[str] = field(default_factory=list)

    @property
    def skipped_bytes(self) -> int:
        return self.junk_bytes + self.damaged_bytes + self.cut_bytes

    @property
    def damaged(self) -> bool:
        return bool(self.skipped_bytes or self.time_back or self.time_jumps)

    def _event(self, text: str) -> None:
        if len(self.events) < MAX_EVENTS:
            self.events.append(text)

    def text(self) -> str:
        """One line: what was kept and what was skipped (with the first places)."""
        parts = []
        if self.junk_bytes:
            parts.append(f"{self.junk_bytes} bytes in no record ({self.junk_runs} "
                         f"{'run' if self.junk_runs == 1 else 'runs'}) skipped")
        if self.damaged_records:
            parts.append(f"{self.damaged_records} damaged {'record' if self.damaged_records == 1 else 'records'} "
                         f"({self.damaged_bytes} bytes) skipped")
        if self.cut_bytes:
            parts.append(f"the last record, cut short by the end of the file ({self.cut_bytes} bytes), skipped")
        if self.time_back:
            parts.append(f"{self.time_back} time {'stamp goes' if self.time_back == 1 else 'stamps go'} "
                         "back (records kept)")
        if self.time_jumps:
            parts.append(f"{self.time_jumps} time {'stamp jumps' if self.time_jumps == 1 else 'stamps jump'} "
                         "more than three days ahead (records kept)")
        line = f"{self.path}: {self.records} records kept"
        if parts:
            line += "; " + "; ".join(parts) + " — " + "; ".join(self.events)
        return line


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


class _Scanner:
    def __init__(self, data: bytes, report: TlogReport) -> None:
        self.data = data
        self.n = len(data)
        self.report = report
        self.deframer = Deframer()
        self.prev: int | None = None  # time stamp of the last record kept

    def ts(self, p: int) -> int:
        return struct.unpack_from(">Q", self.data, p)[0] & ~3

    @staticmethod
    def near(t: int, last: int | None) -> bool:
        return _T_MIN_US <= t < _T_MAX_US and (last is None or abs(t - last) <= _RESYNC_US)

    def parse(self, data: bytes) -> list:
        return self.deframer.feed(data, end=True)

    @staticmethod
    def intact(messages: list) -> bool:
        return len(messages) == 1 and messages[0].get_type() != "BAD_DATA"

    def starts_record(self, p: int, last: int) -> bool:
        """A record may start at p: a time stamp near the last one and something after it."""
        return self.n - p > 8 and self.near(self.ts(p), last)

    def trusted_start(self, p: int, last: int | None) -> bool:
        """A record that can be trusted starts at p (see the module docstring)."""
        body = p + 8
        if body >= self.n or self.data[body] not in STX:
            return False
        t = self.ts(p)
        if not self.near(t, None):
            return False
        length = _frame_length(self.data, body)
        if length is None or body + length > self.n:
            return False
        end = body + length
        if self.near(t, last) and (end == self.n or self.starts_record(end, t)):
            return True
        return self.intact(self.parse(self.data[body:end]))

    def record_inside(self, start: int, stop: int, last: int | None) -> int | None:
        """The first offset in [start, stop) where a record that can be trusted starts, or None."""
        for m in _STX_RE.finditer(self.data, start + 8, stop + 8):
            if self.trusted_start(m.start() - 8, last):
                return m.start() - 8
        return None

    def cut_in_signature(self, body: int, end: int, t: int) -> bool:
        """The signed frame at `body` lost bytes of its signature block (which its CRC does not cover):
        a record that can be trusted starts inside the block, and the frame took its "signature" from
        that record's bytes."""
        if self.data[body] != 0xFD or not self.data[body + 2] & 0x01:
            return False
        return self.record_inside(max(end - _SIGNATURE_LEN, body + 1), end, t) is not None

    def resync(self, start: int, last: int | None) -> int | None:
        """Offset of the next record that can be trusted, at or after `start`."""
        for m in _STX_RE.finditer(self.data, start + 8):
            if self.trusted_start(m.start() - 8, last):
                return m.start() - 8
        return None

    def resync_or_restart(self, start: int, last: int | None) -> tuple[int | None, int | None]:
        """(offset of the next record that can be trusted at or after `start`, the time its nearness is
        judged by from then on): near `last` if one is, else the next of 2000-2100 (None: the time chain
        starts again there), so that a damaged time stamp does not hide the records after it."""
        nxt = self.resync(start, last)
        if nxt is None and last is not None:
            nxt = self.resync(start, None)
            if nxt is not None:
                last = None
        return nxt, last

    def records(self) -> Iterator[TlogRecord]:
        data, n, rep = self.data, self.n, self.report
        offset = 0
        last: int | None = None  # time stamp the next record must be near (None: any of 2000-2100)
        while offset < n:
            if n - offset <= 8:
                if last is None:
                    self.junk(offset, n)
                else:
                    rep.cut_bytes += n - offset
                    rep._event(f"byte {offset}: the last record is cut short ({n - offset} bytes: "
                               f"{'part of a time stamp' if n - offset < 8 else 'a time stamp without its frame'})")
                return
            t = self.ts(offset)
            # the first record must at least be a time stamp of 2000-2100 and a start byte; a record far in
            # time from the last one, an intact frame
            if (not self.near(t, last) or (last is None and data[offset + 8] not in STX)) and \
                    not (last is not None and self.trusted_start(offset, last)):
                nxt = self.resync(offset + 1, last)
                if nxt is None and last is not None:  # nothing near: the time chain starts again
                    nxt = self.resync(offset, None)
                    if nxt is not None:
                        last = None
                        if nxt == offset:
                            continue
                self.junk(offset, n if nxt is None else nxt, t if last is None else None)
                if nxt is None:
                    return
                offset = nxt
                continue
            body = offset + 8
            if data[body] in STX:
                length = _frame_length(data, body)
                end = None if length is None or body + length > n else body + length
                if end is not None:
                    messages = self.parse(data[body:end])
                    at_record = end == n or self.starts_record(end, t)
                    if self.intact(messages):
                        good = at_record or not self.cut_in_signature(body, end, t)
                    else:  # kept as data when it ends where a record starts, unless one that can be trusted
                        good = at_record and self.record_inside(offset + 1, end, t) is None  # starts inside it
                    if good:
                        yield self.keep(offset, t, data[body:end], messages)
                        last, offset = t, end
                        continue
                nxt, last = self.resync_or_restart(offset + 1, last)
                if nxt is None and end is None:
                    rep.cut_bytes += n - offset
                    rep._event(f"byte {offset} (record {rep.records + 1}): the last record is cut short "
                               f"({n - body} of the {length or '?'} bytes of its frame)")
                    return
                stop = n if nxt is None else nxt
                rep.damaged_records += 1
                rep.damaged_bytes += stop - offset
                rep._event(f"byte {offset} (record {rep.records + 1}): the frame is damaged and does not end "
                           f"where a record follows (a damaged length byte?): {stop - offset} bytes skipped")
                if nxt is None:
                    return
                offset = nxt
                continue
            # line noise recorded in place of a frame: data up to the next record; but a time stamp that a
            # record that can be trusted starts inside is no record's
            inside = self.record_inside(offset + 1, body, last)
            if inside is not None:
                self.junk(offset, inside)
                offset = inside
                continue
            nxt, _ = self.resync_or_restart(body, t)
            stop = n if nxt is None else nxt
            if stop == body:  # a time stamp without anything after it: no record
                self.junk(offset, body)
                offset = body
                continue
            yield self.keep(offset, t, data[body:stop], self.parse(data[body:stop]), noise=True)
            last, offset = t, stop

    def junk(self, start: int, stop: int, t_us: int | None = None) -> None:
        rep = self.report
        rep.junk_bytes += stop - start
        rep.junk_runs += 1
        what = f" (its first 8 bytes read as the time {_when(t_us)})" if t_us is not None and start == 0 else ""
        rep._event(f"byte {start}: {stop - start} bytes in no record{what}")

    def keep(self, offset: int, t: int, data: bytes, messages: list, noise: bool = False) -> TlogRecord:
        rep = self.report
        rep.records += 1
        rep.noise_records += noise
        prev, self.prev = self.prev, t
        if prev is not None and t < prev:
            rep.time_back += 1
            rep._event(f"byte {offset} (record {rep.records}): time goes back from {_when(prev)} to {_when(t)} "
                       f"({(prev - t) * 1e-6:.6f} s), kept")
        elif prev is not None and t - prev > _RESYNC_US:
            rep.time_jumps += 1
            rep._event(f"byte {offset} (record {rep.records}): time jumps ahead from {_when(prev)} to {_when(t)} "
                       f"({(t - prev) * 1e-6 / 86400:.1f} days), kept")
        return TlogRecord(t, offset, data, messages)


class TlogReader:
    """Iterate once over the records of a tlog; `report` counts what was kept and skipped so far."""

    def __init__(self, path: str | os.PathLike) -> None:
        self.path = path
        self.data = Path(path).read_bytes()
        self.report = TlogReport(str(path), size=len(self.data))

    def __iter__(self) -> Iterator[TlogRecord]:
        if not self.data:
            raise TlogError(self.path, None, None, "empty file")
        yield from _Scanner(self.data, self.report).records()
        if not self.report.records:
            raise TlogError(self.path, None, None, "not a tlog: no record found; " + "; ".join(self.report.events))


def read_tlog(path: str | os.PathLike) -> TlogReader:
    """The records of a tlog, read (OSError if unreadable) and parsed lazily; see the module docstring."""
    return TlogReader(path)


def check_tlog(path: str | os.PathLike) -> TlogReport:
    """Read a whole tlog: what it keeps and skips. TlogError if it is empty or holds no record."""
    reader = read_tlog(path)
    for _ in reader:
        pass
    return reader.report
