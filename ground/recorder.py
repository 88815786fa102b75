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
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from .recording import RateAppender, RecordingAppender, write_rate_estimates, write_recording
from .streams import Segment

#: how long a sample is held before it is written (its estimates and truth follow within a tick)
SETTLE_S = 1.0


class _Files:
    """The output files of one segment."""

    def __init__(self) -> None:
        self.csv: RecordingAppender | None = None
        self.rates: RateAppender | None = None
        self.paths: dict[str, Path] = {}
        self.written_upto_us = -1  # rows up to this sample time are in the files
        self.pending: set[int] = set()  # sample times received and not yet written
        self.dirty = False  # rows arrived after their place had been written: rewrite at the end


class Recorder:
    """Writes a decoder's segments to `csv` / `rates_csv` (either may be None) as they settle."""

    def __init__(self, csv: str | os.PathLike | None, rates_csv: str | os.PathLike | None, *,
                 protect=(), settle_s: float = SETTLE_S) -> None:
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
        if f is None or not f.pending:
            return
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
                f.csv = RecordingAppender(f.paths["csv"], meta, truth=bool(seg.truth))
                self.written.append(("recording", f.paths["csv"]))
            if "rates" in f.paths:
                f.rates = RateAppender(f.paths["rates"], decoder.rate_metadata(seg))
                self.written.append(("rate estimates", f.paths["rates"]))
        if f.csv is not None:
            rec = decoder.recording(seg, ready)
            if rec.w_ref_radps is not None and not f.csv.truth:
                f.dirty = True  # truth appeared after the file was opened without its columns
            f.csv.append(rec.t_s, rec.b_T, rec.m_Nm,
                         rec.w_ref_radps if rec.w_ref_radps is not None else np.full((len(ready), 3), np.nan))
        if f.rates is not None:
            est = decoder.rate_estimates(seg, ready)
            f.rates.append(est.t_s, est.w_radps, est.sigma_radps)
        f.written_upto_us = ready[-1]


def _same(a: Path, b: Path) -> bool:
    try:
        return a.exists() and b.exists() and os.path.samefile(a, b)
    except OSError:
        return False
