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

import gc
import os
import sqlite3
import struct
from collections import Counter
from contextlib import contextmanager
from itertools import islice
from operator import itemgetter
from dataclasses import dataclass

import numpy as np

from fsw.files import atomic_file
from fsw.telemetry.framing import Deframer

from fsw.telemetry.dialect import mavlink

from ..decode import F32_FIELDS, KNOWLEDGE_MESSAGES, SAMPLE_MESSAGES, Decoder, f32
from ..link_stats import MAG_FIELDS, MAX_TIME_US
from ..recorder import Recorder
from .bulk import LAYOUTS, Sample, decode_samples
from .store import frames

_STAMP = struct.Struct(">Q")


@dataclass
class Exported:
    """What an export wrote: frames read, the first and last receive time (µs; None if no frame), files."""

    frames: int = 0
    first_us: int | None = None
    last_us: int | None = None
    written: list | None = None
    #: the decoder the recordings came from (export_recordings)
    decoder: Decoder | None = None


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


#: the messages the recordings are made of (`ground.decode.Decoder.handle`); every other frame only
#: counts in the link accounting, so it is not decoded (the rows and metadata are the same)
_RECORDED = SAMPLE_MESSAGES | KNOWLEDGE_MESSAGES | {"DEBRIS_LOOP_STATUS", "DEBRIS_SAMPLE_STORE"}
#: of them, the one only the rate estimates' file is made of (decoded when that file is asked for)
_RATES_ONLY = "DEBRIS_RATE_ESTIMATE"


def export_recordings(conn: sqlite3.Connection, sysid: int, csv: str | os.PathLike | None,
                      rates_csv: str | os.PathLike | None = None, from_us: int | None = None,
                      to_us: int | None = None, *, method: int = mavlink.DEBRIS_RATE_METHOD_BOER, origin: str = "",
                      protect=()) -> Exported:
    """Decode box `sysid`'s frames with from_us <= t < to_us through `ground.decode.Decoder` and write
    its recordings (`csv`) and rate estimates of `method` (`rates_csv`); `protect`: files the recorder's extra files
    (other runs) may never take the name of. The sample messages are decoded in bulk, `CHUNK` frames at a time
    (`ground.archive.bulk`); frames of messages the recordings do not use go to the decoder's link accounting and
    clock only (a `Sample` without fields: its header): the same files, at a fraction of the time."""
    recorder = Recorder(csv, rates_csv, protect=protect, hold_rows=HOLD_ROWS)
    decoder = Decoder(method=method, origin=origin, recorder=recorder, rounded=True)
    out = Exported(decoder=decoder)
    with _without_cycle_collection():
        _decode_interval(frames(conn, sysid, from_us, to_us, with_msgid=True), decoder, out,
                         _RECORDED if rates_csv is not None else _RECORDED - {_RATES_ONLY})
    out.written = list(recorder.written)
    return out


@contextmanager
def _without_cycle_collection():
    """Python's cyclic garbage collector held off: the decoder's tables grow by about ten objects a sample,
    all alive to the end, and the collector went through them again and again (a sixth of the export's
    time). Nothing here makes reference cycles; memory is freed by reference counting as before."""
    was = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if was:
            gc.enable()


def _decode_interval(rows, decoder: Decoder, out: Exported, used: set[str]) -> None:
    """`export_recordings`' work: the frames (time, msgid, frame) through the decoder, `CHUNK` at a time, those
    of the messages `used` decoded."""
    decode = Deframer().decode
    stats, counts = decoder.stats, decoder.frames_by_type
    handle, accounted, on_frame, tick = decoder.handle, decoder.accounted, stats.on_frame, decoder.tick
    recorded = {msgid for msgid, cls in mavlink.mavlink_map.items() if cls.msgname in used}
    names = {msgid: cls.msgname for msgid, cls in mavlink.mavlink_map.items()}
    n = 0
    while chunk := list(islice(rows, CHUNK)):
        if n == 0:
            out.first_us = chunk[0][0]
        msgs = _bulk(chunk, recorded)
        for i, (_, msgid, frame) in enumerate(chunk):
            if msgs[i] is None and (msgid in recorded or msgid not in names):
                msgs[i] = _rounded(decode(frame))
        sources = [_source(f) for _, _, f in chunk]
        bulk = _account(stats, chunk, sources, msgs)
        due_s = decoder.tick_due_s              # the decoder's tick does nothing before then
        for (t_us, msgid, frame), src, msg in zip(chunk, sources, msgs):
            now_s = t_us * 1e-6
            if src in bulk:                     # accounted already: all new, all intact
                if msg is not None:
                    stats.last_verdict = "new"
                    accounted(names[msgid], msg, now_s)
            elif msg is not None:
                handle(msg, now_s)              # ticks
                due_s = decoder.tick_due_s
                continue
            else:
                on_frame(Sample(frame, names[msgid], msgid, {}), now_s)   # its header, undecoded
            if now_s >= due_s:
                tick(now_s)
                due_s = decoder.tick_due_s
        ids = (Counter(map(itemgetter(1), chunk)) if len(bulk) == len(set(sources))
               else Counter(msgid for (_, msgid, _), src in zip(chunk, sources) if src in bulk))
        counts.update({names[msgid]: k for msgid, k in ids.items()})
        n += len(chunk)
        out.last_us = chunk[-1][0]
    if n:
        decoder.finish()
    out.frames = n


def _account(stats, chunk: list[tuple], sources: list[tuple[int, int]], msgs: list) -> set:
    """The link accounting of the chunk's frames done at once, per source (`LinkStats.on_run`), for the
    sources whose frames are all intact, of known messages and new (no loss, copy or reordering): those
    sources. The others' frames go to the decoder one by one, as received. (Every frame of an unknown
    message, and every one the bulk decoding refused, is in `msgs` as pymavlink decoded it.)"""
    refused = {sources[i] for i, m in enumerate(msgs) if m is not None and not isinstance(m, tuple)
               and (m.get_msgId() < 0 or m.get_type().startswith("UNKNOWN"))}
    by_source: dict[tuple[int, int], list[int]] = {}
    for i, src in enumerate(sources):
        by_source.setdefault(src, []).append(i)
    done = set()
    for src, places in by_source.items():
        if src in refused or src == _NO_SOURCE:
            continue
        frames_ = [chunk[i][2] for i in places]
        seqs = np.fromiter((f[4] if f[0] == 0xFD else f[2] for f in frames_), dtype=np.int64, count=len(frames_))
        imu = [msgs[i] for i in places if chunk[i][1] == _HIGHRES_IMU and msgs[i] is not None]
        times = [int(m.time_usec) for m in imu if m.fields_updated & MAG_FIELDS == MAG_FIELDS
                 and m.time_usec < MAX_TIME_US]
        if stats.on_run(src, seqs, frames_, chunk[places[0]][0] * 1e-6, chunk[places[-1]][0] * 1e-6, times):
            done.add(src)
    return done


_HIGHRES_IMU = mavlink.MAVLINK_MSG_ID_HIGHRES_IMU
#: the source of a frame too short to hold one (never accounted in bulk)
_NO_SOURCE = (-1, -1)


def _source(frame: bytes) -> tuple[int, int]:
    """(sysid, compid) of a raw MAVLink 2 or 1 frame."""
    if len(frame) >= 10 and frame[0] == 0xFD:
        return frame[5], frame[6]
    if len(frame) >= 6 and frame[0] == 0xFE:
        return frame[3], frame[4]
    return _NO_SOURCE


#: frames decoded in bulk at a time
CHUNK = 20_000
#: rows of a recording formatted and written at a time
HOLD_ROWS = 20_000


def _bulk(chunk: list[tuple], recorded: set[int]) -> list:
    """The chunk's sample messages of the ids `recorded` decoded in bulk, at their place in the chunk (None
    elsewhere, and for those that fail a check: left to pymavlink)."""
    where: dict[int, list[int]] = {}
    for i, (_, msgid, _) in enumerate(chunk):
        if msgid in LAYOUTS and msgid in recorded:
            where.setdefault(msgid, []).append(i)
    out = [None] * len(chunk)
    for msgid, places in where.items():
        for i, msg in zip(places, decode_samples([chunk[i][2] for i in places], msgid)):
            out[i] = msg
    return out


def _rounded(msg):
    """A sample message pymavlink decoded, its `F32_FIELDS` rounded as `Decoder(rounded=True)` takes them."""
    for name in F32_FIELDS.get(msg.get_type(), ()):
        value = getattr(msg, name)
        setattr(msg, name, f32(*value) if isinstance(value, list) else f32(value)[0])
    return msg
