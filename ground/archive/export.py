"""An interval of one box out of the archive: a .tlog, or the recordings `ground.decode --csv` writes.

The .tlog holds the archived frames as they were received, each after its receive time stamp (8 bytes,
big-endian µs, the low 2 bits cleared: pymavlink's link id 0, as `ground.decode.tlog_record` writes
them): any tlog reader (pymavlink's `mavlogdump.py --dialect`, MAVProxy, `ground.decode FILE.tlog`)
reads it. It is written atomically (`fsw.files.atomic_file`).

The recordings are made by the decoder itself: the frames are decoded (with the dialect in use now)
and handed to `ground.decode.Decoder` with their receive times, as `ground.decode` does with a .tlog,
so the CSVs are the ones `ground.decode --csv` writes from the same frames (one file per run of each
source: `ground.recorder`), the ``# source:`` line aside, which names the archive and the box.
"""
from __future__ import annotations

import os
import sqlite3
import struct
from dataclasses import dataclass

from fsw.files import atomic_file
from fsw.telemetry.framing import Deframer

from ..decode import Decoder
from ..recorder import Recorder
from .store import frames

_STAMP = struct.Struct(">Q")


@dataclass
class Exported:
    """What an export wrote: frames read, the first and last receive time (µs; None if no frame), files."""

    frames: int = 0
    first_us: int | None = None
    last_us: int | None = None
    written: list | None = None


def export_tlog(conn: sqlite3.Connection, sysid: int, path: str | os.PathLike, from_us: int | None = None,
                to_us: int | None = None) -> Exported:
    """Write box `sysid`'s frames with from_us <= t < to_us to the .tlog `path` (nothing written when
    there is none)."""
    out = Exported(written=[])
    rows = frames(conn, sysid, from_us, to_us)
    first = next(rows, None)
    if first is None:
        return out
    stamp = _STAMP.pack
    with atomic_file(path, "wb") as f:
        t_us, frame = first
        out.first_us = t_us
        f.write(stamp(t_us & ~3) + frame)
        n = 1
        chunk: list[bytes] = []
        for t_us, frame in rows:
            chunk.append(stamp(t_us & ~3))
            chunk.append(frame)
            if len(chunk) >= 8192:
                f.write(b"".join(chunk))
                chunk.clear()
            n += 1
        f.write(b"".join(chunk))
    out.frames, out.last_us = n, t_us
    out.written.append(("tlog", path))
    return out


def export_recordings(conn: sqlite3.Connection, sysid: int, csv: str | os.PathLike | None,
                      rates_csv: str | os.PathLike | None = None, from_us: int | None = None,
                      to_us: int | None = None, *, origin: str = "", protect=()) -> Exported:
    """Decode box `sysid`'s frames with from_us <= t < to_us through `ground.decode.Decoder` and write
    its recordings (`csv`) and rate estimates (`rates_csv`); `protect`: files the recorder's extra files
    (other runs) may never take the name of."""
    recorder = Recorder(csv, rates_csv, protect=protect)
    decoder = Decoder(origin=origin, recorder=recorder)
    decode = Deframer().decode
    handle = decoder.handle
    out = Exported()
    n = 0
    for t_us, frame in frames(conn, sysid, from_us, to_us):
        if n == 0:
            out.first_us = t_us
        handle(decode(frame), t_us * 1e-6)
        n += 1
    if n:
        decoder.finish()
        out.last_us = t_us
    out.frames = n
    out.written = list(recorder.written)
    return out
