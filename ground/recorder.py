"""Recordings written while the telemetry arrives, one file per run of each source's flight software.

`--csv PATH` (and `--rates-csv PATH`) name the files of the first run recorded; every other run gets a
file beside it, named after its source and its place among that source's runs:
``PATH-stem.SYSID-COMPID.runK.csv`` (e.g. ``run.1-191.run2.csv`` after a restart of the box,
``run.7-1.run1.csv`` for a second source). Nothing received is ever left out because another source or
run appeared.

Rows go out in time order as they settle: a sample is written once it has been in hand for
`SETTLE_S` (its truth and estimates arrive in the same breath) and, in a numbered run, once every
earlier number has arrived or been given up (`ground.gaps`). Each batch is one write of whole lines
(`ground.recording.RecordingAppender`), so a decoder killed at any moment leaves files that read up to
their last complete row. At a normal end (the count or duration reached, the end of a .tlog, SIGINT or
SIGTERM) the rest is written; a run that received samples after their place in the file had passed
(given up, then sent again after all) is rewritten in full, in order, atomically.

What the box knew (`ground.box_knowledge`: the UTC of t = 0, its TLE, its calibration) goes into the
metadata block when the file is opened; what arrives or changes later is appended as ``# key: value``
lines between the rows, which the reader takes as the key's new value (`ground.recording`). Appending was
chosen over the alternatives because it never touches what is written: rewriting the header in place
could lose the file to a kill in the middle, a sidecar file can be separated from its recording, and
holding the rows back until the metadata is known would lose them to a kill -9 (the box sends its TLE
once a minute and its calibration converges after a good part of an orbit). So a kill -9 leaves a file
that reads up to its last complete line with the knowledge stated up to then; SIGTERM states the latest
at the end. The calibration changes a little with every DEBRIS_MAGCAL (10 s): it is restated when its
state changes, at most every `MAGCAL_RESTATE_S` of the box's time otherwise, and at the end; ``utc0``
when it moves by `UTC0_RESTATE_S` or more (a new time set); the TLE when it changes.
"""
from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np

from fsw.drivers.mmc5983ma_regs import TESLA_PER_GAUSS
from fsw.telemetry.dialect import mavlink

from .box_knowledge import KEYS as KNOWLEDGE_KEYS
from .box_knowledge import MAGCAL_KEYS
from .recording import RateAppender, RecordingAppender, write_rate_estimates, write_recording
from .streams import Segment

#: how long a sample is held before it is written (its estimates and truth follow within a tick)
SETTLE_S = 1.0
#: a calibration in the same state is restated at most this often (box time), and at the end
MAGCAL_RESTATE_S = 300.0
#: a UTC of t = 0 that moved by less than this is not restated (SYSTEM_TIME's 1 ms steps)
UTC0_RESTATE_S = 0.005
#: keys restated together
_GROUPS = (("tle_line1", "tle_line2"), MAGCAL_KEYS)


class _Files:
    """The output files of one segment."""

    def __init__(self) -> None:
        self.csv: RecordingAppender | None = None
        self.rates: RateAppender | None = None
        self.paths: dict[str, Path] = {}
        self.written_upto_us = -1  # rows up to this sample time are in the files
        self.pending: set[int] = set()  # sample times received and not yet written
        self.dirty = False  # rows arrived after their place had been written: rewrite at the end
        self.stated: dict[str, str] = {}  # what the recording says of the box's knowledge
        self.utc0_s: float | None = None  # the UTC of t = 0 stated
        self.magcal_t_s: float | None = None  # the box time of the calibration stated
        self.held: _Held | None = None  # rows taken and not yet handed to the files (`hold_rows`)


_NAN3 = (math.nan,) * 3
_ZERO3 = (0.0, 0.0, 0.0)


class _Held:
    """The values of rows taken (`Recorder.hold_rows`), as they were when taken, handed to the files in one
    batch: the same columns and values `Decoder.recording` / `Decoder.rate_estimates` give, row by row."""

    def __init__(self) -> None:
        self.times: list[int] = []
        self.mag: list[tuple] = []
        self.truth: list[tuple] = []     # (w, m) per row, when the file has truth columns
        self.kit: list[tuple] = []       # (kit field, flags) per row, when the file has kit columns
        self.estimates: list = []        # the estimate in hand per row, when there is a rates file

    def take(self, seg: Segment, f: _Files, ready: list[int]) -> None:
        self.times.extend(ready)
        if f.csv is not None:
            self.mag.extend(seg.mag_gauss[t] for t in ready)
            if f.csv.truth:
                if seg.truth:
                    nan = (_NAN3, _NAN3)
                    self.truth.extend(seg.truth.get(t, nan) for t in ready)
                else:       # Recording without truth: moments zero, reference rate NaN
                    self.truth.extend([(_NAN3, _ZERO3)] * len(ready))
            if f.csv.kit:
                if seg.kit_seen:
                    zero = (_ZERO3, 0)
                    self.kit.extend(seg.kit.get(t, zero) for t in ready)
                else:
                    self.kit.extend([(_ZERO3, 0)] * len(ready))
        if f.rates is not None:
            self.estimates.extend(seg.estimate.get(t) for t in ready)

    def hand_over(self, f: _Files) -> None:
        if not self.times:
            return
        t_s = np.array(self.times, dtype=float) / 1e6
        n = len(self.times)
        if f.csv is not None:
            b_T = np.array(self.mag, dtype=float).reshape(-1, 3) * TESLA_PER_GAUSS
            m = w = kit = flags = None
            if f.csv.truth:
                w = np.array([x[0] for x in self.truth], dtype=float).reshape(-1, 3)
                m = np.array([x[1] for x in self.truth], dtype=float).reshape(-1, 3)
            if f.csv.kit:
                kit = np.array([x[0] for x in self.kit], dtype=float).reshape(-1, 3) * TESLA_PER_GAUSS
                flags = np.array([x[1] for x in self.kit], dtype=np.int64)
            f.csv.append(t_s, b_T, m, w, kit, flags)
        if f.rates is not None:
            w = np.full((n, 3), np.nan)
            s = np.full((n, 3), np.nan)
            for i, est in enumerate(self.estimates):
                if est is not None and not est[2] & mavlink.DEBRIS_ESTIMATE_FLAGS_NO_ESTIMATE:
                    w[i], s[i] = est[0], est[1]
            f.rates.append(t_s, w, s)
        self.__init__()


class Recorder:
    """Writes a decoder's segments to `csv` / `rates_csv` (either may be None) as they settle."""

    def __init__(self, csv: str | os.PathLike | None, rates_csv: str | os.PathLike | None, *,
                 protect=(), settle_s: float = SETTLE_S, hold_rows: int = 0) -> None:
        """`hold_rows`: the rows are handed to the files and written that many at a time (their values as
        they were when they settled; the same files): for recordings made from data at rest."""
        self.hold_rows = hold_rows
        self.bases = {"csv": None if csv is None else Path(csv),
                      "rates": None if rates_csv is None else Path(rates_csv)}
        self.settle_s = settle_s
        self._protect = [Path(p) for p in protect]
        self._files: dict[int, _Files] = {}
        self._claimed = False
        #: (what, path) of every file written, in the order they were opened
        self.written: list[tuple[str, Path]] = []

    @property
    def active(self) -> bool:
        return any(self.bases.values())

    def _paths(self, source: tuple[int, int], index: int) -> dict[str, Path]:
        out = {}
        for kind, base in self.bases.items():
            if base is None:
                continue
            if not self._claimed:
                out[kind] = base
                continue
            p = base.with_name(f"{base.stem}.{source[0]}-{source[1]}.run{index + 1}{base.suffix}")
            while any(_same(p, q) for q in self._protect):
                p = p.with_name(f"{p.stem}_{p.suffix}")
            out[kind] = p
        self._claimed = True
        return out

    def service(self, decoder, now_s: float) -> None:
        """Write every segment's settled rows."""
        if not self.active:
            return
        for stream in decoder.streams.values():
            for index, seg in enumerate(stream.segments):
                self._write(decoder, stream.source, index, seg, now_s, final=False)

    def finish(self, decoder) -> None:
        """Write what is left (gaps given up), close, and rewrite the runs that need it."""
        if not self.active:
            return
        for stream in decoder.streams.values():
            for index, seg in enumerate(stream.segments):
                seg.gaps.give_up_all()
                self._write(decoder, stream.source, index, seg, 0.0, final=True)
                f = self._files.get(id(seg))
                if f is None:
                    continue
                self._hand_over(f)
                if f.csv is not None and not f.dirty:
                    missing = seg.report()["missing"]
                    if missing:
                        f.csv.comment("samples_missing", str(missing))
                for app in (f.csv, f.rates):
                    if app is not None:
                        app.close()
                if f.dirty:
                    if "csv" in f.paths:
                        write_recording(f.paths["csv"], decoder.recording(seg))
                    if "rates" in f.paths:
                        write_rate_estimates(f.paths["rates"], decoder.rate_estimates(seg))

    def added(self, seg: Segment, t_us: int) -> None:
        """A new sample in `seg` (the decoder calls this for every one)."""
        if not self.active:
            return
        f = self._files.get(id(seg))
        if f is None:
            f = self._files[id(seg)] = _Files()
        if t_us <= f.written_upto_us:
            f.dirty = True  # its place in the file has passed: the run is rewritten at the end
        else:
            f.pending.add(t_us)

    def _write(self, decoder, source, index: int, seg: Segment, now_s: float, final: bool) -> None:
        f = self._files.get(id(seg))
        if f is None:
            return
        if f.pending:
            self._write_rows(decoder, source, index, seg, f, now_s, final)
        if f.csv is not None:
            self._restate(seg, f, final)

    def _restate(self, seg: Segment, f: _Files, final: bool) -> None:
        """Append what the box's knowledge says now and the file does not (see the module's docstring)."""
        k = seg.knowledge
        now = k.metadata()
        changed = {key: v for key, v in now.items() if f.stated.get(key) != v}
        if "utc0" in changed and f.utc0_s is not None and abs(k.utc0_s - f.utc0_s) < UTC0_RESTATE_S:
            del changed["utc0"]
        if any(key in changed for key in MAGCAL_KEYS) and not final and "magcal_state" in f.stated \
                and f.stated["magcal_state"] == k.magcal_state and k.magcal_t_s - f.magcal_t_s < MAGCAL_RESTATE_S:
            for key in MAGCAL_KEYS:
                changed.pop(key, None)
        for group in _GROUPS:
            if any(key in changed for key in group):
                changed.update({key: now[key] for key in group if key in now})
        if not changed:
            return
        self._hand_over(f)
        f.csv.comments({key: changed[key] for key in KNOWLEDGE_KEYS if key in changed})
        self._stated(f, seg, changed)

    @staticmethod
    def _stated(f: _Files, seg: Segment, meta: dict[str, str]) -> None:
        f.stated.update({key: v for key, v in meta.items() if key in KNOWLEDGE_KEYS})
        if "utc0" in meta:
            f.utc0_s = seg.knowledge.utc0_s
        if "magcal_t_s" in meta:
            f.magcal_t_s = seg.knowledge.magcal_t_s

    def _write_rows(self, decoder, source, index: int, seg: Segment, f: _Files, now_s: float, final: bool) -> None:
        ready = []
        for t in sorted(f.pending):
            if not final:
                if seg.arrived_s[t] > now_s - self.settle_s:
                    break
                if seg.numbered and seg.seq_of[t] >= seg.gaps.watermark:
                    break
            ready.append(t)
        if not ready:
            return
        f.pending.difference_update(ready)
        if f.csv is None and f.rates is None:
            f.paths = self._paths(source, index)
            meta = decoder.metadata(seg)
            if "csv" in f.paths:
                f.csv = RecordingAppender(f.paths["csv"], meta, truth=bool(seg.truth), kit=seg.kit_seen)
                self._stated(f, seg, meta)
                self.written.append(("recording", f.paths["csv"]))
            if "rates" in f.paths:
                f.rates = RateAppender(f.paths["rates"], decoder.rate_metadata(seg))
                self.written.append(("rate estimates", f.paths["rates"]))
        if self.hold_rows:
            f.written_upto_us = ready[-1]
            if f.held is None:
                f.held = _Held()
            if f.csv is not None:
                if seg.truth and not f.csv.truth:
                    f.dirty = True  # as below
                if seg.kit_seen and not f.csv.kit:
                    f.dirty = True
            f.held.take(seg, f, ready)
            if len(f.held.times) >= self.hold_rows:
                self._hand_over(f)
            return
        if f.csv is not None:
            rec = decoder.recording(seg, ready)
            if rec.w_ref_radps is not None and not f.csv.truth:
                f.dirty = True  # truth appeared after the file was opened without its columns
            if rec.kit_T is not None and not f.csv.kit:
                f.dirty = True  # the kit's field appeared after the file was opened without its columns
            nan3 = np.full((len(ready), 3), np.nan)
            f.csv.append(rec.t_s, rec.b_T, rec.m_Nm, rec.w_ref_radps if rec.w_ref_radps is not None else nan3,
                         rec.kit_T if rec.kit_T is not None else np.zeros((len(ready), 3)),
                         rec.flags if rec.flags is not None else np.zeros(len(ready)))
        if f.rates is not None:
            est = decoder.rate_estimates(seg, ready)
            f.rates.append(est.t_s, est.w_radps, est.sigma_radps)
        f.written_upto_us = ready[-1]

    @staticmethod
    def _hand_over(f: _Files) -> None:
        """The rows held (`hold_rows`) to the files."""
        if f.held is not None:
            f.held.hand_over(f)


def _same(a: Path, b: Path) -> bool:
    try:
        return a.exists() and b.exists() and os.path.samefile(a, b)
    except OSError:
        return False
