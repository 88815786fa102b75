"""Decode the box's MAVLink telemetry: live status, loss accounting, tlog and recording-format CSVs.

    python -m ground.decode URL [--baud B] [--tlog FILE] [--csv FILE] [--rates-csv FILE]
                                [--method boer|derivative|kalman] [--duration S] [--count N] [--quiet]

URL is any pymavlink connection string: ``udpin:0.0.0.0:14550``, ``tcp:host:port``, a serial device
(with ``--baud``) or a ``.tlog`` file (read to its end, on its recorded timeline; a damaged one is read
as far as it is intact: `ground.tlog`, what was skipped is reported in the summary).

Before anything is opened, the output paths are checked (`fsw.files.check_paths`): an output that is
the input or another output (also through a link), or that cannot be written, is refused (exit 2).
`--method` offers the estimators the flight software sends (`fsw.flight.METHODS`); the ground-only
methods are `ground.estimate`'s.

Parsing is pymavlink's robust parser bound to the project dialect: bytes that do not frame, frames
with a bad CRC and frames of unknown message ids are rejected and counted (`ground.link_stats`), never
fatal. About once a second a line shows the last magnetometer sample's time and |B|, the onboard rate
estimate of the selected method, the simulator's true rate when DEBRIS_SIM_STATE arrives (SITL), the
identification experiment's latest inertia estimate (DEBRIS_INERTIA_ESTIMATE: diagonal ± 95 %, state;
all of them in `Decoder.inertia_estimates`), and the loss so far. At the end a summary: frames by type, loss per source, rejected data.

Outputs
- ``--tlog``: every intact frame as received (pymavlink tlog: 8-byte big-endian µs time stamp, then
  the raw frame), streamed while running so that a crash keeps what came before it.
- ``--csv``: the magnetometer samples (HIGHRES_IMU with the mag bits in fields_updated, gauss → µT) in
  recording format v1, time = the flight software's sample time; with DEBRIS_SIM_STATE present (SITL)
  the reference rate w*_dps and the applied moment m*_Nm of the same sample (matched on time_usec;
  NaN for a sample whose truth frame was lost).
- ``--rates-csv``: the onboard estimates of the selected method, one row per magnetometer sample, NaN
  where none arrived or the estimate is flagged DEBRIS_ESTIMATE_FLAGS_NO_ESTIMATE.
The CSVs are written atomically when decoding stops: duration or count reached, end of a tlog, or
Ctrl-C. Frames with non-finite values (or a negative σ) are counted and left out, never
written. Samples are taken from one source, the first that sends magnetometer samples. When the
flight software restarts (its DEBRIS_LOOP_STATUS tick count goes back, or a sample is older than any of
the current run), a new segment begins; the CSVs hold the last one.

Store and forward: samples the box kept during a link outage arrive later, older than the newest;
they are merged by time (``late`` in the summary), and the summary lists what is still missing
(gaps in the sample times, at the median sample period).

``--key FILE``: verify every frame's MAVLink 2 signature with the mission key (`fsw.telemetry.signing`,
with a 64-frame reorder window); unsigned, wrongly signed or replayed frames are counted by reason
and not used (the link accounting and the tlog still see every intact frame).
"""
from __future__ import annotations

import argparse
import itertools
import math
import struct
import sys
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from fsw.telemetry import dialect
from fsw.telemetry.dialect import mavlink

from fsw.telemetry.signing import (TICKS_PER_S, UNIX_TO_MAVLINK_EPOCH_S, SigningClock, Verdict, Verifier,
                                   load_key)

from fsw.telemetry.framing import Deframer

from fsw.argtypes import check_paths_or_exit, finite_float, int_range, link_url
from fsw.files import check_paths

from .link_stats import MAG_FIELDS, LinkStats
from .recording import RateEstimates, Recording, write_rate_estimates, write_recording
from .tlog import read_tlog

#: DEBRIS_RATE_METHOD values by their short lower-case name (boer, derivative, ...).
METHODS: dict[str, int] = {
    entry.name.removeprefix("DEBRIS_RATE_METHOD_").lower(): value
    for value, entry in mavlink.enums["DEBRIS_RATE_METHOD"].items()
    if not entry.name.endswith("_ENUM_END")}
METHOD_NAMES = {value: name for name, value in METHODS.items()}

T_PER_GAUSS = 1e-4
#: Sample time going back by more than this means the flight software restarted.
RESTART_BACKSTEP_S = 1.0
#: Messages whose time_usec is the magnetometer sample time.
SAMPLE_MESSAGES = frozenset({"HIGHRES_IMU", "DEBRIS_RATE_ESTIMATE", "DEBRIS_SIM_STATE"})


def f32(*values: float) -> tuple[float, ...]:
    """MAVLink float fields as the shortest decimals that round to the same float32: 0.1 sent as
    float32 reads 0.1, not 0.10000000149011612 (both are within the float32 rounding the sender
    applied; this one is what the sender most likely meant)."""
    return tuple(float(str(np.float32(v))) for v in values)


@dataclass
class _Segment:
    """Samples of one run of the flight software, keyed by sample time (µs)."""

    mag_gauss: dict[int, tuple[float, float, float]] = field(default_factory=dict)
    estimate: dict[int, tuple[tuple[float, ...], tuple[float, ...], int]] = field(default_factory=dict)
    truth: dict[int, tuple[tuple[float, ...], tuple[float, ...]]] = field(default_factory=dict)
    latest_us: int = -1
    first_us: int = -1
    late: int = 0  # magnetometer samples that arrived after a newer one (store-and-forward replay)
    arrivals: list[int] = field(default_factory=list)  # sample times since the last DEBRIS_LOOP_STATUS


class Decoder:
    """Stateful decoding of a telemetry stream; feed it every message pymavlink returns."""

    def __init__(self, method: int = mavlink.DEBRIS_RATE_METHOD_BOER,
                 source: tuple[int, int] | None = None,
                 on_line: Callable[[str], None] | None = None, origin: str = "",
                 line_period_s: float = 1.0, key: bytes | None = None) -> None:
        """`method`: the DEBRIS_RATE_METHOD exported and shown; `source`: (sysid, compid) to record
        from, None = the first to send samples; `on_line`: receives the live line about every
        `line_period_s` of `now_s`; `origin`: the link, for the CSVs' ``# source:``; `key`: verify
        signatures with this mission key (`now_s` is then Unix time, or 0 when unknown)."""
        if method not in METHOD_NAMES:
            raise ValueError(f"unknown DEBRIS_RATE_METHOD {method}")
        self.method = method
        self.source = source
        self.on_line = on_line
        self.origin = origin
        self.line_period_s = line_period_s
        self.stats = LinkStats()
        self.frames_by_type: Counter[str] = Counter()
        #: Intact frames whose values cannot be a sample (NaN/inf field, negative σ), by type.
        self.invalid: Counter[str] = Counter()
        self.segments: list[_Segment] = [_Segment()]
        self._next_line_s: float | None = None
        self._last_est: tuple[float, ...] | None = None
        self._last_truth: tuple[float, ...] | None = None
        self.interrupted = False
        # now_s is Unix time: the signing clock's epoch maps it to 10 µs since 2015
        self.verifier = None if key is None else Verifier(
            key, SigningClock(epoch=-UNIX_TO_MAVLINK_EPOCH_S * TICKS_PER_S), window=64)
        #: intact frames refused by the signature check, by reason
        self.unauthenticated: Counter[str] = Counter()
        self._loop_time_us: int | None = None
        #: decoded DEBRIS_INERTIA_ESTIMATE messages, in arrival order (see `_inertia`)
        self.inertia_estimates: list[dict] = []

    # --- input -------------------------------------------------------------------------------

    def handle(self, msg, now_s: float) -> None:
        """Account and decode one message (any type, including BAD_DATA / UNKNOWN_*)."""
        kind = msg.get_type()
        self.frames_by_type[kind] += 1
        self.stats.on_frame(msg, now_s)
        if msg.get_msgId() >= 0 and self.stats.last_verdict != "duplicate" and not kind.startswith("UNKNOWN"):
            if self.verifier is not None:
                verdict = self.verifier.check(bytes(msg.get_msgbuf()), now_s)
                if verdict is not Verdict.OK:
                    self.unauthenticated[verdict.value] += 1
                    self.tick(now_s)
                    return
            if kind in SAMPLE_MESSAGES:
                self._sample_message(kind, msg)
            elif kind == "DEBRIS_LOOP_STATUS" and self.stats.last_verdict == "new":
                self._loop_status(msg)
            elif kind == "DEBRIS_INERTIA_ESTIMATE":
                self._inertia(msg)
        self.tick(now_s)

    def _inertia(self, msg) -> None:
        """DEBRIS_INERTIA_ESTIMATE (the identification experiment's running/final estimate), kept in
        ``inertia_estimates`` as dicts in SI with the state name; non-finite values are refused."""
        vals = f32(*msg.inertia, *msg.ci95, *msg.ci99)
        if not all(map(math.isfinite, vals)) or min(vals[6:]) < 0:
            self.invalid["DEBRIS_INERTIA_ESTIMATE"] += 1
            return
        state = mavlink.enums["DEBRIS_IDENT_STATE"].get(msg.state)
        self.inertia_estimates.append({
            "t_s": msg.time_usec * 1e-6, "samples": int(msg.samples), "inertia_kgm2": vals[:6],
            "ci95_kgm2": vals[6:12], "ci99_kgm2": vals[12:], "state": int(msg.state),
            "state_name": state.name.removeprefix("DEBRIS_IDENT_STATE_").lower() if state else str(msg.state),
            "flags": int(msg.flags)})

    def _loop_status(self, msg) -> None:
        """The live loop time going back means the flight software restarted: a new segment, which takes
        the samples that arrived since the previous DEBRIS_LOOP_STATUS and are not after this one."""
        if self.source is not None and (msg.get_srcSystem(), msg.get_srcComponent()) != self.source:
            return
        t_us = int(msg.time_usec)
        seg = self.segments[-1]
        if self._loop_time_us is not None and t_us < self._loop_time_us - RESTART_BACKSTEP_S * 1e6:
            self._say(f"loop time went back from {self._loop_time_us * 1e-6:.3f} s to {t_us * 1e-6:.3f} s: "
                      "flight software restarted, new recording segment")
            new = _Segment()
            for t in seg.arrivals:
                if t <= t_us:
                    for table in ("mag_gauss", "estimate", "truth"):
                        old = getattr(seg, table)
                        if t in old:
                            getattr(new, table)[t] = old.pop(t)
            if new.mag_gauss or new.estimate or new.truth:
                times = [*new.mag_gauss, *new.estimate, *new.truth]
                new.first_us, new.latest_us = min(times), max(times)
            self.segments.append(new)
            seg = new
        self._loop_time_us = t_us
        seg.arrivals.clear()

    def _sample_message(self, kind: str, msg) -> None:
        src = (msg.get_srcSystem(), msg.get_srcComponent())
        if kind == "HIGHRES_IMU" and msg.fields_updated & MAG_FIELDS != MAG_FIELDS:
            return
        if self.source is None:
            self.source = src
        if src != self.source:
            return
        t_us = int(msg.time_usec)
        seg = self.segments[-1]
        if t_us < seg.latest_us - RESTART_BACKSTEP_S * 1e6 and t_us < seg.first_us:
            self._say(f"sample time went back from {seg.latest_us * 1e-6:.3f} s to {t_us * 1e-6:.3f} s: "
                      "flight software restarted, new recording segment")
            seg = _Segment()
            self.segments.append(seg)
        if kind == "HIGHRES_IMU" and t_us < seg.latest_us and t_us not in seg.mag_gauss:
            seg.late += 1  # kept on board during an outage, replayed: merged by time
        seg.latest_us = max(seg.latest_us, t_us)
        seg.first_us = t_us if seg.first_us < 0 else min(seg.first_us, t_us)
        seg.arrivals.append(t_us)
        if kind == "HIGHRES_IMU":
            b = f32(msg.xmag, msg.ymag, msg.zmag)
            if not all(map(math.isfinite, b)):
                self.invalid[kind] += 1
                return
            seg.mag_gauss[t_us] = b
        elif kind == "DEBRIS_RATE_ESTIMATE":
            if msg.method == self.method:
                w, sigma = f32(msg.wx, msg.wy, msg.wz), f32(msg.sx, msg.sy, msg.sz)
                if not all(map(math.isfinite, w + sigma)) or min(sigma) < 0:
                    self.invalid[kind] += 1
                    return
                seg.estimate[t_us] = (w, sigma, msg.flags)
                if not msg.flags & mavlink.DEBRIS_ESTIMATE_FLAGS_NO_ESTIMATE:
                    self._last_est = w
        else:
            w, m = f32(msg.wx, msg.wy, msg.wz), f32(msg.mx, msg.my, msg.mz)
            if not all(map(math.isfinite, w + m)):
                self.invalid[kind] += 1
                return
            seg.truth[t_us] = (w, m)
            self._last_truth = w

    def tick(self, now_s: float) -> None:
        """Emit the live line when one is due (call also when nothing arrives)."""
        if self._next_line_s is None:
            self._next_line_s = now_s + self.line_period_s
        elif now_s >= self._next_line_s:
            self._next_line_s = max(self._next_line_s + self.line_period_s, now_s)
            self._say(self.status_line())

    def _say(self, line: str) -> None:
        if self.on_line is not None:
            self.on_line(line)

    # --- views -------------------------------------------------------------------------------

    def _recorded(self) -> _Segment:
        """The last segment that holds magnetometer samples (or the current one)."""
        return next((s for s in reversed(self.segments) if s.mag_gauss), self.segments[-1])

    def status_line(self) -> str:
        seg = self._recorded()
        parts = []
        if seg.mag_gauss:
            t_us = max(seg.mag_gauss)
            b_uT = math.sqrt(sum(x * x for x in seg.mag_gauss[t_us])) * T_PER_GAUSS * 1e6
            parts.append(f"t {t_us * 1e-6:9.3f} s  |B| {b_uT:6.2f} µT")
        else:
            parts.append("no magnetometer samples yet")
        name = METHOD_NAMES[self.method]
        if self._last_est is not None:
            w = np.rad2deg(self._last_est)
            parts.append(f"ω[{name}] ({w[0]:+7.2f} {w[1]:+7.2f} {w[2]:+7.2f}) |{np.linalg.norm(w):6.2f}| °/s")
        else:
            parts.append(f"ω[{name}] —")
        if self._last_truth is not None:
            parts.append(f"true |ω| {np.linalg.norm(np.rad2deg(self._last_truth)):6.2f} °/s")
        if self.inertia_estimates:
            e = self.inertia_estimates[-1]
            if e["samples"]:
                i, c = e["inertia_kgm2"], e["ci95_kgm2"]
                parts.append(f"I[{e['state_name']}] ({i[0]:.1f}±{c[0]:.1f} {i[1]:.1f}±{c[1]:.1f} "
                             f"{i[2]:.1f}±{c[2]:.1f}) kg·m²")
            else:
                parts.append(f"I[{e['state_name']}] —")
        received, lost = self.stats.received(), self.stats.lost()
        pct = 100.0 * lost / (received + lost) if received + lost else 0.0
        parts.append(f"frames {received} lost {lost} ({pct:.1f} %)")
        return "  ".join(parts)

    def _metadata(self) -> dict[str, str]:
        where = f" from {self.origin}" if self.origin else ""
        who = f", system {self.source[0]} component {self.source[1]}" if self.source else ""
        meta = {"source": f"MAVLink telemetry{where}{who}, decoded by ground.decode",
                "time": "flight software sample time (HIGHRES_IMU time_usec) since it started"}
        if len(self.segments) > 1:
            meta["segment"] = (f"last of {len(self.segments)} runs of the flight software "
                               "(restarts seen in the stream)")
        return meta

    def recording(self) -> Recording:
        """The magnetometer samples as a Recording (SI), with simulation truth where it arrived."""
        seg = self._recorded()
        times = sorted(seg.mag_gauss)
        t_s = np.array(times, dtype=float) / 1e6
        b_T = np.array([seg.mag_gauss[t] for t in times], dtype=float).reshape(-1, 3) * T_PER_GAUSS
        meta = self._metadata()
        if not seg.truth:
            return Recording(t_s=t_s, b_T=b_T, metadata=meta)
        nan3 = ((math.nan,) * 3, (math.nan,) * 3)
        truth = [seg.truth.get(t, nan3) for t in times]
        w = np.array([x[0] for x in truth], dtype=float).reshape(-1, 3)
        m = np.array([x[1] for x in truth], dtype=float).reshape(-1, 3)
        meta["reference"] = "DEBRIS_SIM_STATE: simulation truth, for scoring only"
        return Recording(t_s=t_s, b_T=b_T, m_Nm=m, w_ref_radps=w, metadata=meta)

    def rate_estimates(self) -> RateEstimates:
        """Onboard estimates of the selected method, one row per magnetometer sample (NaN where
        none arrived or the estimate is flagged NO_ESTIMATE)."""
        seg = self._recorded()
        times = sorted(seg.mag_gauss)
        w = np.full((len(times), 3), np.nan)
        s = np.full((len(times), 3), np.nan)
        for i, t in enumerate(times):
            est = seg.estimate.get(t)
            if est is not None and not est[2] & mavlink.DEBRIS_ESTIMATE_FLAGS_NO_ESTIMATE:
                w[i], s[i] = est[0], est[1]
        meta = self._metadata()
        meta["method"] = f"{METHOD_NAMES[self.method]} (onboard, DEBRIS_RATE_ESTIMATE)"
        return RateEstimates(t_s=np.array(times, dtype=float) / 1e6, w_radps=w, sigma_radps=s,
                             metadata=meta)

    def summary_text(self) -> str:
        """Frames by type, loss per source, rejected data: the end-of-run report."""
        out = ["frames by type: " + (", ".join(f"{k} {n}" for k, n in sorted(self.frames_by_type.items()))
                                     or "none")]
        summary = self.stats.summary()
        for (sysid, compid), s in summary["sources"].items():
            out.append(f"source {sysid}/{compid}: received {s['received']}, lost {s['lost']} "
                       f"({100 * s['loss_fraction']:.2f} %), duplicates {s['duplicates']}, late {s['late']}, "
                       f"out of sequence {s['out_of_sequence']}, unknown ids {s['unknown']}; "
                       f"magnetometer samples {s['samples']}, missing {s['samples_missing']}")
        out.append(f"rejected: {summary['garbage_bytes']} garbage bytes in {summary['garbage_chunks']} runs, "
                   f"{summary['bad_crc']} bad CRC, {summary['malformed']} malformed, "
                   f"{summary['unknown']} unknown message ids")
        rep = self.sample_report()
        if rep["samples"]:
            late = f", {rep['late']} of them replayed after an outage and merged by time" if rep["late"] else ""
            if rep["missing"]:
                shown = ", ".join(f"{a:.3f}–{b:.3f} s ({k})" for a, b, k in rep["gaps"][:5])
                more = f" and {len(rep['gaps']) - 5} more" if len(rep["gaps"]) > 5 else ""
                lost = f"{rep['missing']} missing in {len(rep['gaps'])} gaps: {shown}{more}"
            else:
                lost = "none missing"
            out.append(f"magnetometer samples recorded: {rep['samples']}{late}; {lost}")
        if self.verifier is not None:
            refused = ", ".join(f"{k} {n}" for k, n in sorted(self.unauthenticated.items())) or "none"
            out.append(f"signatures: {self.verifier.counts[Verdict.OK]} frames verified; refused: {refused}")
        if self.invalid:
            out.append("not recorded, non-finite values: "
                       + ", ".join(f"{k} {n}" for k, n in sorted(self.invalid.items())))
        if len(self.segments) > 1:
            out.append(f"flight software restarts seen: {len(self.segments) - 1}; CSVs hold the last run")
        return "\n".join(out)

    def sample_report(self) -> dict:
        """The recorded run's magnetometer samples: ``samples``, ``late`` (arrived after a newer one:
        replayed from the box's store-and-forward buffer), ``missing`` and the ``gaps`` still open, as
        (last time before, first time after, samples missing) at the median sample period."""
        seg = self._recorded()
        t = np.array(sorted(seg.mag_gauss), dtype=np.int64)
        gaps: list[tuple[float, float, int]] = []
        if t.size >= 3:
            dt = np.diff(t)
            k = np.rint(dt / float(np.median(dt))).astype(np.int64) - 1
            gaps = [(t[i] * 1e-6, t[i + 1] * 1e-6, int(k[i])) for i in np.flatnonzero(k > 0)]
        return {"samples": int(t.size), "late": seg.late, "missing": sum(g[2] for g in gaps), "gaps": gaps}

    def write(self, csv: str | Path | None = None, rates_csv: str | Path | None = None) -> None:
        """Write the recording and/or rate-estimate CSVs (atomically)."""
        if csv is not None:
            write_recording(csv, self.recording())
        if rates_csv is not None:
            write_rate_estimates(rates_csv, self.rate_estimates())


def tlog_record(msg, now_s: float) -> bytes:
    """One tlog record: big-endian µs time stamp (low 2 bits: link id 0, as pymavlink writes it),
    then the frame's bytes as received."""
    return struct.pack(">Q", int(now_s * 1e6) & ~3) + bytes(msg.get_msgbuf())


def run(url: str, *, duration_s: float | None = None, count: int | None = None,
        tlog: str | Path | None = None, csv: str | Path | None = None,
        rates_csv: str | Path | None = None, method: int = mavlink.DEBRIS_RATE_METHOD_BOER,
        quiet: bool = False, on_line: Callable[[str], None] = print, baud: int = 115200,
        clock: Callable[[], float] = time.time, key: bytes | None = None) -> Decoder:
    """Decode `url` until `duration_s` (of the link's time line: `clock` for live links, the
    recorded time stamps for a tlog) or `count` intact frames, the end of a tlog, or Ctrl-C; then
    write the CSVs. Waits on the link in 0.1 s slices, never spins.

    Output paths are checked first (`fsw.files.check_paths`: PathError). A tlog is read by
    `ground.tlog.read_tlog`: every intact record is decoded, damage is skipped and counted in
    ``decoder.tlog_report``; a file with nothing intact raises TlogError and nothing is written. Live
    links are framed by `fsw.telemetry.framing.Deframer` (byte-wise resync, so no intact frame is lost
    to line noise); a serial port that goes away is reopened every second until it is back.
    The CSVs are written on a normal end or Ctrl-C, never after an error."""
    check_paths(inputs={"input": url if Path(url).exists() else None},
                outputs={"--tlog": tlog, "--csv": csv, "--rates-csv": rates_csv})
    decoder = Decoder(method=method, on_line=None if quiet else on_line, origin=url, key=key)
    is_log = Path(url).is_file()
    live = records = None
    if is_log:
        reader = read_tlog(url)
        records = iter(reader)
        records = itertools.chain([next(records)], records)  # TlogError now if nothing is intact
        decoder.tlog_report = reader.report
    else:
        live = _LiveLink(url, baud, decoder._say)
    log_out = None
    frames = 0
    start_s = flushed_s = None
    done = False
    try:
        log_out = open(tlog, "wb") if tlog is not None else None
        while not done:
            if is_log:
                record = next(records, None)
                if record is None:
                    break
                batch, now_s = record.messages, record.t_us * 1e-6
            else:
                batch, now_s = live.read(), clock()
            if start_s is None:
                start_s = flushed_s = now_s
            if not batch:
                decoder.tick(now_s)
            for msg in batch:
                decoder.handle(msg, now_s)
                if msg.get_type() != "BAD_DATA":
                    frames += 1
                    if log_out is not None:
                        log_out.write(tlog_record(msg, now_s))
                if count is not None and frames >= count:
                    done = True
                    break
            if log_out is not None and now_s - flushed_s >= 1.0:
                log_out.flush()
                flushed_s = now_s
            if duration_s is not None and now_s - start_s >= duration_s:
                break
        if not is_log and not done:
            for msg in live.flush():
                decoder.handle(msg, now_s)
                if msg.get_type() != "BAD_DATA" and log_out is not None:
                    log_out.write(tlog_record(msg, now_s))
    except KeyboardInterrupt:
        decoder.interrupted = True
    finally:
        if live is not None:
            live.close()
        if log_out is not None:
            log_out.close()
    decoder.write(csv=csv, rates_csv=rates_csv)
    return decoder


class _LiveLink:
    """A pymavlink connection read as raw bytes and framed by the Deframer; serial ports that fail are
    reopened (once a second)."""

    def __init__(self, url: str, baud: int, say: Callable[[str], None]) -> None:
        self.url, self.baud, self.say = url, baud, say
        self.conn = self._open()
        self.deframer = Deframer()
        self._retry_at = 0.0
        self.reconnects = 0

    def _open(self):
        conn = dialect.open_link(self.url, source_system=dialect.GCS_SYSID, source_component=dialect.GCS_COMPID,
                                 input=True, baud=self.baud)
        conn.first_byte = False  # the dialect is bound already: no protocol auto-switch by pymavlink
        return conn

    def read(self) -> list:
        if self.conn is None:  # the port went away: try it again now and then
            if time.monotonic() < self._retry_at:
                time.sleep(0.1)
                return []
            try:
                self.conn = self._open()
                self.reconnects += 1
                self.say(f"{self.url}: reconnected")
            except OSError:
                self._retry_at = time.monotonic() + 1.0
                return []
        data = bytearray()
        try:
            self.conn.select(0.1)
            for _ in range(64):
                chunk = self.conn.recv(4096)
                if not chunk:
                    break
                data += chunk.encode("latin-1") if isinstance(chunk, str) else chunk
        except OSError as e:  # serial adapter unplugged: keep what came, reopen later
            self.say(f"{self.url}: {e}; reconnecting")
            try:
                self.conn.close()
            except OSError:
                pass
            self.conn = None
            self._retry_at = time.monotonic() + 1.0
        return self.deframer.feed(bytes(data)) if data else []

    def flush(self) -> list:
        return self.deframer.flush()

    def close(self) -> None:
        if self.conn is not None:
            self.conn.close()


def sent_methods() -> dict[str, int]:
    """The DEBRIS_RATE_METHOD values the flight software sends, by name (`fsw.flight.METHODS`)."""
    from fsw.flight import METHODS as SENT  # the estimators run on board; imported here: it loads them

    return {name: value for name, value in METHODS.items() if value in SENT.values()}


def main(argv: list[str] | None = None) -> int:
    sent = sent_methods()
    ap = argparse.ArgumentParser(prog="python -m ground.decode", description=__doc__.splitlines()[0])
    ap.add_argument("url", type=link_url, help="pymavlink connection string: udpin:0.0.0.0:14550, tcp:HOST:PORT, "
                                               "a serial device, or a .tlog file")
    ap.add_argument("--baud", type=int_range(1), default=115200, help="serial baud rate (default 115200)")
    ap.add_argument("--tlog", help="record every intact frame to this tlog")
    ap.add_argument("--csv", help="write the magnetometer samples as a recording-format CSV")
    ap.add_argument("--rates-csv", help="write the onboard rate estimates of --method as CSV")
    ap.add_argument("--method", choices=sorted(sent, key=sent.get), default="boer",
                    help="onboard estimator to show and export (default boer); the ground's own methods: "
                         "python -m ground.estimate")
    ap.add_argument("--duration", type=finite_float(0, min_exclusive=True), metavar="S",
                    help="stop after this many seconds (> 0)")
    ap.add_argument("--count", type=int_range(1), metavar="N", help="stop after this many intact frames (>= 1)")
    ap.add_argument("--quiet", action="store_true", help="no live lines, only the summary")
    ap.add_argument("--key", metavar="FILE", help="mission key file: verify the frames' signatures, use only "
                                                  "authentic ones")
    args = ap.parse_args(argv)
    check_paths_or_exit(ap, inputs={"input": args.url if Path(args.url).exists() else None, "--key": args.key},
                        outputs={"--tlog": args.tlog, "--csv": args.csv, "--rates-csv": args.rates_csv})
    try:
        key = load_key(args.key) if args.key else None
        decoder = run(args.url, duration_s=args.duration, count=args.count, tlog=args.tlog, csv=args.csv,
                      rates_csv=args.rates_csv, method=sent[args.method], quiet=args.quiet,
                      baud=args.baud, key=key)
    except (OSError, ValueError) as e:
        print(f"ground.decode: {e}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("ground.decode: interrupted", file=sys.stderr)
        return 130
    if decoder.interrupted:
        print("interrupted")
    print(decoder.summary_text())
    report = getattr(decoder, "tlog_report", None)
    if report is not None and report.damaged:
        print(f"damaged tlog: {report.text()}")
    for what, path in (("recording", args.csv), ("rate estimates", args.rates_csv), ("tlog", args.tlog)):
        if path:
            print(f"wrote {what}: {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
