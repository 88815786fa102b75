"""What the ground has received from each box: per source (sysid, compid) a :class:`Stream`, per run of
that source's flight software a :class:`Segment` with its samples, onboard estimates and (SITL) truth,
keyed by sample time.

Sources are kept apart: a frame from another (sysid, compid) — a second box, or a stray or forged
frame — starts a stream of its own and never touches another's samples.

Runs: numbered samples (DEBRIS_MAG_SAMPLE) carry the run id of the flight software that took them, so
a restart, and samples of an earlier run sent again later, go to the right segment. Streams of plain
HIGHRES_IMU magnetometer samples (another MAVLink system, an older recording) have no run id: there a
restart is seen from the time line — DEBRIS_LOOP_STATUS's loop time going back, or a sample older than
the run's first by more than `RESTART_BACKSTEP_S` — and samples older than the newest but within the run
(sent again after an outage) are merged by time.

What the box says it knows (time, TLE, calibration: `ground.box_knowledge`) goes to the run whose loop
time its message carries: the current run, or — a loop time further back than `RESTART_BACKSTEP_S` from
the current run's newest sample, or no run yet — the next run to start (its samples have not arrived
yet). A message without a time (DEBRIS_TLE) goes where the latest timed one went.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .box_knowledge import BoxKnowledge
from .gaps import GapRequester, SeqGaps

#: Sample time going back by more than this means the flight software restarted (plain streams).
RESTART_BACKSTEP_S = 1.0
#: the kit field of a DEBRIS_MAG_SAMPLE without the kit extension (a sender from before it): none
_NO_KIT = (0.0, 0.0, 0.0)


@dataclass
class Segment:
    """One run of one source's flight software. Times are µs of that run's clock."""

    run_id: int | None = None  # None: a plain (unnumbered) stream
    mag_gauss: dict[int, tuple[float, float, float]] = field(default_factory=dict)
    estimate: dict[int, tuple[tuple[float, ...], tuple[float, ...], int]] = field(default_factory=dict)
    truth: dict[int, tuple[tuple[float, ...], tuple[float, ...]]] = field(default_factory=dict)
    seq_of: dict[int, int] = field(default_factory=dict)  # sample time → its number
    arrived_s: dict[int, float] = field(default_factory=dict)  # sample time → when it arrived
    #: numbered samples: sample time → (kit field the box took out, gauss; flags without RESENT)
    kit: dict[int, tuple[tuple[float, float, float], int]] = field(default_factory=dict)
    kit_seen: bool = False  # a sample with a kit field or a kit flag arrived: the recording gets the columns
    latest_us: int = -1
    first_us: int = -1
    late: int = 0  # samples that arrived after a newer one (sent again after an outage or on request)
    arrivals: list[int] = field(default_factory=list)  # plain streams: sample times since the last loop status
    gaps: SeqGaps = field(default_factory=SeqGaps)
    requester: GapRequester = field(default_factory=GapRequester)
    #: what the box's DEBRIS_SAMPLE_STORE said of this run: oldest number held, store kept in a file
    stored_first_seq: int | None = None
    persistent: bool = False
    #: what the box said it knew during this run (time, TLE, calibration)
    knowledge: BoxKnowledge = field(default_factory=BoxKnowledge)

    @property
    def numbered(self) -> bool:
        return self.run_id is not None

    def add_sample(self, t_us: int, b_gauss: tuple[float, float, float], now_s: float,
                   seq: int | None = None) -> bool:
        """Keep a sample; False when it is a duplicate (same number). A plain sample at a time already
        held replaces it (the link's exact duplicates are caught before, by `ground.link_stats`; a
        restart's first sample may share a time with the previous run's until the restart is seen)."""
        if seq is not None and not self.gaps.add(seq):
            return False
        if t_us < self.latest_us:
            self.late += 1
        self.latest_us = max(self.latest_us, t_us)
        self.first_us = t_us if self.first_us < 0 else min(self.first_us, t_us)
        self.mag_gauss[t_us] = b_gauss
        self.arrived_s[t_us] = now_s
        if seq is not None:
            self.seq_of[t_us] = seq
        return True

    def times(self) -> list[int]:
        return sorted(self.mag_gauss)

    def report(self) -> dict:
        """``samples``, ``late``, ``missing`` and the ``gaps`` still open as (last time before, first time
        after, samples missing): by sample number in a numbered run (what the box sent and the ground
        does not have), else at the median sample period."""
        t = np.array(self.times(), dtype=np.int64)
        gaps: list[tuple[float, float, int]] = []
        if self.numbered and t.size:
            seq = np.array([self.seq_of[int(x)] for x in t], dtype=np.int64)
            k = np.diff(seq) - 1
            gaps = [(t[i] * 1e-6, t[i + 1] * 1e-6, int(k[i])) for i in np.flatnonzero(k > 0)]
            tail = self.gaps.end - 1 - int(seq[-1])
            if tail > 0:
                gaps.append((t[-1] * 1e-6, math.nan, tail))
        elif t.size >= 3:
            dt = np.diff(t)
            k = np.rint(dt / float(np.median(dt))).astype(np.int64) - 1
            gaps = [(t[i] * 1e-6, t[i + 1] * 1e-6, int(k[i])) for i in np.flatnonzero(k > 0)]
        return {"samples": int(t.size), "late": self.late, "missing": sum(g[2] for g in gaps), "gaps": gaps}


class Stream:
    """Everything from one source: its runs in the order they were first seen."""

    def __init__(self, source: tuple[int, int]) -> None:
        self.source = source
        self.segments: list[Segment] = []
        self._by_run: dict[int, Segment] = {}
        self.current: Segment | None = None  # the run whose live samples arrive now
        self.loop_time_us: int | None = None
        self.restarts: list[str] = []  # what was said at each restart
        #: what the box said before the samples of its run arrived: adopted by the next segment
        self.pending_knowledge: BoxKnowledge | None = None
        self._last_knowledge: BoxKnowledge | None = None

    def run(self, run_id: int) -> Segment:
        seg = self._by_run.get(run_id)
        if seg is None:
            seg = self._adopt(Segment(run_id=run_id))
            self._by_run[run_id] = seg
            self.segments.append(seg)
        return seg

    def _adopt(self, seg: Segment) -> Segment:
        """A new segment takes what the box said before its samples arrived."""
        if self.pending_knowledge is not None:
            seg.knowledge, self.pending_knowledge = self.pending_knowledge, None
        return seg

    def knowledge(self, t_us: int | None) -> BoxKnowledge:
        """Where a message of what the box knows, at loop time `t_us` (None: a message without a time), goes."""
        if t_us is None and self._last_knowledge is not None:
            return self._last_knowledge
        seg = self.current
        if seg is None or (t_us is not None and seg.latest_us >= 0
                           and t_us < seg.latest_us - RESTART_BACKSTEP_S * 1e6):
            if self.pending_knowledge is None:
                self.pending_knowledge = BoxKnowledge()
            k = self.pending_knowledge
        else:
            k = seg.knowledge
        self._last_knowledge = k
        return k

    def numbered_sample(self, msg, now_s: float, b_gauss) -> Segment | None:
        """A DEBRIS_MAG_SAMPLE; the segment it went to, or None for a duplicate."""
        seg = self.run(int(msg.run_id))
        resent = bool(msg.flags & 1)
        if not resent and seg is not self.current:
            if self.current is not None and self.current.numbered:
                self.restarts.append(f"run id changed from {self.current.run_id:#010x} to {seg.run_id:#010x}: "
                                     "flight software restarted, new recording segment")
            self.current = seg
        if not seg.add_sample(int(msg.time_usec), b_gauss, now_s, int(msg.seq)):
            return None
        kit = getattr(msg, "kit_mag", _NO_KIT)
        flags = int(msg.flags) & ~1  # RESENT is the link's, not the sample's
        if any(kit):  # a field taken out (or a NaN): the recording gets the columns
            kit = tuple(map(float, kit))
            if not all(map(math.isfinite, kit)):
                kit = (math.nan,) * 3
            seg.kit_seen = True
        else:
            kit = tuple(kit)
        if flags:
            seg.kit_seen = True
        seg.kit[int(msg.time_usec)] = (kit, flags)
        return seg

    def plain_sample(self, t_us: int, now_s: float, b_gauss) -> Segment | None:
        """A HIGHRES_IMU magnetometer sample (no number, no run id)."""
        seg = self.current
        if seg is None or seg.numbered:
            seg = self._new_plain()
        elif t_us < seg.latest_us - RESTART_BACKSTEP_S * 1e6 and t_us < seg.first_us:
            self.restarts.append(f"sample time went back from {seg.latest_us * 1e-6:.3f} s to {t_us * 1e-6:.3f} s: "
                                 "flight software restarted, new recording segment")
            seg = self._new_plain()
        if not seg.add_sample(t_us, b_gauss, now_s):
            return None
        seg.arrivals.append(t_us)
        return seg

    def _new_plain(self) -> Segment:
        seg = self._adopt(Segment())
        self.segments.append(seg)
        self.current = seg
        return seg

    def loop_status(self, t_us: int) -> None:
        """DEBRIS_LOOP_STATUS: in a plain stream, the loop time going back means a restart; the new
        segment takes the samples that arrived since the previous status and are not after this one."""
        seg = self.current
        if seg is not None and not seg.numbered and self.loop_time_us is not None \
                and t_us < self.loop_time_us - RESTART_BACKSTEP_S * 1e6:
            self.restarts.append(f"loop time went back from {self.loop_time_us * 1e-6:.3f} s to {t_us * 1e-6:.3f} s: "
                                 "flight software restarted, new recording segment")
            new = self._new_plain()
            for t in seg.arrivals:
                if t <= t_us and t in seg.mag_gauss:
                    for table in ("mag_gauss", "estimate", "truth", "arrived_s"):
                        old = getattr(seg, table)
                        if t in old:
                            getattr(new, table)[t] = old.pop(t)
            if new.mag_gauss:
                new.first_us, new.latest_us = min(new.mag_gauss), max(new.mag_gauss)
            seg = new
        self.loop_time_us = t_us
        if seg is not None:
            seg.arrivals.clear()

    def store_status(self, msg) -> Segment:
        """DEBRIS_SAMPLE_STORE: what exists of the current run (and, for a store kept in a file, of the
        earlier ones)."""
        seg = self.run(int(msg.run_id))
        seg.stored_first_seq, seg.persistent = int(msg.stored_first_seq), bool(msg.persistent)
        g = seg.gaps
        if g.lo is not None:
            first = int(msg.run_first_seq)
            if first < g.lo and g.lo - first <= 256 and first >= seg.stored_first_seq:
                g.start_at(first)  # the recording began near the run's start: from its first sample
            g.extend(int(msg.next_seq))
        if seg.persistent:  # earlier runs' numbers below this run's first exist in the same store
            for old in self.segments:
                if old is not seg and old.numbered and old.gaps.lo is not None and old.gaps.lo < msg.run_first_seq:
                    old.gaps.extend(int(msg.run_first_seq))
                    old.stored_first_seq, old.persistent = seg.stored_first_seq, True
        return seg

    @property
    def samples(self) -> int:
        return sum(len(s.mag_gauss) for s in self.segments)
