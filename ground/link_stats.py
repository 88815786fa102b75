"""Link quality from MAVLink sequence numbers and sample times, per source (sysid, compid).

Every MAVLink frame carries an 8-bit sequence number that its sender increments per frame
(MAVLink 2 serialization, "seq"). For each source the next frame is expected to carry
``expected = (last + 1) mod 256``; a frame with seq s means ``(s − expected) mod 256`` frames were
lost in between. pymavlink's own counter (`mavfile.mav_loss`) applies that formula to every frame,
so a frame received twice (a radio or a UDP relay repeating it) counts as 255 lost frames, one
frame arriving a place late (seq 0, 1, 3, 2, 4) as 256, and a frame of a message id the dialect
does not know as lost. Here:

- duplicate: the same frame (same bytes, so same seq and payload) as one of the last
  `REORDER_WINDOW` frames from that source: counted in ``duplicates``, not as loss;
- late: a frame whose seq was counted lost a moment ago (within `REORDER_WINDOW`): the loss is
  taken back and the frame counted in ``late``;
- out of sequence: any other frame whose seq lies within `REORDER_WINDOW` behind the last one (a
  second sender using the same ids, or the sender restarting its counter): counted in
  ``out_of_sequence``, neither loss nor a jump of the expected seq;
- frames of unknown message ids from a known source are counted (``unknown``) and keep the sequence.

Limits, by construction of an 8-bit counter: a gap of n ≥ 256 frames reads as n mod 256; a gap of
256 − `REORDER_WINDOW` … 255 frames reads as out-of-sequence; a restart of the sender's counter
reads as a gap. The flight software therefore says how many frames it has written on the link
(DEBRIS_LINK_STATUS ``frames_sent``, 1 Hz): between two of these, the sender's count minus the frames
accounted here (received + lost by sequence number) is the loss the sequence number could not show,
a multiple of 256, added to ``lost`` (``hidden_gaps`` counts such corrections). A sender whose count
goes back has restarted: the count starts over. To see long outages the stream's own clock is used where the
rate is known from the
stream itself: magnetometer samples (HIGHRES_IMU with the mag bits in fields_updated) carry
time_usec, and a step of k median sample periods means k − 1 missing samples (``samples_missing``).
That assumes a steady sample rate; a deliberate rate change shows as missing samples.

Bytes that pymavlink's robust parser could not frame (BAD_DATA "Bad prefix") are counted as
``garbage_bytes``; frames that fail their CRC as ``bad_crc`` (the frame is lost: its seq shows up as
a gap); other rejected frames (bad length, incompatibility flags, signature) as ``malformed``.
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

import numpy as np

from fsw.telemetry.dialect import mavlink

#: How far back (in frames) duplicates and late frames are recognised.
REORDER_WINDOW = 16
#: Sample times at or beyond 2**53 µs (285 years) are impossible and refused: no float holds them to the
#: µs (two of them would make the same time in a recording), no int64 at all from 2**63 on.
MAX_TIME_US = 2**53
#: HIGHRES_IMU fields_updated bits of a magnetometer sample.
MAG_FIELDS = (mavlink.HIGHRES_IMU_UPDATED_XMAG | mavlink.HIGHRES_IMU_UPDATED_YMAG
              | mavlink.HIGHRES_IMU_UPDATED_ZMAG)


def frames_lost(seq: int, expected: int) -> int:
    """Frames missing between the expected sequence number and the one received (MAVLink seq is
    8-bit and wraps at 256)."""
    return (seq - expected) % 256


def samples_missing(t_us: np.ndarray) -> int:
    """Samples missing from a stream sampled at a steady rate: with T the median step, a step Δt
    means round(Δt / T) − 1 samples absent. Times are sorted first; repeated times are ignored."""
    t = np.unique(np.asarray(t_us, dtype=np.int64))
    if t.size < 3:
        return 0
    dt = np.diff(t)
    period = float(np.median(dt))
    return int(np.sum(np.maximum(np.rint(dt / period) - 1, 0)))


@dataclass
class SourceStats:
    """Counters of one (sysid, compid) source."""

    received: int = 0
    unknown: int = 0
    lost: int = 0
    duplicates: int = 0
    late: int = 0
    out_of_sequence: int = 0
    first_s: float | None = None
    last_s: float | None = None
    expected: int | None = None  # position of the next frame, sequence number unwrapped
    recent: deque = field(default_factory=lambda: deque(maxlen=REORDER_WINDOW))
    missing: deque = field(default_factory=lambda: deque(maxlen=REORDER_WINDOW))
    sample_times_us: list[int] = field(default_factory=list)
    hidden_gaps: int = 0
    _mark: tuple[int, int] | None = None  # (sender's frames_sent, our position) at its last LINK_STATUS

    def sender_count(self, frames_sent: int) -> None:
        """The sender's own count of frames written, carried by the frame just accounted (which was
        'new', so its position is expected − 1): adds the losses of 256 frames or more."""
        position = self.expected - 1
        if self._mark is not None and frames_sent >= self._mark[0]:
            hidden = (frames_sent - self._mark[0]) - (position - self._mark[1])
            if hidden >= 256 and hidden % 256 == 0:
                self.lost += hidden
                self.expected += hidden
                position += hidden
                self.hidden_gaps += 1
        self._mark = (frames_sent, position)

    def account(self, seq: int, frame: bytes) -> str:
        """Classify one frame by its sequence number: 'new', 'duplicate', 'late' or
        'out_of_sequence'; updates the loss counters (the caller counts received/unknown)."""
        if self.expected is None:
            self.expected = seq + 1
            self.recent.append(frame)
            return "new"
        if frame in self.recent:
            self.duplicates += 1
            return "duplicate"
        self.recent.append(frame)
        behind = (self.expected - 1 - seq) % 256
        if behind < REORDER_WINDOW:
            position = self.expected - 1 - behind
            if position in self.missing:
                self.missing.remove(position)
                self.lost -= 1
                self.late += 1
                return "late"
            self.out_of_sequence += 1
            return "out_of_sequence"
        gap = frames_lost(seq, self.expected % 256)
        self.missing.extend(range(self.expected + gap - min(gap, REORDER_WINDOW), self.expected + gap))
        self.lost += gap
        self.expected += gap + 1
        return "new"

    def account_run(self, seqs: np.ndarray, frames: list[bytes]) -> bool:
        """`account` of a run of frames at once when every one of them is 'new' with nothing lost before
        it (each sequence number the one expected, none a copy of a recent frame): True, the counters as
        `account` one by one leaves them; else False, nothing changed (account them one by one)."""
        n = len(frames)
        if n == 0:
            return True
        first = int(seqs[0])
        if self.expected is not None and first != self.expected % 256:
            return False
        if n > 1 and not np.all(np.diff(seqs.astype(np.int64)) % 256 == 1):
            return False
        # a copy of a frame still in `recent`; within the run, frames less than 256 apart differ in seq
        if self.recent and any(f in self.recent for f in frames[:REORDER_WINDOW]):
            return False
        self.expected = (first if self.expected is None else self.expected) + n
        self.recent.extend(frames[-REORDER_WINDOW:])
        return True

    def as_dict(self) -> dict:
        expected = self.received + self.unknown + self.lost
        return {"received": self.received, "unknown": self.unknown, "lost": self.lost,
                "duplicates": self.duplicates, "late": self.late,
                "out_of_sequence": self.out_of_sequence, "hidden_gaps": self.hidden_gaps,
                "loss_fraction": self.lost / expected if expected else 0.0,
                "samples": len(self.sample_times_us),
                "samples_missing": samples_missing(np.array(self.sample_times_us)),
                "first_s": self.first_s, "last_s": self.last_s}


class LinkStats:
    """Loss, duplicate and garbage accounting for everything received on one link."""

    def __init__(self) -> None:
        self.sources: dict[tuple[int, int], SourceStats] = {}
        self.garbage_bytes = 0
        self.garbage_chunks = 0
        self.bad_crc = 0
        self.malformed = 0
        self.unknown = 0
        self.last_verdict = ""

    def on_frame(self, msg, now_s: float) -> None:
        """Account one message from pymavlink (BAD_DATA and UNKNOWN_* are passed to on_bad_data).
        `last_verdict` tells what the frame was: 'new', 'duplicate', 'late', 'out_of_sequence'."""
        if msg.get_msgId() < 0:
            self.on_bad_data(msg)
            return
        key = (msg.get_srcSystem(), msg.get_srcComponent())
        src = self.sources.get(key)
        if src is None:
            src = self.sources[key] = SourceStats(first_s=now_s)
        src.last_s = now_s
        self.last_verdict = src.account(msg.get_seq(), bytes(msg.get_msgbuf()))
        if self.last_verdict == "duplicate":
            return
        src.received += 1
        kind = msg.get_type()
        if kind == "HIGHRES_IMU" and msg.fields_updated & MAG_FIELDS == MAG_FIELDS and msg.time_usec < MAX_TIME_US:
            src.sample_times_us.append(int(msg.time_usec))
        elif kind == "DEBRIS_LINK_STATUS" and self.last_verdict == "new" and getattr(msg, "frames_sent", 0):
            src.sender_count(int(msg.frames_sent))

    def on_run(self, key: tuple[int, int], seqs: np.ndarray, frames: list[bytes], first_s: float, last_s: float,
               sample_times_us=()) -> bool:
        """`on_frame` of a run of source `key`'s frames of known messages, received from `first_s` to
        `last_s`, at once (`SourceStats.account_run`): True when they were all 'new' and are accounted,
        False (nothing changed) otherwise. `sample_times_us`: the magnetometer sample times of the run's
        HIGHRES_IMU frames (as `on_frame` takes them). DEBRIS_LINK_STATUS's count of frames sent is not read
        here: a caller that wants losses of 256 frames or more found gives those frames to `on_frame`."""
        src = self.sources.get(key)
        fresh = src is None
        if fresh:
            src = SourceStats(first_s=first_s)
        if not src.account_run(seqs, frames):
            return False
        if fresh:
            self.sources[key] = src
        src.last_s = last_s
        src.received += len(frames)
        src.sample_times_us.extend(sample_times_us)
        self.last_verdict = "new"
        return True

    def on_bad_data(self, msg) -> None:
        """Account pymavlink's BAD_DATA (unframeable bytes, bad CRC, malformed frame) or UNKNOWN_*
        (a well-formed frame of a message id the dialect lacks; its CRC cannot be checked)."""
        kind = msg.get_type()
        data = bytes(getattr(msg, "data", b"") or b"")
        self.last_verdict = kind
        if kind.startswith("UNKNOWN"):
            self.unknown += 1
            header = _header(data)
            if header is not None and header[1:] in self.sources:
                src = self.sources[header[1:]]
                self.last_verdict = src.account(header[0], data)
                if self.last_verdict != "duplicate":
                    src.unknown += 1
            return
        reason = str(getattr(msg, "reason", ""))
        if reason.startswith("Bad prefix"):
            self.garbage_bytes += len(data)
            self.garbage_chunks += 1
        elif "CRC" in reason:
            self.bad_crc += 1
        else:
            self.malformed += 1

    def lost(self) -> int:
        """Frames lost so far, all sources (cheap; for live display)."""
        return sum(s.lost for s in self.sources.values())

    def received(self) -> int:
        """Intact frames of known messages received so far, all sources."""
        return sum(s.received for s in self.sources.values())

    def summary(self) -> dict:
        """Per source and total counters, plus the link-level rejects:
        ``{"sources": {(sysid, compid): {...}}, "totals": {...}, "garbage_bytes", "garbage_chunks",
        "bad_crc", "malformed", "unknown"}``."""
        per = {k: s.as_dict() for k, s in sorted(self.sources.items())}
        totals = {name: sum(d[name] for d in per.values())
                  for name in ("received", "unknown", "lost", "duplicates", "late", "out_of_sequence",
                               "samples", "samples_missing")}
        expected = totals["received"] + totals["unknown"] + totals["lost"]
        totals["loss_fraction"] = totals["lost"] / expected if expected else 0.0
        return {"sources": per, "totals": totals, "garbage_bytes": self.garbage_bytes,
                "garbage_chunks": self.garbage_chunks, "bad_crc": self.bad_crc,
                "malformed": self.malformed, "unknown": self.unknown}


def _header(frame: bytes) -> tuple[int, int, int] | None:
    """(seq, sysid, compid) from a raw MAVLink 1 or 2 frame, None if too short."""
    if len(frame) >= 10 and frame[0] == mavlink.PROTOCOL_MARKER_V2:
        return frame[4], frame[5], frame[6]
    if len(frame) >= 6 and frame[0] == mavlink.PROTOCOL_MARKER_V1:
        return frame[2], frame[3], frame[4]
    return None
