"""Decode the box's MAVLink telemetry: live status, loss accounting, tlog and recording-format CSVs.

    python -m ground.decode URL [--baud B] [--tlog FILE] [--csv FILE] [--rates-csv FILE] [--key FILE]
                                [--method boer|derivative|kalman] [--duration S] [--count N] [--quiet]
                                [--no-resend] [--archive FILE | --no-archive]

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
all of them in `Decoder.inertia_estimates`), and the loss so far. At the end a summary: frames by type, loss
per source, rejected data.

Outputs
- ``--tlog``: every intact frame as received (pymavlink tlog: 8-byte big-endian µs time stamp, then
  the raw frame), flushed after every read so that a crash keeps what came before it.
- ``--csv``: the magnetometer samples (DEBRIS_MAG_SAMPLE, or HIGHRES_IMU with the mag bits in
  fields_updated from other systems; gauss → µT) in recording format v1, time = the flight software's
  sample time; with DEBRIS_SIM_STATE present (SITL) the reference rate w*_dps and the applied moment
  m*_Nm of the same sample (matched on time_usec; NaN for a sample whose truth frame was lost).
  The recording's metadata carries what the box knew (`ground.box_knowledge`): the UTC of t = 0
  (``utc0``), the TLE it flies (``tle_line1``, ``tle_line2``), its field model, and its last host
  calibration (``magcal_*``: not applied to the samples, which are the sensor's own); what arrives after
  the file was started is appended as ``# key: value`` lines (`ground.recorder`).
- ``--rates-csv``: the onboard estimates of the selected method, one row per magnetometer sample, NaN
  where none arrived or the estimate is flagged DEBRIS_ESTIMATE_FLAGS_NO_ESTIMATE.
The CSVs are written while the frames arrive, one file per run of each source's flight software
(`ground.recorder`: names, order, what a crash leaves), and completed when decoding stops: duration or
count reached, end of a tlog, SIGINT or SIGTERM. Frames with non-finite values (or a negative σ), or a
sample time of 2**53 µs or more (`MAX_TIME_US`), are counted and left out, never written. Every source
(sysid, compid) is kept apart (`ground.streams`).

Nothing lost to the link: the box numbers its samples and keeps them (`fsw.telemetry.sample_store`).
On a live link the decoder asks again for the numbers that did not arrive (DEBRIS_SAMPLE_REQUEST,
`ground.gaps`; ``--no-resend`` to stop it); they come back flagged RESENT and go into their place.
Samples the box kept during an outage of a serial link arrive later too. The summary says what is still
missing.

``--archive FILE`` (default for a live link: `ground.archive.default_path`; ``--no-archive``): every
intact frame also goes into the archive (`ground.archive`, SQLite), a crash losing at most the last second.

``--key FILE``: verify every frame's MAVLink 2 signature with the mission key (`fsw.telemetry.signing`,
with a 64-frame reorder window); unsigned, wrongly signed or replayed frames are counted by reason
and not used (the link accounting and the tlog still see every intact frame).
"""
from __future__ import annotations

import itertools
import math
import signal
import struct
import sys
import time
from collections import Counter
from pathlib import Path
from typing import Callable

import numpy as np

from fsw.telemetry import dialect
from fsw.telemetry.dialect import mavlink

from fsw.telemetry.signing import Verdict, Verifier, load_key, unix_clock


from fsw.argtypes import ArgumentParser, check_paths_or_exit, finite_float, int_range, link_url
from fsw.files import check_paths

from .archive.store import ArchiveFeed, default_path
from .command import GroundLink
from .link_stats import MAG_FIELDS, MAX_TIME_US, LinkStats
from .live_link import LiveLink
from .recorder import Recorder
from .recording import RateEstimates, Recording, write_rate_estimates, write_recording
from .streams import Segment, Stream
from .tlog import read_tlog

#: DEBRIS_RATE_METHOD values by their short lower-case name (boer, derivative, ...).
METHODS: dict[str, int] = {
    entry.name.removeprefix("DEBRIS_RATE_METHOD_").lower(): value
    for value, entry in mavlink.enums["DEBRIS_RATE_METHOD"].items()
    if not entry.name.endswith("_ENUM_END")}
METHOD_NAMES = {value: name for name, value in METHODS.items()}
#: DEBRIS_RATE_FILTER names (the flown filter, DEBRIS_ATTITUDE_SIGMA.filter)
FILTER_NAMES = {value: entry.name.removeprefix("DEBRIS_RATE_FILTER_").lower()
                for value, entry in mavlink.enums["DEBRIS_RATE_FILTER"].items() if not entry.name.endswith("_ENUM_END")}

T_PER_GAUSS = 1e-4
#: Messages whose time_usec is the magnetometer sample time.
SAMPLE_MESSAGES = frozenset({"DEBRIS_MAG_SAMPLE", "HIGHRES_IMU", "DEBRIS_RATE_ESTIMATE", "DEBRIS_SIM_STATE"})
#: Messages of what the box knows: time, orbit, calibration (`ground.box_knowledge`).
KNOWLEDGE_MESSAGES = frozenset({"DEBRIS_TIME_ORBIT", "SYSTEM_TIME", "DEBRIS_TLE", "DEBRIS_MAGCAL"})
#: how often missing samples are asked for and settled rows written
SERVICE_PERIOD_S = 0.5
#: with no way to ask the box (a .tlog, no uplink), how long a missing sample is waited for
NO_REQUESTS_WAIT_S = 10.0
#: the signing link id of the decoder's requests (ground.command signs on link 0)
REQUEST_LINK_ID = 2


def f32(*values: float) -> tuple[float, ...]:
    """MAVLink float fields as the shortest decimals that round to the same float32: 0.1 sent as
    float32 reads 0.1, not 0.10000000149011612 (both are within the float32 rounding the sender
    applied; this one is what the sender most likely meant)."""
    return tuple(float(str(np.float32(v))) for v in values)


def _as_given(*values: float) -> tuple[float, ...]:
    return values


#: the float fields of the sample messages the decoder reads through `f32` (`Decoder(rounded=True)`:
#: they come rounded, `ground.archive.bulk`)
F32_FIELDS = {"DEBRIS_MAG_SAMPLE": ("mag",), "HIGHRES_IMU": ("xmag", "ymag", "zmag"),
              "DEBRIS_RATE_ESTIMATE": ("wx", "wy", "wz", "sx", "sy", "sz"),
              "DEBRIS_SIM_STATE": ("wx", "wy", "wz", "mx", "my", "mz")}


class Decoder:
    """Stateful decoding of a telemetry stream; feed it every message pymavlink returns."""

    def __init__(self, method: int = mavlink.DEBRIS_RATE_METHOD_BOER,
                 source: tuple[int, int] | None = None,
                 on_line: Callable[[str], None] | None = None, origin: str = "",
                 line_period_s: float = 1.0, key: bytes | None = None,
                 recorder: Recorder | None = None, requests: GroundLink | None = None,
                 rounded: bool = False) -> None:
        """`method`: the DEBRIS_RATE_METHOD exported and shown; `source`: (sysid, compid) to record
        from, None = every source (the first to send samples is the one shown); `on_line`: receives
        the live line about every `line_period_s` of `now_s`; `origin`: the link, for the CSVs'
        ``# source:``; `key`: verify signatures with this mission key (`now_s` is then Unix time, or 0
        when unknown); `recorder`: writes the recordings as they settle (`ground.recorder`);
        `requests`: where to send DEBRIS_SAMPLE_REQUEST for missing numbered samples (None: they are
        waited for a while, then given up); `rounded`: the sample messages' `F32_FIELDS` are float32's
        shortest decimals already (decoded in bulk by `ground.archive.bulk`)."""
        if method not in METHOD_NAMES:
            raise ValueError(f"unknown DEBRIS_RATE_METHOD {method}")
        self.method = method
        self.only = source
        self._f32 = _as_given if rounded else f32
        self.source = source
        self.on_line = on_line
        self.origin = origin
        self.line_period_s = line_period_s
        self.stats = LinkStats()
        self.frames_by_type: Counter[str] = Counter()
        #: Intact frames whose values cannot be a sample (NaN/inf field, negative σ), by type.
        self.invalid: Counter[str] = Counter()
        self.streams: dict[tuple[int, int], Stream] = {}
        self.recorder = recorder
        self.requests = requests
        self._next_line_s: float | None = None
        self._next_service_s: float | None = None
        self._last_est: tuple[float, ...] | None = None
        self._last_truth: tuple[float, ...] | None = None
        self.interrupted = False
        # now_s is Unix time: the signing clock's epoch maps it to 10 µs since 2015
        self.verifier = None if key is None else Verifier(
            key, unix_clock(), window=64)
        #: intact frames refused by the signature check, by reason
        self.unauthenticated: Counter[str] = Counter()
        #: decoded DEBRIS_INERTIA_ESTIMATE messages, in arrival order (see `_inertia`)
        self.inertia_estimates: list[dict] = []
        #: DEBRIS_SAMPLE_REQUEST frames sent
        self.requests_sent = 0
        #: the latest DEBRIS_KIT_FIELD per channel (the kit's field at the sensor as modelled on board)
        self.kit_field: dict[int, object] = {}
        #: the latest DEBRIS_MAG_STATUS (the magnetometer driver's health and its offset's counters)
        self.mag_status = None
        #: the flown filter's latest attitude and 1-σ (see `_attitude`)
        self.attitude: dict = {}
        #: the de-orbit controller's latest inputs (DEBRIS_DEORBIT_ATTITUDE, see `_deorbit_attitude`)
        self.deorbit_attitude: dict = {}
        #: the mission's latest DEBRIS_MISSION_STATUS and every phase change seen (see `_mission_status`)
        self.mission: dict = {}
        self.mission_phases: list[tuple[float, str, str]] = []

    # --- input -------------------------------------------------------------------------------

    def handle(self, msg, now_s: float) -> None:
        """Account and decode one message (any type, including BAD_DATA / UNKNOWN_*)."""
        kind = msg.get_type()
        self.frames_by_type[kind] += 1
        self.stats.on_frame(msg, now_s)
        if msg.get_msgId() >= 0 and self.stats.last_verdict != "duplicate" and not kind.startswith("UNKNOWN"):
            self.accounted(kind, msg, now_s)
        self.tick(now_s)

    def accounted(self, kind: str, msg, now_s: float) -> None:
        """Decode an intact message of a known type that the link accounting (`stats`) has taken as not a
        duplicate, its verdict in ``stats.last_verdict`` (`handle` without the counting and the tick: for
        frames accounted in bulk, `ground.archive.export`)."""
        if self.verifier is not None:
            verdict = self.verifier.check(bytes(msg.get_msgbuf()), now_s)
            if verdict is not Verdict.OK:
                self.unauthenticated[verdict.value] += 1
                return
        if kind in SAMPLE_MESSAGES:
            self._sample_message(kind, msg, now_s)
        elif kind == "DEBRIS_LOOP_STATUS" and self.stats.last_verdict == "new":
            stream = self._stream(msg, create=False)
            if stream is not None:
                stream.loop_status(int(msg.time_usec))
                self._restarts(stream)
        elif kind == "DEBRIS_SAMPLE_STORE":
            stream = self._stream(msg)
            if stream is not None:
                stream.store_status(msg)
        elif kind == "DEBRIS_INERTIA_ESTIMATE":
            self._inertia(msg)
        elif kind in KNOWLEDGE_MESSAGES:
            self._knowledge(kind, msg)
        elif kind == "DEBRIS_KIT_FIELD" and msg.channel in (0, 1):
            self.kit_field[int(msg.channel)] = msg
        elif kind == "DEBRIS_MAG_STATUS":
            self.mag_status = msg
        elif kind in ("ATTITUDE_QUATERNION", "DEBRIS_ATTITUDE_SIGMA"):
            self._attitude(kind, msg)
        elif kind == "DEBRIS_DEORBIT_ATTITUDE":
            self._deorbit_attitude(msg)
        elif kind == "DEBRIS_MISSION_STATUS":
            self._mission_status(msg)

    def _mission_status(self, msg) -> None:
        """The mission's phase (DEBRIS_MISSION_STATUS): the latest kept in ``mission`` (SI, phase and reason
        by name), each change of phase appended to ``mission_phases`` as (time, phase, reason)."""
        phase = mavlink.enums["DEBRIS_MISSION_PHASE"].get(msg.phase)
        reason = mavlink.enums["DEBRIS_MISSION_REASON"].get(msg.reason)
        if phase is None or reason is None or not math.isfinite(msg.time_in_phase):
            self.invalid["DEBRIS_MISSION_STATUS"] += 1
            return
        name = phase.name.removeprefix("DEBRIS_MISSION_PHASE_")
        why = reason.name.removeprefix("DEBRIS_MISSION_REASON_").lower()
        t = msg.time_usec * 1e-6
        if not self.mission_phases or self.mission_phases[-1][1] != name:
            self.mission_phases.append((t - msg.time_in_phase, name, why))
        self.mission = {"t_s": t, "phase": name, "reason": why, "time_in_phase_s": msg.time_in_phase,
                        "rate_radps": msg.rate, "rate_sigma_radps": msg.rate_sigma, "ci95_pct": msg.ci95_pct,
                        "inertia_kgm2": f32(*msg.inertia), "energy_J": f32(*msg.energy)}

    def _deorbit_attitude(self, msg) -> None:
        """The de-orbit controller's inputs (yaw, pitch, roll w.r.t. the orbital frame, the rate relative to
        it, their σ, where they come from and whether it is trusted), kept in ``deorbit_attitude`` (SI;
        NaN: none yet)."""
        source = mavlink.enums["DEBRIS_CONTROLLER_ATTITUDE"].get(msg.source)
        if source is None:
            self.invalid["DEBRIS_DEORBIT_ATTITUDE"] += 1
            return
        self.deorbit_attitude = {
            "t_s": msg.time_usec * 1e-6, "yaw_rad": msg.yaw, "pitch_rad": msg.pitch, "roll_rad": msg.roll,
            "rate_radps": f32(*msg.rate), "pointing_sigma_rad": f32(*msg.pointing_sigma),
            "rate_sigma_radps": msg.rate_sigma, "hypotheses": msg.hypotheses, "held": msg.held,
            "source": source.name.removeprefix("DEBRIS_CONTROLLER_ATTITUDE_").lower(),
            # SITL's truth beside them (NaN from the target, or a sender without the extension)
            "truth_ypr_rad": f32(*getattr(msg, "truth_ypr", (math.nan,) * 3))}

    def _attitude(self, kind: str, msg) -> None:
        """The flown filter's attitude (ATTITUDE_QUATERNION: q body → ECI) and its 1-σ with the rate's and
        which filter publishes (DEBRIS_ATTITUDE_SIGMA): the latest kept in ``attitude`` (SI)."""
        a = self.attitude
        if kind == "ATTITUDE_QUATERNION":
            q = f32(msg.q1, msg.q2, msg.q3, msg.q4)
            if not all(map(math.isfinite, q)):
                self.invalid[kind] += 1
                return
            a["t_s"], a["q_body_to_eci"] = msg.time_boot_ms * 1e-3, q
        else:
            a["sigma_att_rad"], a["sigma_rate_radps"] = f32(*msg.attitude_sigma), f32(*msg.rate_sigma)
            a["filter"] = FILTER_NAMES.get(msg.filter, str(msg.filter))
            a["handovers"] = msg.handovers
        a[kind] = a.get(kind, 0) + 1

    def _stream(self, msg, create: bool = True) -> Stream | None:
        src = (msg.get_srcSystem(), msg.get_srcComponent())
        if self.only is not None and src != self.only:
            return None
        stream = self.streams.get(src)
        if stream is None and create:
            stream = self.streams[src] = Stream(src)
        return stream

    def _restarts(self, stream: Stream) -> None:
        while stream.restarts:
            who = f"{stream.source[0]}/{stream.source[1]}: " if len(self.streams) > 1 else ""
            self._say(who + stream.restarts.pop(0))

    def _knowledge(self, kind: str, msg) -> None:
        """What the box says it knows (`ground.box_knowledge`), kept with the run it belongs to; values that
        cannot be used are counted in ``invalid`` and left out."""
        if kind == "DEBRIS_TLE":
            if msg.target_system != 0:
                return  # a station staging a TLE on a box (an uplink seen on a shared link), not the box's own
            t_us = None
        elif kind == "SYSTEM_TIME":
            t_us = int(msg.time_boot_ms) * 1000
        else:
            t_us = int(msg.time_usec)
        stream = self._stream(msg)
        if stream is None:
            return
        k = stream.knowledge(t_us)
        ok = (k.time_orbit(msg) if kind == "DEBRIS_TIME_ORBIT" else k.tle_lines(msg) if kind == "DEBRIS_TLE"
              else k.calibration(msg) if kind == "DEBRIS_MAGCAL" else k.system_time(msg))
        if not ok:
            self.invalid[kind] += 1

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

    def _sample_message(self, kind: str, msg, now_s: float) -> None:
        if kind == "HIGHRES_IMU" and msg.fields_updated & MAG_FIELDS != MAG_FIELDS:
            return
        t_us = int(msg.time_usec)
        if t_us >= MAX_TIME_US:
            self.invalid[kind] += 1
            return
        stream = self._stream(msg)
        if stream is None:
            return
        if kind in ("DEBRIS_MAG_SAMPLE", "HIGHRES_IMU"):
            b = self._f32(*msg.mag) if kind == "DEBRIS_MAG_SAMPLE" else self._f32(msg.xmag, msg.ymag, msg.zmag)
            if not all(map(math.isfinite, b)):
                self.invalid[kind] += 1
                return
            if kind == "DEBRIS_MAG_SAMPLE":
                seg = stream.numbered_sample(msg, now_s, b)
                if seg is not None:
                    seg.requester.arrived(int(msg.seq))
            else:
                seg = stream.plain_sample(t_us, now_s, b)
            self._restarts(stream)
            if seg is not None:
                if self.source is None:
                    self.source = stream.source
                if self.recorder is not None:
                    self.recorder.added(seg, t_us)
            return
        seg = stream.current
        if seg is None:
            return
        if kind == "DEBRIS_RATE_ESTIMATE":
            if msg.method == self.method:
                w, sigma = self._f32(msg.wx, msg.wy, msg.wz), self._f32(msg.sx, msg.sy, msg.sz)
                if not all(map(math.isfinite, w + sigma)) or min(sigma) < 0:
                    self.invalid[kind] += 1
                    return
                seg.estimate[t_us] = (w, sigma, msg.flags)
                if not msg.flags & mavlink.DEBRIS_ESTIMATE_FLAGS_NO_ESTIMATE:
                    self._last_est = w
        else:
            w, m = self._f32(msg.wx, msg.wy, msg.wz), self._f32(msg.mx, msg.my, msg.mz)
            if not all(map(math.isfinite, w + m)):
                self.invalid[kind] += 1
                return
            seg.truth[t_us] = (w, m)
            self._last_truth = w

    @property
    def tick_due_s(self) -> float:
        """The earliest time at which `tick` does something (−∞: at the next call): a caller that feeds many
        frames at once (`ground.archive.export`) calls it only from then on, with the same outcome."""
        if self._next_service_s is None or (self.on_line is not None and self._next_line_s is None):
            return -math.inf
        return self._next_service_s if self.on_line is None else min(self._next_service_s, self._next_line_s)

    def tick(self, now_s: float) -> None:
        """Emit the live line when one is due, ask for missing samples and write what has settled (call
        also when nothing arrives)."""
        if self.on_line is None:
            pass  # nobody to tell: the line is not made
        elif self._next_line_s is None:
            self._next_line_s = now_s + self.line_period_s
        elif now_s >= self._next_line_s:
            self._next_line_s = max(self._next_line_s + self.line_period_s, now_s)
            self._say(self.status_line())
        if self._next_service_s is None or now_s >= self._next_service_s:
            self._next_service_s = now_s + SERVICE_PERIOD_S
            self.service(now_s)

    def service(self, now_s: float) -> None:
        """Ask the box again for the numbered samples that are missing (or give them up), then write the
        rows that have settled."""
        for stream in self.streams.values():
            for seg in stream.segments:
                if not seg.numbered or seg.gaps.lo is None:
                    continue
                if seg is not stream.current and not seg.persistent:
                    seg.gaps.give_up_all()  # an earlier run whose store went with it
                    continue
                if self.requests is None:
                    seg.requester.max_attempts = 0  # nobody to ask: wait a while, then give up
                    seg.requester.hold_s = NO_REQUESTS_WAIT_S
                for first, count in seg.requester.due(seg.gaps, now_s, seg.stored_first_seq):
                    self.requests.send(mavlink.MAVLink_debris_sample_request_message(
                        stream.source[0], stream.source[1], first, count), now_s)
                    self.requests_sent += 1
        if self.recorder is not None:
            self.recorder.service(self, now_s)

    def finish(self) -> None:
        """End of decoding: write everything that is left (`recorder`)."""
        if self.recorder is not None:
            self.recorder.finish(self)

    def _say(self, line: str) -> None:
        if self.on_line is not None:
            self.on_line(line)

    # --- views -------------------------------------------------------------------------------

    @property
    def segments(self) -> list[Segment]:
        """The runs of the source shown (the first to send samples)."""
        stream = self.streams.get(self.source) if self.source is not None else None
        return stream.segments if stream is not None else [Segment()]

    def _recorded(self) -> Segment:
        """The last segment of the source shown that holds magnetometer samples (or its last one)."""
        return next((s for s in reversed(self.segments) if s.mag_gauss), self.segments[-1])

    def status_line(self) -> str:
        seg = self._recorded()
        parts = []
        if seg.mag_gauss:
            t_us = seg.latest_us
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
        if seg.numbered and seg.gaps.lo is not None:
            parts.append(f"samples missing {len(seg.gaps.missing())}")
        return "  ".join(parts)

    def _where(self, seg: Segment) -> tuple[tuple[int, int] | None, int, int]:
        for stream in self.streams.values():
            if seg in stream.segments:
                return stream.source, stream.segments.index(seg), len(stream.segments)
        return self.source, 0, 1

    def metadata(self, seg: Segment | None = None) -> dict[str, str]:
        """The recording's ``# key: value`` lines for a segment (default: the one shown)."""
        seg = self._recorded() if seg is None else seg
        src, index, runs = self._where(seg)
        where = f" from {self.origin}" if self.origin else ""
        who = f", system {src[0]} component {src[1]}" if src else ""
        meta = {"source": f"MAVLink telemetry{where}{who}, decoded by ground.decode",
                "time": "flight software sample time since that run of it started"}
        if seg.numbered:
            meta["run_id"] = f"{seg.run_id:#010x}"
        if runs > 1:
            meta["segment"] = f"run {index + 1} of {runs} runs of the flight software seen in the stream"
        meta.update(seg.knowledge.metadata())
        return meta

    def rate_metadata(self, seg: Segment | None = None) -> dict[str, str]:
        meta = self.metadata(seg)
        meta["method"] = f"{METHOD_NAMES[self.method]} (onboard, DEBRIS_RATE_ESTIMATE)"
        return meta

    def recording(self, seg: Segment | None = None, times: list[int] | None = None) -> Recording:
        """The magnetometer samples of a segment (default: the last one with samples of the source
        shown) as a Recording (SI), with simulation truth where it arrived; `times`: only these."""
        seg = self._recorded() if seg is None else seg
        times = seg.times() if times is None else times
        t_s = np.array(times, dtype=float) / 1e6
        b_T = np.array([seg.mag_gauss[t] for t in times], dtype=float).reshape(-1, 3) * T_PER_GAUSS
        meta = self.metadata(seg)
        kit = {}
        if seg.kit_seen:  # the kit's field the box took out, and the flags (KIT_MOVING)
            zero = ((0.0, 0.0, 0.0), 0)
            k = [seg.kit.get(t, zero) for t in times]
            kit = {"kit_T": np.array([x[0] for x in k], dtype=float).reshape(-1, 3) * T_PER_GAUSS,
                   "flags": np.array([x[1] for x in k], dtype=np.int64)}
        if not seg.truth:
            return Recording(t_s=t_s, b_T=b_T, metadata=meta, **kit)
        nan3 = ((math.nan,) * 3, (math.nan,) * 3)
        truth = [seg.truth.get(t, nan3) for t in times]
        w = np.array([x[0] for x in truth], dtype=float).reshape(-1, 3)
        m = np.array([x[1] for x in truth], dtype=float).reshape(-1, 3)
        meta["reference"] = "DEBRIS_SIM_STATE: simulation truth, for scoring only"
        return Recording(t_s=t_s, b_T=b_T, m_Nm=m, w_ref_radps=w, metadata=meta, **kit)

    def rate_estimates(self, seg: Segment | None = None, times: list[int] | None = None) -> RateEstimates:
        """Onboard estimates of the selected method, one row per magnetometer sample (NaN where
        none arrived or the estimate is flagged NO_ESTIMATE)."""
        seg = self._recorded() if seg is None else seg
        times = seg.times() if times is None else times
        w = np.full((len(times), 3), np.nan)
        s = np.full((len(times), 3), np.nan)
        for i, t in enumerate(times):
            est = seg.estimate.get(t)
            if est is not None and not est[2] & mavlink.DEBRIS_ESTIMATE_FLAGS_NO_ESTIMATE:
                w[i], s[i] = est[0], est[1]
        return RateEstimates(t_s=np.array(times, dtype=float) / 1e6, w_radps=w, sigma_radps=s,
                             metadata=self.rate_metadata(seg))

    def summary_text(self) -> str:
        """Frames by type, loss per source, rejected data: the end-of-run report."""
        out = ["frames by type: " + (", ".join(f"{k} {n}" for k, n in sorted(self.frames_by_type.items()))
                                     or "none")]
        summary = self.stats.summary()
        for (sysid, compid), s in summary["sources"].items():
            out.append(f"source {sysid}/{compid}: received {s['received']}, lost {s['lost']} "
                       f"({100 * s['loss_fraction']:.2f} %), duplicates {s['duplicates']}, late {s['late']}, "
                       f"out of sequence {s['out_of_sequence']}, unknown ids {s['unknown']}")
        out.append(f"rejected: {summary['garbage_bytes']} garbage bytes in {summary['garbage_chunks']} runs, "
                   f"{summary['bad_crc']} bad CRC, {summary['malformed']} malformed, "
                   f"{summary['unknown']} unknown message ids")
        for stream in self.streams.values():
            for index, seg in enumerate(stream.segments):
                rep = seg.report()
                if not rep["samples"]:
                    continue
                who = f"{stream.source[0]}/{stream.source[1]}"
                run = f" run {index + 1} of {len(stream.segments)}" if len(stream.segments) > 1 else ""
                late = (f", {rep['late']} of them sent again after an outage or on request and merged in order"
                        if rep["late"] else "")
                if rep["missing"]:
                    shown = ", ".join(f"{a:.3f}–{b:.3f} s ({k})" for a, b, k in rep["gaps"][:5])
                    more = f" and {len(rep['gaps']) - 5} more" if len(rep["gaps"]) > 5 else ""
                    lost = f"{rep['missing']} missing in {len(rep['gaps'])} gaps: {shown}{more}"
                else:
                    lost = "none missing"
                out.append(f"magnetometer samples recorded from {who}{run}: {rep['samples']}{late}; {lost}")
                said = seg.knowledge.summary()
                if said:
                    out.append(f"what the box knew ({who}{run}), in the recording's metadata: {said}")
        if self.requests_sent:
            out.append(f"requests for missing samples sent: {self.requests_sent}")
        if self.mag_status is not None:
            m = self.mag_status
            state = mavlink.enums["DEBRIS_MAG_STATE"].get(m.state)
            o_uT = [v * T_PER_GAUSS * 1e6 for v in (m.offset_x, m.offset_y, m.offset_z)]
            out.append(f"magnetometer driver: {state.name.removeprefix('DEBRIS_MAG_STATE_') if state else m.state}, "
                       f"{m.samples} samples, {m.bus_errors} bus errors, {m.timeouts} timeouts, {m.resets} resets; "
                       f"bridge offset ({', '.join(f'{v:+.2f}' for v in o_uT)}) uT; offset measurements kept out "
                       f"of its mean: {m.offset_outliers} outliers, {m.offset_disturbed} while the kit moved; "
                       f"{m.offset_jumps} jumps")
        for ch, m in sorted(self.kit_field.items()):
            out.append(f"kit field on board, {('pitch', 'yaw')[ch]}: scale {m.scale:.3f} ± {m.scale_sigma:.3f}, "
                       f"{m.steps} calibration steps ({m.ill_conditioned} ill-conditioned, {m.outliers} outliers), "
                       f"{m.flagged} samples flagged while it moved")
        a = self.attitude
        if "filter" in a:
            sa, sr = np.degrees(a["sigma_att_rad"]), np.degrees(a["sigma_rate_radps"])
            att = (f"attitude q(body→ECI) ({', '.join(f'{x:+.4f}' for x in a['q_body_to_eci'])}) at "
                   f"{a['t_s']:.3f} s, 1-σ ({sa[0]:.2f} {sa[1]:.2f} {sa[2]:.2f}) deg"
                   if "q_body_to_eci" in a and np.all(np.isfinite(sa)) else "no attitude")
            out.append(f"flown rate filter: {a['filter']} ({a['handovers']} hand-overs from the fixed-field filter), "
                       f"{a.get('ATTITUDE_QUATERNION', 0)} ATTITUDE_QUATERNION; last {att}; "
                       f"rate 1-σ ({sr[0]:.2f} {sr[1]:.2f} {sr[2]:.2f}) deg/s")
        if self.mission:
            m = self.mission
            seen = ", ".join(f"{name} at {t:.0f} s ({why})" for t, name, why in self.mission_phases)
            names = ("tumbling", "rates known", "identifying", "detumbling", "stabilising", "stabilised", "safe")
            energy = ", ".join(f"{n} {e:.0f}" for n, e in zip(names, m["energy_J"]) if e)
            out.append(f"mission: {m['phase']} for {m['time_in_phase_s']:.0f} s ({m['reason']}); phases seen: {seen}; "
                       f"rate {math.degrees(m['rate_radps']):.3f} deg/s, tensor diagonal "
                       f"({', '.join(f'{x:.2f}' for x in m['inertia_kgm2'])}) kg.m^2, ci95 {m['ci95_pct']:.2f} % of "
                       f"the largest; kit energy by phase [J]: {energy or 'none'}")
        if self.verifier is not None:
            refused = ", ".join(f"{k} {n}" for k, n in sorted(self.unauthenticated.items())) or "none"
            out.append(f"signatures: {self.verifier.counts[Verdict.OK]} frames verified; refused: {refused}")
        if self.invalid:
            out.append("not recorded, non-finite values or impossible times: "
                       + ", ".join(f"{k} {n}" for k, n in sorted(self.invalid.items())))
        return "\n".join(out)

    def sample_report(self) -> dict:
        """The shown run's magnetometer samples: ``samples``, ``late`` (arrived after a newer one),
        ``missing`` and the ``gaps`` still open (`ground.streams.Segment.report`)."""
        return self._recorded().report()

    def write(self, csv: str | Path | None = None, rates_csv: str | Path | None = None) -> None:
        """Write the shown run's recording and/or rate-estimate CSVs at once (atomically)."""
        if csv is not None:
            write_recording(csv, self.recording())
        if rates_csv is not None:
            write_rate_estimates(rates_csv, self.rate_estimates())


def tlog_record(msg, now_s: float) -> bytes:
    """One tlog record: big-endian µs time stamp (`now_s` rounded to the µs, as the archive keeps it; low
    2 bits: link id 0, as pymavlink writes it), then the frame's bytes as received. Rounded, not truncated:
    a time stamp read from a tlog (t × 1e-6 s) is written back as it was."""
    return struct.pack(">Q", round(now_s * 1e6) & ~3) + bytes(msg.get_msgbuf())


def run(url: str, *, duration_s: float | None = None, count: int | None = None,
        tlog: str | Path | None = None, csv: str | Path | None = None,
        rates_csv: str | Path | None = None, method: int = mavlink.DEBRIS_RATE_METHOD_BOER,
        quiet: bool = False, on_line: Callable[[str], None] = print, baud: int = 115200,
        clock: Callable[[], float] = time.time, key: bytes | None = None, resend: bool = True,
        uplink: str | None = None, should_stop: Callable[[], bool] = lambda: False,
        archive: str | Path | None = None) -> Decoder:
    """Decode `url` until `duration_s` (of the link's time line: `clock` for live links, the
    recorded time stamps for a tlog) or `count` intact frames, the end of a tlog, `should_stop()`
    (SIGINT/SIGTERM in `main`) or Ctrl-C. Waits on the link in 0.1 s slices, never spins.

    The recordings are written while the frames arrive (`ground.recorder`): one file per run of each
    source, rows in order as they settle, completed at the end. The tlog gets every intact frame as
    received, flushed after every read. On a live link (`resend`) the decoder asks the box again for
    numbered samples that did not arrive (DEBRIS_SAMPLE_REQUEST, signed with `key` when given), back on
    the link or on `uplink` (a connection string) when the box takes commands elsewhere.

    Output paths are checked first (`fsw.files.check_paths`: PathError). A tlog is read by
    `ground.tlog.read_tlog`: every intact record is decoded, damage is skipped and counted in
    ``decoder.tlog_report``; a file with nothing intact raises TlogError and nothing is written. Live
    links are framed by `fsw.telemetry.framing.Deframer` (byte-wise resync, so no intact frame is lost
    to line noise); a serial port that goes away is reopened every second until it is back.

    `archive`: every intact frame also goes into this archive (`ground.archive`, created if missing),
    committed within half a second; ``decoder.archived`` counts them."""
    check_paths(inputs={"input": url if Path(url).exists() else None},
                outputs={"--tlog": tlog, "--csv": csv, "--rates-csv": rates_csv, "--archive": archive})
    recorder = Recorder(csv, rates_csv, protect=[p for p in (url, tlog) if p is not None and Path(p).exists()])
    decoder = Decoder(method=method, on_line=None if quiet else on_line, origin=url, key=key, recorder=recorder)
    is_log = Path(url).is_file()
    live = records = up = None
    if is_log:
        reader = read_tlog(url)
        records = iter(reader)
        records = itertools.chain([next(records)], records)  # TlogError now if nothing is intact
        decoder.tlog_report = reader.report
    else:
        live = LiveLink(url, baud, decoder._say)
        if resend:
            if uplink is not None:
                up = dialect.open_link(uplink, source_system=dialect.GCS_SYSID,
                                       source_component=dialect.GCS_COMPID, baud=baud)
            decoder.requests = GroundLink(live.write if up is None else up.write, key, unix_clock(),
                                          link_id=REQUEST_LINK_ID)
    log_out = None
    store = None
    frames = 0
    start_s = None
    done = False
    try:
        log_out = open(tlog, "wb") if tlog is not None else None
        store = ArchiveFeed(archive, decoder._say) if archive is not None else None
        while not done and not should_stop():
            if is_log:
                record = next(records, None)
                if record is None:
                    break
                batch, now_s = record.messages, record.t_us * 1e-6
            else:
                batch, now_s = live.read(), clock()
            if start_s is None:
                start_s = now_s
            if not batch:
                decoder.tick(now_s)
            for msg in batch:
                decoder.handle(msg, now_s)
                if msg.get_type() != "BAD_DATA":
                    frames += 1
                    if log_out is not None:
                        log_out.write(tlog_record(msg, now_s))
                    if store is not None:
                        store.add(msg, now_s)
                if count is not None and frames >= count:
                    done = True
                    break
            if log_out is not None and batch and not is_log:
                log_out.flush()
            if store is not None:
                store.tick()
            if duration_s is not None and now_s - start_s >= duration_s:
                break
        if not is_log and not done:
            for msg in live.flush():
                decoder.handle(msg, now_s)
                if msg.get_type() != "BAD_DATA" and log_out is not None:
                    log_out.write(tlog_record(msg, now_s))
                if msg.get_type() != "BAD_DATA" and store is not None:
                    store.add(msg, now_s)
        if should_stop():
            decoder.interrupted = True
    except KeyboardInterrupt:
        decoder.interrupted = True
    finally:
        if live is not None:
            live.close()
        if up is not None:
            up.close()
        if log_out is not None:
            log_out.close()
        if store is not None:
            store.close()
    decoder.frames = frames
    decoder.archived = store.frames if store is not None else 0
    decoder.archive_lost, decoder.archive_error = (store.lost, store.error) if store is not None else (0, None)
    decoder.finish()
    return decoder


def _missing_path(url: str) -> str | None:
    """Why `url` cannot be opened, when it names a file or serial device that is not there (pymavlink
    would say "could not open port" for both)."""
    if url.partition(":")[0] in _SCHEMES or Path(url).exists():
        return None
    if url.startswith("/dev/"):
        return f"{url}: no such serial device"
    return f"{url}: no such file (nor a connection string: udpin:HOST:PORT, tcp:HOST:PORT, a serial device)"


_SCHEMES = frozenset({"udp", "udpin", "udpout", "udpbcast", "tcp", "tcpin", "mcast", "wsserver", "ws"})


def sent_methods() -> dict[str, int]:
    """The DEBRIS_RATE_METHOD values the flight software sends, by name (`fsw.flight.METHODS`)."""
    from fsw.flight import METHODS as SENT  # the estimators run on board; imported here: it loads them

    return {name: value for name, value in METHODS.items() if value in SENT.values()}


def main(argv: list[str] | None = None) -> int:
    sent = sent_methods()
    ap = ArgumentParser(prog="python -m ground.decode", description=__doc__.splitlines()[0])
    ap.add_argument("url", type=link_url, help="pymavlink connection string: udpin:0.0.0.0:14550, tcp:HOST:PORT, "
                                               "a serial device, or a .tlog file")
    ap.add_argument("--baud", type=int_range(1), default=115200, help="serial baud rate (default 115200)")
    ap.add_argument("--tlog", help="record every intact frame to this tlog")
    ap.add_argument("--csv", help="write the magnetometer samples as a recording-format CSV (one file per run "
                                  "of each source: see ground.recorder)")
    ap.add_argument("--rates-csv", help="write the onboard rate estimates of --method as CSV")
    ap.add_argument("--method", choices=sorted(sent, key=sent.get), default="boer",
                    help="onboard estimator to show and export (default boer); the ground's own methods: "
                         "python -m ground.estimate")
    ap.add_argument("--duration", type=finite_float(0, min_exclusive=True), metavar="S",
                    help="stop after this many seconds (> 0)")
    ap.add_argument("--count", type=int_range(1), metavar="N", help="stop after this many intact frames (>= 1)")
    ap.add_argument("--quiet", action="store_true", help="no live lines, only the summary")
    ap.add_argument("--key", metavar="FILE", help="mission key file: verify the frames' signatures, use only "
                                                  "authentic ones; sign the requests for missing samples")
    ap.add_argument("--no-resend", action="store_true",
                    help="do not ask the box again for numbered samples that did not arrive")
    archiving = ap.add_mutually_exclusive_group()
    archiving.add_argument("--archive", metavar="FILE",
                    help=f"archive every intact frame in this SQLite file (ground.archive); default for a live "
                         f"link: {default_path()}, for a .tlog: none")
    archiving.add_argument("--no-archive", action="store_true", help="do not archive the frames")
    ap.add_argument("--uplink", metavar="URL", type=link_url,
                    help="send the requests for missing samples on this link (the box's --uplink) instead of "
                         "back on URL")
    args = ap.parse_args(argv)
    archive = None if args.no_archive else args.archive
    if archive is None and not args.no_archive and not Path(args.url).is_file():
        archive = default_path()
        try:
            archive.parent.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            ap.error(f"--archive {archive}: cannot make its directory ({e.strerror or e}); --no-archive to run "
                     "without one")
    check_paths_or_exit(ap, inputs={"input": args.url if Path(args.url).exists() else None, "--key": args.key},
                        outputs={"--tlog": args.tlog, "--csv": args.csv, "--rates-csv": args.rates_csv,
                                 "--archive": archive})
    missing = _missing_path(args.url)
    if missing:
        print(f"ground.decode: {missing}", file=sys.stderr)
        return 1
    stop = []

    def on_signal(signum, frame):
        stop.append(signum)

    old = {sig: signal.signal(sig, on_signal) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        key = load_key(args.key) if args.key else None
        decoder = run(args.url, duration_s=args.duration, count=args.count, tlog=args.tlog, csv=args.csv,
                      rates_csv=args.rates_csv, method=sent[args.method], quiet=args.quiet,
                      baud=args.baud, key=key, resend=not args.no_resend, uplink=args.uplink,
                      should_stop=lambda: bool(stop), archive=archive)
    except (OSError, ValueError) as e:
        print(f"ground.decode: {e}", file=sys.stderr)
        return 1
    finally:
        for sig, handler in old.items():
            signal.signal(sig, handler)
    if decoder.interrupted:
        print("interrupted" if not stop or stop[0] == signal.SIGINT else "terminated")
    print(decoder.summary_text())
    report = getattr(decoder, "tlog_report", None)
    if report is not None and report.damaged:
        print(f"damaged tlog: {report.text()}")
    if not decoder.frames:
        print(f"ground.decode: nothing received from {args.url}", file=sys.stderr)
        return 1
    for what, path in decoder.recorder.written:
        print(f"wrote {what}: {path}")
    if (args.csv or args.rates_csv) and not decoder.recorder.written:
        print("no magnetometer samples received: no recording written")
    if args.tlog:
        print(f"wrote tlog: {args.tlog}")
    if archive is not None:
        print(f"archived {decoder.archived} frames: {archive}")
        if decoder.archive_error is not None:
            print(f"archive failed ({decoder.archive_error}): {decoder.archive_lost} frames not archived")
    return 0


if __name__ == "__main__":
    from fsw.startup import exit_with

    exit_with(main)
