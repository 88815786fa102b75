"""The archive file: an SQLite database of every intact frame, per box and receive time.

One table, ``frames``: the receive time ``t_us`` (µs since 1970, the ground's clock, or a .tlog's time
stamps), the source ``sysid`` / ``compid``, the ``msgid``, the box's own time of the message when it
has one (``box_t_us``: time_usec, or time_boot_ms × 1000; NULL otherwise) and the ``frame`` itself,
raw, as received (signature included). Raw frames make the .tlog export exact and keep the archive
independent of the dialect's version: a frame is decoded when it is read, with the dialect then in use.
The index ``(sysid, t_us)`` makes an interval of one box a range scan.

Durability and readers: the database is in WAL mode (one writer, any number of readers, each reading a
consistent snapshot: whole transactions only) with ``synchronous=FULL``: a commit is on the disk when
it returns (one fsync of the WAL per commit). :class:`ArchiveWriter` commits whenever the oldest frame
it holds was handed over `COMMIT_PERIOD_S` ago (by the monotonic clock, checked on every `add` and
`tick`: `ground.decode` ticks at least every 0.1 s) or it holds `MAX_PENDING` frames, so a crash of the
process or a power cut loses at most the frames of the last second; what is committed is never lost or
torn (SQLite's journal). A .tlog imported (`ground.decode FILE.tlog --archive A`) is committed by the
same clock: a few commits a second, however long the recording. A second station reads
the file while it is written (`open_reader`: read-only) and sees the frames up to the last commit.
Several writers on one file (two decoders) take turns: each waits up to `BUSY_TIMEOUT_S` for the other's
commit.
"""
from __future__ import annotations

import os
import secrets
import sqlite3
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterator

#: PRAGMA user_version of an archive of this layout
SCHEMA_VERSION = 1
#: PRAGMA application_id: "DBAR"
APPLICATION_ID = 0x44424152
#: a frame is committed at most this long (receive time) after it was added ...
COMMIT_PERIOD_S = 0.5
#: ... or once this many frames are waiting
MAX_PENDING = 20_000
#: how long a writer waits for another's commit
BUSY_TIMEOUT_S = 10.0
#: the largest time SQLite's INTEGER holds
_INT64_MAX = 2**63 - 1

_SCHEMA = """
CREATE TABLE IF NOT EXISTS frames (
    t_us INTEGER NOT NULL,
    sysid INTEGER NOT NULL,
    compid INTEGER NOT NULL,
    msgid INTEGER NOT NULL,
    box_t_us INTEGER,
    frame BLOB NOT NULL
);
CREATE INDEX IF NOT EXISTS frames_box_time ON frames (sysid, t_us);
"""
_INSERT = "INSERT INTO frames (t_us, sysid, compid, msgid, box_t_us, frame) VALUES (?, ?, ?, ?, ?, ?)"


class ArchiveError(ValueError):
    """A file that is not an archive (or one of a newer layout), or that cannot be opened."""


def default_path() -> Path:
    """``$XDG_DATA_HOME/debris-box/archive.sqlite`` (``~/.local/share/debris-box/archive.sqlite``): one
    archive per user, whatever directory the station is started from."""
    base = os.environ.get("XDG_DATA_HOME") or os.path.join(os.path.expanduser("~"), ".local", "share")
    return Path(base) / "debris-box" / "archive.sqlite"


def _check(conn: sqlite3.Connection, path) -> None:
    try:
        app, version = (conn.execute("PRAGMA application_id").fetchone()[0],
                        conn.execute("PRAGMA user_version").fetchone()[0])
    except sqlite3.DatabaseError as e:
        raise ArchiveError(f"{path}: not an archive ({e})") from None
    if app != APPLICATION_ID or version > SCHEMA_VERSION:
        what = "of a newer layout" if app == APPLICATION_ID else "not an archive (another SQLite database)"
        raise ArchiveError(f"{path}: {what}")


def box_time_us(msg) -> int | None:
    """The box's time of a message: time_usec, or time_boot_ms in µs; None for messages without one."""
    t = getattr(msg, "time_usec", None)
    if t is None:
        ms = getattr(msg, "time_boot_ms", None)
        if ms is None:
            return None
        t = ms * 1000
    return t if 0 <= t <= _INT64_MAX else None


def _create(path: Path) -> None:
    """Make a new, empty archive at `path` at once: built in a temporary file beside it, then linked
    into place, so that no reader ever sees a file without its table (if another writer made it
    meanwhile, theirs is kept)."""
    tmp = path.parent / f".{path.name}.{secrets.token_hex(8)}.tmp"
    os.close(os.open(tmp, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o666))  # the umask's permissions: others may read
    try:
        conn = sqlite3.connect(tmp, isolation_level=None)
        try:
            conn.execute(f"PRAGMA application_id = {APPLICATION_ID}")
            conn.execute(f"PRAGMA user_version = {SCHEMA_VERSION}")
            conn.execute("PRAGMA journal_mode = WAL")
            conn.executescript(_SCHEMA)
        finally:
            conn.close()
        try:
            os.link(tmp, path)
        except FileExistsError:
            pass
        except OSError:  # a file system without hard links: renamed instead, unless one appeared meanwhile
            if not path.exists():
                os.rename(tmp, path)
                return
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def archive_row(msg, now_s: float) -> tuple:
    """The archive's row of an intact frame (a pymavlink message as parsed) received at `now_s` (Unix time,
    s): (received µs, system, component, message id, the box's time µs or None, the frame's bytes)."""
    return (round(now_s * 1e6), msg.get_srcSystem(), msg.get_srcComponent(), msg.get_msgId(), box_time_us(msg),
            bytes(msg.get_msgbuf()))


class ArchiveWriter:
    """Appends frames to an archive (created if missing) in transactions of the frames handed over within
    `commit_period_s` of `clock` (monotonic seconds) or `max_pending` frames; `close` commits the rest."""

    def __init__(self, path: str | os.PathLike, *, commit_period_s: float = COMMIT_PERIOD_S,
                 clock: Callable[[], float] = time.monotonic,
                 max_pending: int = MAX_PENDING) -> None:
        self.path = Path(path)
        self.commit_period_s = commit_period_s
        self.clock = clock
        self.max_pending = max_pending
        try:
            if not self.path.exists():
                _create(self.path)
            self.conn = sqlite3.connect(self.path, timeout=BUSY_TIMEOUT_S, isolation_level=None)
            _check(self.conn, self.path)
            self.conn.execute("PRAGMA journal_mode = WAL")
            self.conn.execute("PRAGMA synchronous = FULL")
        except (sqlite3.Error, OSError) as e:
            raise ArchiveError(f"{self.path}: {getattr(e, 'strerror', None) or e}") from None
        self._rows: list[tuple] = []
        self._oldest_s: float | None = None
        #: frames committed by this writer, and commits
        self.frames = 0
        self.commits = 0

    def add(self, msg, now_s: float) -> None:
        """Archive an intact frame (a pymavlink message as parsed) received at `now_s` (Unix time, s)."""
        rows = self._rows
        rows.append(archive_row(msg, now_s))
        now = self.clock()
        if self._oldest_s is None:
            self._oldest_s = now
        elif now - self._oldest_s >= self.commit_period_s or len(rows) >= self.max_pending:
            self.commit()

    def add_many(self, msgs: list, times_s: list[float]) -> None:
        """`add` of a batch of messages received at `times_s`, the commit checked once at its end (the
        ground station's ingest: the frames waiting, taken together)."""
        rows = self._rows
        rows.extend(map(archive_row, msgs, times_s))
        if rows and self._oldest_s is None:
            self._oldest_s = self.clock()
        self.tick()

    def add_frame(self, t_us: int, sysid: int, compid: int, msgid: int, box_t_us: int | None, frame: bytes) -> None:
        """Archive a raw frame received at `t_us` (µs since 1970)."""
        self._rows.append((t_us, sysid, compid, msgid, box_t_us, frame))
        if self._oldest_s is None:
            self._oldest_s = self.clock()
        self.tick()

    def tick(self) -> None:
        """Commit if the oldest frame held was handed over `commit_period_s` ago, or `max_pending` are held
        (call it also when nothing arrives)."""
        if self._rows and (self.clock() - self._oldest_s >= self.commit_period_s or
                           len(self._rows) >= self.max_pending):
            self.commit()

    def commit(self) -> None:
        """Write the frames held in one transaction (on the disk when this returns)."""
        if not self._rows:
            return
        rows, self._rows, self._oldest_s = self._rows, [], None
        try:
            with self.conn:
                self.conn.execute("BEGIN IMMEDIATE")
                self.conn.executemany(_INSERT, rows)
        except sqlite3.Error as e:
            raise ArchiveError(f"{self.path}: {e}") from None
        self.frames += len(rows)
        self.commits += 1

    def close(self) -> None:
        try:
            self.commit()
        finally:
            self.conn.close()

    def __enter__(self) -> ArchiveWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class ArchiveFeed:
    """A decoder's archive while it runs: the frames go to an `ArchiveWriter` until it fails (a full disk,
    the file taken away); then the failure is said once (`say`), the writer is dropped and decoding goes on,
    so the recordings and the tlog lose nothing. `lost` counts the frames that did not reach the archive."""

    def __init__(self, path: str | os.PathLike | None, say: Callable[[str], None]) -> None:
        self.writer = ArchiveWriter(path) if path is not None else None
        self.say = say
        self.given = 0
        #: frames committed; the failure's text once it failed
        self.frames = 0
        self.error: str | None = None

    @property
    def lost(self) -> int:
        return self.given - self.frames if self.error is not None else 0

    def add(self, msg, now_s: float) -> None:
        if self.writer is None:
            self.given += self.error is not None
            return
        self.given += 1
        self._guard(self.writer.add, msg, now_s)

    def add_many(self, msgs: list, times_s: list[float]) -> None:
        if self.writer is None:
            self.given += len(msgs) if self.error is not None else 0
            return
        self.given += len(msgs)
        self._guard(self.writer.add_many, msgs, times_s)

    def tick(self) -> None:
        if self.writer is not None:
            self._guard(self.writer.tick)

    def close(self) -> None:
        if self.writer is not None:
            self._guard(self.writer.commit)
        if self.writer is not None:
            self.writer.conn.close()
            self.writer = None

    def _guard(self, call, *args) -> None:
        try:
            call(*args)
        except ArchiveError as e:
            self.error = str(e)
            self.say(f"archive failed, decoding goes on without it: {e}")
            try:
                self.writer.conn.close()
            except sqlite3.Error:
                pass
            self.writer = None
        if self.writer is not None:
            self.frames = self.writer.frames


@dataclass
class BoxSpan:
    """Frames of one source within one stretch of reception (no gap longer than the gap asked for)."""

    sysid: int
    compid: int
    first_us: int
    last_us: int
    frames: int


def open_reader(path: str | os.PathLike) -> sqlite3.Connection:
    """A read-only connection to an existing archive (ArchiveError if it is missing or not one)."""
    p = Path(path)
    if not p.is_file():
        raise ArchiveError(f"{p}: no such archive")
    try:
        conn = sqlite3.connect(p.resolve().as_uri() + "?mode=ro", uri=True, timeout=BUSY_TIMEOUT_S,
                               isolation_level=None)
    except sqlite3.Error as e:
        raise ArchiveError(f"{p}: {e}") from None
    _check(conn, p)
    try:
        conn.execute("SELECT 1 FROM frames LIMIT 1").fetchall()
    except sqlite3.Error as e:
        conn.close()
        raise ArchiveError(f"{p}: not an archive ({e})") from None
    return conn


def spans(conn: sqlite3.Connection, gap_s: float = 60.0) -> list[BoxSpan]:
    """Every source's stretches of reception, split where nothing came for more than `gap_s`, by
    (sysid, compid, time). One snapshot of the archive."""
    gap_us = round(gap_s * 1e6)
    out: list[BoxSpan] = []
    rows = conn.execute("SELECT sysid, compid, t_us FROM frames ORDER BY sysid, compid, t_us")
    cur: BoxSpan | None = None
    for sysid, compid, t in rows:
        if cur is None or (sysid, compid) != (cur.sysid, cur.compid) or t - cur.last_us > gap_us:
            cur = BoxSpan(sysid, compid, t, t, 0)
            out.append(cur)
        cur.last_us = t
        cur.frames += 1
    return out


def frames(conn: sqlite3.Connection, sysid: int, from_us: int | None = None, to_us: int | None = None, *,
           with_msgid: bool = False) -> Iterator[tuple]:
    """(receive time µs, raw frame) — (time, msgid, frame) `with_msgid` — of box `sysid` (every component)
    with from_us <= t < to_us, in receive order; one snapshot (a single read transaction) of the archive."""
    lo = -1 if from_us is None else from_us
    hi = _INT64_MAX if to_us is None else to_us
    cols = "t_us, msgid, frame" if with_msgid else "t_us, frame"
    yield from conn.execute(f"SELECT {cols} FROM frames WHERE sysid = ? AND t_us >= ? AND t_us < ? "
                            "ORDER BY t_us, rowid", (sysid, lo, hi))
