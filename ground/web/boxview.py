"""One box as the live web view shows it: its frames verified with its own key, the values to plot kept in
rings of the last minutes (decimated), its state and its event log.

A :class:`BoxView` takes every intact frame of one system id (`ground.station.Fleet` routes them): the link
accounting (`ground.link_stats`) sees every frame, the signature check (`fsw.telemetry.signing.Verifier`,
the box's key, a 64-frame reorder window as in `ground.decode`) comes next, and only authentic frames reach
the plots, the state and the events. Refused frames are counted by reason (unsigned, bad_signature, replay,
future): a frame signed with another box's key is a bad_signature of this box.

Plots (`Series`): each is a ring of rows ``(t_s, v1, …)`` on the box's own time line (the flight software's
time since it started), in display units (µT, °/s, deg, kg·m², J), rounded to `DIGITS` decimals (NaN as
null) when published. Rows arrive at the box's rate (up to a kHz) and wait in ``pending``; at every
publication (`Series.flush`, 4 Hz from the server) those at least `MIN_DT_S` of box time after the last one
published go into the ring and to the browsers, and always the newest: ten rows a second of box time
whatever the box's rate or the publications' jitter (a publication late by a second loses no detail). The
ring keeps `window_s` of box time, at most window / `MIN_DT_S` + window × 4 Hz rows, so the memory per box
is bounded whatever the telemetry rate (a few MB for ten minutes); ``pending`` is thinned (every other
row) when it exceeds `MAX_PENDING`. Rows older than the ring's newest (resent samples, frames replayed
after an outage: they are in the archive) are not plotted, and counted; a new run of the flight software
(a new run_id in DEBRIS_MAG_SAMPLE) clears the plots.

Nothing here holds a key: the view's JSON (`snapshot`, `update`) carries values, counters and names only.
"""
from __future__ import annotations

import math
from collections import Counter, deque

from fsw.telemetry.dialect import mavlink
from fsw.telemetry.signing import Verdict, Verifier, unix_clock

from ..link_stats import LinkStats

#: rows published are at least this far apart in box time (the newest is always published too)
MIN_DT_S = 0.1
#: the expected publication rate (the ring's hard bound assumes it)
FLUSH_HZ = 4.0
#: rows waiting between two publications before they are thinned
MAX_PENDING = 4096
#: decimals of the values published (µT, °/s, deg, kg·m², J: far below any sensor's noise)
DIGITS = 4
#: events kept (STATUSTEXT, COMMAND_ACK, the view's own notes)
MAX_EVENTS = 200
UT_PER_GAUSS = 100.0
DEG = 180.0 / math.pi

RATE_METHOD_NAMES = {v: e.name.removeprefix("DEBRIS_RATE_METHOD_").lower()
                     for v, e in mavlink.enums["DEBRIS_RATE_METHOD"].items() if not e.name.endswith("_ENUM_END")}
#: the estimators the box sends (fsw.flight.METHODS, which loads them: not imported here; a test keeps them equal)
ONBOARD_METHODS = ("boer", "derivative", "kalman")


def _enum_name(enum: str, value: int) -> str:
    entry = mavlink.enums.get(enum, {}).get(value)
    if entry is None:
        return str(value)
    prefix = enum + "_"
    return entry.name.removeprefix(prefix).lower()


def _num(x: float, digits: int = 5) -> float | None:
    """A float for JSON: NaN and infinities as None (JSON has no NaN), rounded to `digits` decimals."""
    x = float(x)
    return round(x, digits) if math.isfinite(x) else None


def euler_zyx_deg(q: tuple[float, float, float, float]) -> tuple[float, float, float]:
    """Roll, pitch, yaw (deg; Z-Y-X) of a quaternion (w, x, y, z) body → reference."""
    w, x, y, z = q
    n = math.sqrt(w * w + x * x + y * y + z * z) or 1.0
    w, x, y, z = w / n, x / n, y / n, z / n
    roll = math.atan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = math.asin(max(-1.0, min(1.0, 2 * (w * y - z * x))))
    yaw = math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return roll * DEG, pitch * DEG, yaw * DEG


class Series:
    """A plot's ring of rows (t_s, values…), decimated at publication (see the module's docstring)."""

    def __init__(self, cols: tuple[str, ...], window_s: float) -> None:
        self.cols = cols
        self.window_s = window_s
        self.ring: deque[tuple] = deque(maxlen=max(16, int(window_s / MIN_DT_S + window_s * FLUSH_HZ)))
        self._last_t = -math.inf  # box time of the last row published
        self.pending: list[tuple] = []
        self.late = 0
        self.reset = False

    @property
    def newest_t(self) -> float:
        if self.pending:
            return self.pending[-1][0]
        return self.ring[-1][0] if self.ring else -math.inf

    def add(self, row: tuple) -> None:
        if row[0] < self.newest_t:
            self.late += 1
            return
        self.pending.append(row)
        if len(self.pending) > MAX_PENDING:
            last = self.pending[-1]
            self.pending = self.pending[-2::-2][::-1] + [last]

    def flush(self) -> list[tuple]:
        """The rows published now (at least MIN_DT_S apart after the last published, and the newest), kept in
        the ring, which is trimmed to the window."""
        p, self.pending = self.pending, []
        out = []
        last = self._last_t
        for r in p:
            if r[0] >= last + MIN_DT_S:
                out.append(r)
                last = r[0]
        if p and (not out or out[-1] is not p[-1]):
            out.append(p[-1])  # the newest, always
        if out:
            self._last_t = max(last, out[-1][0])
        out = [(r[0], *(_num(x, DIGITS) for x in r[1:])) for r in out]  # rounded for JSON when published
        self.ring.extend(out)
        if self.ring:
            oldest = self.ring[-1][0] - self.window_s
            while self.ring[0][0] < oldest:
                self.ring.popleft()
        return out

    def clear(self) -> None:
        self.ring.clear()
        self.pending.clear()
        self._last_t = -math.inf
        self.reset = True

    def as_dict(self) -> dict:
        return {"cols": list(self.cols), "rows": [list(r) for r in self.ring]}


#: the plots of a box: name → columns after t_s
SERIES = {
    "field_uT": ("bx", "by", "bz"),
    "rate_dps": ("wx", "wy", "wz", "sx", "sy", "sz"),
    "truth_rate_dps": ("wx", "wy", "wz"),
    "attitude_deg": ("roll", "pitch", "yaw"),
    "truth_attitude_deg": ("roll", "pitch", "yaw"),
    "inertia_kgm2": ("ixx", "iyy", "izz", "cxx", "cyy", "czz"),
    "kit_energy_J": ("pitch", "yaw"),
    "kit_steps": ("pitch", "yaw"),
    "sail_deg": ("yaw", "pitch"),
    "backlog_frames": ("buffered", "replayed", "dropped"),
}


class BoxView:
    """Everything the page shows of one box (system id `sysid`), its frames checked with `key` (None: not
    checked; the page says so)."""

    def __init__(self, sysid: int, key: bytes | None, *, method: int = mavlink.DEBRIS_RATE_METHOD_KALMAN,
                 window_s: float = 600.0) -> None:
        self.sysid = sysid
        self.verifier = None if key is None else Verifier(key, unix_clock(), window=64)
        self.method = method
        self.stats = LinkStats()
        self.rejected: Counter[str] = Counter()
        self.series = {name: Series(cols, window_s) for name, cols in SERIES.items()}
        self.events: deque[dict] = deque(maxlen=MAX_EVENTS)
        self._new_events: list[dict] = []
        self.state: dict = {"sysid": sysid, "verified": key is not None, "method": RATE_METHOD_NAMES[method]}
        self.frames = 0
        self.authentic = 0
        self.last_rx_s: float | None = None
        self.run_id: int | None = None
        self._att_sigma_deg: tuple | None = None
        self._changed = True

    # --- input -------------------------------------------------------------------------------------

    def handle(self, msg, now_s: float) -> None:
        """Account one intact frame of this system id received at `now_s` (Unix time)."""
        self.frames += 1
        self.last_rx_s = now_s
        self._changed = True
        self.stats.on_frame(msg, now_s)
        kind = msg.get_type()
        if self.stats.last_verdict == "duplicate" or kind.startswith("UNKNOWN"):
            return
        if self.verifier is not None:
            verdict = self.verifier.check(bytes(msg.get_msgbuf()), now_s)
            if verdict is not Verdict.OK:
                self.rejected[verdict.value] += 1
                return
        self.authentic += 1
        handler = self._HANDLERS.get(kind)
        if handler is not None:
            handler(self, msg, now_s)

    def _mag(self, msg, now_s):
        if msg.flags & mavlink.DEBRIS_SAMPLE_FLAGS_RESENT:
            return
        if self.run_id is not None and msg.run_id != self.run_id:
            for s in self.series.values():
                s.clear()
            self._event(now_s, "notice", f"new run of the flight software (run id {msg.run_id:#010x}): plots cleared")
        self.run_id = msg.run_id
        b = [x * UT_PER_GAUSS for x in msg.mag]
        if all(map(math.isfinite, b)):
            self.series["field_uT"].add((msg.time_usec * 1e-6, *b))
            self.state["field_norm_uT"] = _num(math.sqrt(sum(x * x for x in b)), 3)

    def _rate(self, msg, now_s):
        if msg.method != self.method or msg.flags & mavlink.DEBRIS_ESTIMATE_FLAGS_NO_ESTIMATE:
            return
        vals = (msg.wx, msg.wy, msg.wz, msg.sx, msg.sy, msg.sz)
        if all(map(math.isfinite, vals)):
            self.series["rate_dps"].add((msg.time_usec * 1e-6, *(v * DEG for v in vals)))
            self.state["rate_norm_dps"] = _num(math.sqrt(sum(v * v for v in vals[:3])) * DEG, 3)

    def _truth(self, msg, now_s):
        t = msg.time_usec * 1e-6
        w = (msg.wx, msg.wy, msg.wz)
        if all(map(math.isfinite, w)):
            self.series["truth_rate_dps"].add((t, *(v * DEG for v in w)))
            self.state["truth_rate_norm_dps"] = _num(math.sqrt(sum(v * v for v in w)) * DEG, 3)
        if all(map(math.isfinite, msg.q)) and any(msg.q):
            self.series["truth_attitude_deg"].add((t, *euler_zyx_deg(tuple(msg.q))))

    def _attitude(self, msg, now_s):
        q = (msg.q1, msg.q2, msg.q3, msg.q4)
        if all(map(math.isfinite, q)) and any(q):
            self.series["attitude_deg"].add((msg.time_boot_ms * 1e-3, *euler_zyx_deg(q)))

    def _attitude_sigma(self, msg, now_s):
        self.state["filter"] = _enum_name("DEBRIS_RATE_FILTER", msg.filter)
        self.state["attitude_sigma_deg"] = [_num(s * DEG, 3) for s in msg.attitude_sigma]

    def _inertia(self, msg, now_s):
        i, c = list(msg.inertia), list(msg.ci95)
        self.state["inertia"] = {"state": _enum_name("DEBRIS_IDENT_STATE", msg.state), "samples": int(msg.samples),
                                 "inertia_kgm2": [_num(x, 4) for x in i], "ci95_kgm2": [_num(x, 4) for x in c]}
        if msg.samples and all(map(math.isfinite, i[:3] + c[:3])):
            self.series["inertia_kgm2"].add((msg.time_usec * 1e-6, *i[:3], *c[:3]))

    def _kit(self, msg, now_s):
        t = msg.time_usec * 1e-6
        self.state["kit"] = {
            "capsules": [_enum_name("DEBRIS_CAPSULE_STATE", s) for s in msg.capsule_state],
            "magnets": [_enum_name("DEBRIS_MAGNET_STATE", s) for s in msg.magnet_state],
            "polarity": list(msg.polarity), "position_steps": list(msg.position_steps),
            "pulses": list(msg.steps_total), "energy_J": [_num(e, 3) for e in msg.energy],
            "capsule_openings": list(msg.capsule_openings), "magnet_turns": list(msg.magnet_turns),
            "faults": [f for f in msg.fault], "interlock_violations": int(msg.interlock_violations),
            "controller": _enum_name("DEBRIS_CONTROLLER_STATE", msg.controller_state)}
        self.series["kit_energy_J"].add((t, *msg.energy))
        self.series["kit_steps"].add((t, *(float(s) for s in msg.steps_total)))

    def _sail(self, msg, now_s):
        yaw, pitch = msg.yaw * DEG, msg.pitch * DEG
        self.state["sail"] = {"yaw_deg": _num(yaw, 2), "pitch_deg": _num(pitch, 2), "held": int(msg.held),
                              "source": _enum_name("DEBRIS_CONTROLLER_ATTITUDE", msg.source)}
        if math.isfinite(yaw) and math.isfinite(pitch):
            self.series["sail_deg"].add((msg.time_usec * 1e-6, yaw, pitch))

    def _link(self, msg, now_s):
        self.state["box_link"] = {
            "link_up": int(msg.link_up), "buffered": int(msg.tlm_buffered), "replayed": int(msg.tlm_replayed),
            "dropped": int(msg.tlm_dropped), "cmd_accepted": int(msg.cmd_accepted),
            "uplink_rejected": int(msg.rejected_unsigned + msg.rejected_bad_signature + msg.rejected_replay
                                   + msg.rejected_invalid)}
        self.series["backlog_frames"].add((msg.time_usec * 1e-6, float(msg.tlm_buffered), float(msg.tlm_replayed),
                                           float(msg.tlm_dropped)))

    def _loop(self, msg, now_s):
        self.state["sample_rate_hz"] = _num(msg.sample_rate, 3)
        self.state["box_time_s"] = _num(msg.time_usec * 1e-6, 3)

    def _statustext(self, msg, now_s):
        text = msg.text if isinstance(msg.text, str) else bytes(msg.text).decode("utf-8", "replace")
        self._event(now_s, _enum_name("MAV_SEVERITY", msg.severity), text.rstrip("\x00"))

    def _ack(self, msg, now_s):
        self._event(now_s, "ack", f"{_enum_name('MAV_CMD', msg.command).upper()}: "
                                  f"{_enum_name('MAV_RESULT', msg.result).upper()}")

    def _heartbeat(self, msg, now_s):
        self.state["heartbeat_rx_s"] = now_s

    _HANDLERS = {
        "DEBRIS_MAG_SAMPLE": _mag, "DEBRIS_RATE_ESTIMATE": _rate, "DEBRIS_SIM_STATE": _truth,
        "ATTITUDE_QUATERNION": _attitude, "DEBRIS_ATTITUDE_SIGMA": _attitude_sigma,
        "DEBRIS_INERTIA_ESTIMATE": _inertia, "DEBRIS_DEORBIT_STATUS": _kit, "DEBRIS_DEORBIT_ATTITUDE": _sail,
        "DEBRIS_LINK_STATUS": _link, "DEBRIS_LOOP_STATUS": _loop, "STATUSTEXT": _statustext,
        "COMMAND_ACK": _ack, "HEARTBEAT": _heartbeat}

    def _event(self, now_s: float, severity: str, text: str) -> None:
        e = {"rx_s": round(now_s, 3), "severity": severity, "text": text}
        self.events.append(e)
        self._new_events.append(e)
        self._changed = True

    # --- output ------------------------------------------------------------------------------------

    def status(self) -> dict:
        """The box's state and counters (small: sent whole with every update that changed it)."""
        sources = self.stats.sources.values()  # the counters only (summary() also scans sample times)
        received, lost = sum(s.received + s.unknown for s in sources), sum(s.lost for s in sources)
        late = sum(s.late for s in self.series.values())
        return {**self.state, "frames": self.frames, "authentic": self.authentic, "last_rx_s": self.last_rx_s,
                "link": {"received": received, "lost": lost, "duplicates": sum(s.duplicates for s in sources),
                         "loss_fraction": _num(lost / (received + lost), 5) if received + lost else 0.0,
                         "late_not_plotted": late},
                "rejected": dict(self.rejected)}

    def update(self) -> dict | None:
        """What changed since the last call: the rows published now per series (decimated), the state, the
        new events; None when nothing did."""
        rows = {}
        reset = []
        for name, s in self.series.items():
            if s.reset:
                reset.append(name)
                s.reset = False
            new = s.flush()
            if new:
                rows[name] = [list(r) for r in new]
        if not rows and not reset and not self._changed:
            return None
        events, self._new_events = self._new_events, []
        self._changed = False
        return {"rows": rows, "reset": reset, "state": self.status(), "events": events}

    def snapshot(self) -> dict:
        """Everything the page needs to draw this box from scratch (the rings, not what is still pending)."""
        return {"series": {name: s.as_dict() for name, s in self.series.items()}, "state": self.status(),
                "events": list(self.events)}
