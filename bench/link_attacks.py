"""Attacks on the uplink's datagrams for the soak (`bench.soak`): floods and spoofed sources.

- :class:`Flooder`: bursts of `burst_s` at `rate_Bps` (1 MB/s: 20 KB a 50 Hz tick), every `every_s`,
  the kinds in turn: 0xFE in 64 KB datagrams (every 0xFE is a MAVLink 1 start byte with a known id),
  0xFD in 4 KB (every 0xFD a MAVLink 2 start byte), random bytes in datagrams of 200 B to 4 KB; from an
  address that is not the ground station's. In the middle of each burst the ground sends a genuine
  signed command (a *probe*) that must be obeyed within 1 s. Each burst's record keeps the loop's
  overruns from its start to 1 s after its end.
- :class:`Spoofer`: every `every_s`, `n` datagrams from `n` new source addresses: unsigned commands
  from other system/component ids, commands signed with a wrong key, commands claiming the ground
  station's ids (signed with a wrong key), and replays of a genuine command frame the box has obeyed.
  None may be obeyed, none may make its address the one the box answers, and the box's table of
  sources must stay bounded. (A stranger who relays a genuine frame the box has *not* seen yet would
  get the answer to that one frame, as MAVLink signing does not cover addresses; the ground's retry
  takes the answer address back. The soak replays only frames already obeyed.)

Both act on `hil.faults.FaultyDatagramLink` before the loop tick they arrive for; everything random
comes from the generator given.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from fsw.telemetry.dialect import FSW_COMPID, FSW_SYSID, mavlink
from fsw.telemetry.signing import SigningClock, sign_frame

from ground.command import GroundLink

from hil.faults import GROUND_ADDR

FLOOD_KINDS = ("0xFE", "0xFD", "random")
#: the flood probe: a command the soak registers, its param7 the probe's number
FLOOD_PROBE = mavlink.MAV_CMD_USER_2
#: the attacks' own source address (floods)
FLOODER_ADDR = ("203.0.113.9", 40000)
#: the ground's link id for its flood probes (its own signing stream)
PROBE_LINK_ID = 2


@dataclass
class FloodRecord:
    kind: str
    start_s: float
    end_s: float
    bytes: int = 0
    datagrams: int = 0
    bytes_delivered: int = 0  # reached the box's receive buffer (not while the link is down)
    overruns_at_start: int = 0
    overruns: int | None = None  # from the start to 1 s after the end
    probe: int = 0
    probe_sent_s: float | None = None  # when it reached the box's receive buffer
    probe_obeyed_s: float | None = None

    def as_dict(self) -> dict:
        lat = None if self.probe_obeyed_s is None else round(self.probe_obeyed_s - self.probe_sent_s, 3)
        return {"kind": self.kind, "start_s": round(self.start_s, 3), "duration_s": round(self.end_s - self.start_s, 3),
                "bytes": self.bytes, "bytes_delivered": self.bytes_delivered, "datagrams": self.datagrams,
                "loop_overruns": self.overruns,
                "probe_latency_s": lat}


class Flooder:
    def __init__(self, link, key: bytes, clock: SigningClock, rng: np.random.Generator, *, duration_s: float,
                 first_s: float = 45.0, every_s: float = 90.0, burst_s: float = 5.0, rate_Bps: float = 1e6,
                 tail_s: float = 60.0) -> None:
        """`key`, `clock`: the ground station's, for the probes (on their own signing stream)."""
        self.link = link
        self._delivered = False
        self.ground = GroundLink(self._write, key, clock, link_id=PROBE_LINK_ID)
        self.rng = rng
        self.rate_Bps = rate_Bps
        self.schedule = [(t, t + burst_s) for t in np.arange(first_s, duration_s - tail_s - burst_s, every_s)]
        self.records: list[FloodRecord] = []
        self._current: FloodRecord | None = None
        self._owed = 0.0  # bytes due and not yet sent
        self._probe_due = False
        self.probe_resends = 0

    def tick(self, now_s: float, dt_s: float, overruns: int) -> None:
        """The flood's share of this tick (call before the loop tick at `now_s`)."""
        rec = self._current
        if rec is None and self.schedule and now_s >= self.schedule[0][0]:
            start, end = self.schedule.pop(0)
            rec = self._current = FloodRecord(FLOOD_KINDS[len(self.records) % len(FLOOD_KINDS)], start, end,
                                              overruns_at_start=overruns, probe=len(self.records) + 1)
            self.records.append(rec)
            self._owed = 0.0
            self._probe_due = True
        for r in self.records:  # overruns are counted up to 1 s after each burst
            if r.overruns is None and r is not rec and now_s >= r.end_s + 1.0:
                r.overruns = overruns - r.overruns_at_start
        if rec is None:
            return
        if now_s >= rec.end_s:
            self._current = None
            return
        self._owed += self.rate_Bps * dt_s
        while self._owed > 0:
            d = self._datagram(rec.kind)
            if self.link.inject(d, FLOODER_ADDR):
                rec.bytes_delivered += len(d)
            rec.bytes += len(d)
            rec.datagrams += 1
            self._owed -= len(d)
            if self._probe_due and now_s >= 0.5 * (rec.start_s + rec.end_s):
                self._send_probe(rec, now_s)

    def _datagram(self, kind: str) -> bytes:
        if kind == "0xFE":
            return b"\xfe" * 65000
        if kind == "0xFD":
            return b"\xfd" * 4000
        return self.rng.bytes(int(self.rng.integers(200, 4001)))

    def _write(self, frame: bytes) -> None:
        # over the network like the flood (not through the radio's loss, whose random draws stay the
        # faults' own); lost only while the link is down
        self._delivered = self.link.inject(frame, GROUND_ADDR)

    def _send_probe(self, rec: FloodRecord, now_s: float) -> None:
        self.ground.command_long(FLOOD_PROBE, [0, 0, 0, 0, 0, 0, float(rec.probe)], now_s)
        if self._delivered:  # not while the link is down: then again on the next tick
            self._probe_due = False
            rec.probe_sent_s = now_s
        else:
            self.probe_resends += 1

    def executed(self, probe: float, now_s: float) -> None:
        """The flight software ran probe number `probe`."""
        for rec in self.records:
            if rec.probe == int(probe) and rec.probe_obeyed_s is None:
                rec.probe_obeyed_s = now_s

    def finish(self, overruns: int) -> None:
        for r in self.records:
            if r.overruns is None:
                r.overruns = overruns - r.overruns_at_start

    def figures(self) -> dict:
        recs = self.records
        lat = [r.probe_obeyed_s - r.probe_sent_s for r in recs if r.probe_obeyed_s is not None]
        return {
            "floods": {k: sum(r.kind == k for r in recs) for k in FLOOD_KINDS},
            "flood_bytes": sum(r.bytes for r in recs),
            "flood_bytes_delivered": sum(r.bytes_delivered for r in recs),
            "flood_datagrams": sum(r.datagrams for r in recs),
            "flood_rate_Bps": self.rate_Bps,
            "loop_overruns_during_floods": sum(r.overruns or 0 for r in recs),
            "flood_probes": sum(r.probe_sent_s is not None for r in recs),
            "flood_probes_obeyed_within_1s": sum(x <= 1.0 for x in lat),
            "flood_probe_latency_max_s": round(max(lat), 3) if lat else None,
            "flood_probe_resends_link_down": self.probe_resends,
            "flood_records": [r.as_dict() for r in recs],
        }


@dataclass
class SpoofStats:
    bursts: int = 0
    datagrams: int = 0
    sources: int = 0
    peer_table_max: int = 0
    answer_address_hijacked: int = 0  # bursts after which the box answered another address
    kinds: dict = field(default_factory=dict)


class Spoofer:
    def __init__(self, link, rng: np.random.Generator, captured, ground_ids: tuple[int, int], command: int, *,
                 duration_s: float, first_s: float = 35.0, every_s: float = 60.0, n: int = 100,
                 epoch: int = 0) -> None:
        """`captured()`: a genuine command frame of the ground that the box has already obeyed (or
        None), replayed from strangers; `ground_ids`: the ground station's (sysid, compid); `command`:
        the command the forgeries carry (param7: a negative number, never a genuine one's)."""
        self.link = link
        self.command = command
        self.rng = rng
        self.captured = captured
        self.ground_ids = ground_ids
        self.times = list(np.arange(first_s, duration_s, every_s))
        self.n = n
        self.epoch = epoch
        self.stats = SpoofStats()
        self._pending_check = False
        self._burst = 0

    def tick(self, now_s: float, uplink) -> None:
        """Before the loop tick at `now_s`; `uplink`: the box's `fsw.telemetry.uplink.Uplink` (its peer
        table is checked after each burst)."""
        if self._pending_check:
            self._pending_check = False
            peers = uplink.peers
            self.stats.peer_table_max = max(self.stats.peer_table_max, len(peers))
            if peers.answer_address not in (None, GROUND_ADDR):
                self.stats.answer_address_hijacked += 1
        if not self.times or now_s < self.times[0]:
            return
        self.times.pop(0)
        self._burst += 1
        st = self.stats
        st.bursts += 1
        kinds = ("other_ids", "wrong_key", "ground_ids", "replay")
        for i in range(self.n):
            kind = kinds[i % len(kinds)]
            frame = self._frame(kind, i, now_s)
            if frame is None:
                continue
            addr = (f"198.51.100.{1 + int(self.rng.integers(254))}", int(self.rng.integers(1024, 65536)))
            self.link.inject(frame, addr)
            st.datagrams += 1
            st.sources += 1
            st.kinds[kind] = st.kinds.get(kind, 0) + 1
        self._pending_check = True

    def _frame(self, kind: str, i: int, now_s: float) -> bytes | None:
        """other_ids: unsigned, random system/component ids; wrong_key: signed with a random key;
        ground_ids: the ground's ids and stream, the next timestamp, a random key; replay: a genuine
        frame again."""
        nonce = -float(10_000 * self._burst + i)  # an attack's probe number: never a genuine one
        if kind == "replay":
            return self.captured()
        sysid, compid = self.ground_ids if kind == "ground_ids" else (
            int(self.rng.integers(1, 255)), int(self.rng.integers(1, 255)))
        p = mavlink.MAVLink(None, srcSystem=sysid, srcComponent=compid)
        raw = mavlink.MAVLink_command_long_message(FSW_SYSID, FSW_COMPID, self.command, 0,
                                                   0, 0, 0, 0, 0, 0, nonce).pack(p)
        if kind == "other_ids":
            return raw
        ts = SigningClock(epoch=self.epoch).now(now_s) + 1
        return sign_frame(self.rng.bytes(32), raw, 0, ts)
