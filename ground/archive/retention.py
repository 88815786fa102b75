"""Retention: a box's frames received before a time taken out of the archive, never silently.

`prune` deletes box `sysid`'s frames received before `before_us`, and only after they are kept elsewhere:
with `keep` (a .tlog path) they are first written there exactly as `export_tlog` writes them (atomically,
on the disk before anything is deleted); without it the caller has said it wants them gone
(``--discard`` on the command line). What was deleted is returned (count, first and last receive time),
for the command line to say.

The export reads one snapshot of the archive without holding its write lock, so a station writing the
archive meanwhile is not held up; the deletion is then one short write transaction that deletes exactly
the rows exported (the box's rows before the time up to the last row id exported; frames that arrived
meanwhile have higher row ids and stay). If the rows found then are not the ones exported (another prune
ran meanwhile), nothing is deleted (`ArchiveError`). Readers see the frames either all there or all gone
(WAL snapshots). SQLite reuses the freed pages for new frames; the file does not shrink.
"""
from __future__ import annotations

import os
import sqlite3
from dataclasses import dataclass
from pathlib import Path

from .export import export_tlog
from .store import BUSY_TIMEOUT_S, ArchiveError, _check


@dataclass
class Pruned:
    """Frames deleted, their first and last receive time (µs; None when none), where they were kept."""

    frames: int = 0
    first_us: int | None = None
    last_us: int | None = None
    kept: Path | None = None


def prune(path: str | os.PathLike, sysid: int, before_us: int, keep: str | os.PathLike | None) -> Pruned:
    """Delete box `sysid`'s frames with receive time < `before_us` from the archive at `path`, after writing
    them to the .tlog `keep` (None: discarded)."""
    try:
        conn = sqlite3.connect(Path(path), timeout=BUSY_TIMEOUT_S, isolation_level=None)
    except sqlite3.Error as e:
        raise ArchiveError(f"{path}: {e}") from None
    try:
        _check(conn, path)
        return _prune(conn, path, sysid, before_us, keep)
    except sqlite3.Error as e:
        raise ArchiveError(f"{path}: {e}") from None
    finally:
        conn.close()


def _prune(conn: sqlite3.Connection, path, sysid: int, before_us: int, keep) -> Pruned:
    where = "sysid = ? AND t_us < ? AND rowid <= ?"
    conn.execute("BEGIN")                  # one snapshot for what is counted and what is kept
    count, first, last, top = conn.execute(
        "SELECT count(*), min(t_us), max(t_us), max(rowid) FROM frames WHERE sysid = ? AND t_us < ?",
        (sysid, before_us)).fetchone()
    if count and keep is not None:
        written = export_tlog(conn, sysid, keep, None, before_us)
        if written.frames != count:
            raise ArchiveError(f"{path}: {written.frames} frames exported of {count}: nothing deleted")
    conn.execute("COMMIT")
    out = Pruned(kept=None if keep is None or not count else Path(keep))
    if not count:
        return out
    with conn:
        conn.execute("BEGIN IMMEDIATE")
        now = conn.execute(f"SELECT count(*) FROM frames WHERE {where}", (sysid, before_us, top)).fetchone()[0]
        if now != count:
            raise ArchiveError(f"{path}: the frames before the time changed while they were kept ({count} then "
                               f"{now}): nothing deleted, run it again")
        conn.execute(f"DELETE FROM frames WHERE {where}", (sysid, before_us, top))
    out.frames, out.first_us, out.last_us = count, first, last
    return out
