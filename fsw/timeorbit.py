"""Time and orbit on board: the UTC set from the ground, the TLE uploaded, the field along the orbit.

An onboard application (`fsw.app.App`, task "timeorbit", 1 Hz) around the pure pieces
(`estimation.utc_clock`, `estimation.tle`, `estimation.onboard_field`):

- **Time**: SYSTEM_TIME from the ground (MAVLink's way of giving a system the time:
  ``time_unix_usec``), taken at the loop time it arrives, sets the UTC estimate; successive sets give
  the drift of the box's clock. With a mission key the uplink only hands over frames signed with it
  (the others are dropped and counted as unsigned in DEBRIS_LINK_STATUS); without a key every time set
  is refused and counted here. A time before 2020 (or 0, MAVLink's "unknown") is refused and counted.
- **Orbit**: a TLE does not fit in a COMMAND_LONG, so it comes in two steps: the DEBRIS_TLE message
  stages the two lines, then MAV_CMD_DEBRIS_TLE_LOAD with the CRC of the staged lines checks them and
  puts them in force. The command gives the COMMAND_ACK, the command protocol's retries and its
  replay safety; the CRC binds the command to exactly the lines the ground meant. Refusals
  (`DEBRIS_TLE_REFUSAL`, counted): not staged / CRC differs, bad format, bad checksum, epoch after the
  onboard UTC, epoch older than the parameter TLE_MAX_AGE_D → DENIED; no onboard UTC yet →
  TEMPORARILY_REJECTED (set the time, then load again). The COMMAND_ACK's result_param2 carries the
  reason. A TLE in force is written atomically to
  `tle_file` (a plain two-line file) and read back at start.
- **Field**: :meth:`TimeOrbit.field_now` gives the field along the orbit (IGRF-14 at the flight
  degree, SGP4, knots every 60 s, interpolated) when a TLE and the UTC are on board and the TLE is
  neither stale nor from the future, else None and why: what needs it (the identification
  experiment) refuses then, it never flies on a missing or stale orbit. The task computes the knots
  around the loop time ahead of need, one batch at a time.
- **Time sync** (https://mavlink.io/en/services/timesync.html): a TIMESYNC request (tc1 = 0) is
  answered with tc1 = the onboard UTC in ns (the box's loop time before a time set: the magnitude tells
  which), ts1 mirrored: the ground sees the time it set, and the round trip.
- **Telemetry**: SYSTEM_TIME (the UTC estimate, 1 Hz) and DEBRIS_TIME_ORBIT (offset age, drift, TLE
  epoch, age and state, counters, field degree; every `status_period_s`, and at once after a time
  set, a TLE loaded or a refusal, so that the ground sees the effect of what it sent); the TLE in
  force itself as DEBRIS_TLE (target 0) every `tle_period_s` and at once when it is put in force or
  read from the TLE file, so that the ground's recordings carry the orbit the box flies (a receiver
  that joins late has it within a minute; 165 bytes a minute).

Time is the loop's ``now_s`` (the monotonic clock on target, the simulator's in SITL); nothing reads
the wall clock.
"""
from __future__ import annotations

import math
import zlib
from pathlib import Path

from .commands import int_param
from .estimation import tle as tles
from .estimation.igrf import FLIGHT_DEGREE, load_coefficients
from .estimation.onboard_field import KNOT_STEP_S, OnboardOrbitField, affine_utc
from .estimation.utc_clock import UtcEstimator
from .files import write_atomic
from .telemetry.dialect import mavlink

#: the earliest UTC believed from the ground (2020-01-01T00:00:00Z)
MIN_UTC_S = 1577836800.0
DEFAULT_TLE_MAX_AGE_D = 14.0

REFUSAL = {"not staged": mavlink.DEBRIS_TLE_REFUSAL_NOT_STAGED, tles.FORMAT: mavlink.DEBRIS_TLE_REFUSAL_FORMAT,
           tles.CHECKSUM: mavlink.DEBRIS_TLE_REFUSAL_CHECKSUM,
           tles.FUTURE_EPOCH: mavlink.DEBRIS_TLE_REFUSAL_FUTURE_EPOCH, tles.TOO_OLD: mavlink.DEBRIS_TLE_REFUSAL_TOO_OLD,
           "no time": mavlink.DEBRIS_TLE_REFUSAL_NO_TIME, "unsigned": mavlink.DEBRIS_TLE_REFUSAL_UNSIGNED}
STATE_NAMES = {mavlink.DEBRIS_TLE_STATE_NONE: "no TLE on board", mavlink.DEBRIS_TLE_STATE_OK: "ok",
               mavlink.DEBRIS_TLE_STATE_NO_TIME: "no UTC on board (set the time)",
               mavlink.DEBRIS_TLE_STATE_STALE: "the TLE is older than TLE_MAX_AGE_D",
               mavlink.DEBRIS_TLE_STATE_FUTURE: "the TLE's epoch is after the onboard UTC"}


def tle_crc(line1: str, line2: str) -> int:
    """The CRC MAV_CMD_DEBRIS_TLE_LOAD carries: CRC-32 of the 138 characters, low 24 bits (a float32 holds it)."""
    return zlib.crc32((line1 + line2).encode("ascii", "replace")) & 0xFFFFFF


def _text(raw) -> str:
    if isinstance(raw, (bytes, bytearray)):
        return bytes(raw).split(b"\x00", 1)[0].decode("ascii", errors="replace")
    return str(raw).split("\x00", 1)[0]


class TimeOrbit:
    """The box's knowledge of time, orbit and field; an onboard application."""

    name = "timeorbit"
    rate_hz = 1.0
    budget = 0.5  # a batch of knots (SGP4 + IGRF): ~2–5 ms once a minute
    status_period_s = 5.0
    tle_period_s = 60.0

    def __init__(self, *, tle_file: str | Path | None = None, max_tle_age_d: float = DEFAULT_TLE_MAX_AGE_D,
                 degree: int = FLIGHT_DEGREE, knot_step_s: float = KNOT_STEP_S,
                 clock: UtcEstimator | None = None) -> None:
        self.clock = clock if clock is not None else UtcEstimator()
        self.max_tle_age_s = float(max_tle_age_d) * 86400.0
        self.degree = int(degree)
        self.knot_step_s = float(knot_step_s)
        self.tle_file = Path(tle_file) if tle_file else None
        self.tle: tles.Tle | None = None
        self.tle_persisted = False
        self.time_refused = 0
        self.tle_loaded = 0
        self.tle_refused = 0
        self.last_refusal = mavlink.DEBRIS_TLE_REFUSAL_NONE
        self.last_error = ""
        self.persist_errors = 0
        self.field_errors = 0
        self.last_field_error = ""
        self.notes: list[str] = []
        self._staged: tuple[str, str] | None = None
        self._field: OnboardOrbitField | None = None
        self._next_status_s = -math.inf
        self._next_tle_s = -math.inf
        self._router = None
        load_coefficients()  # at start-up, not in the tick that first needs the field
        if self.tle_file is not None:
            self._read_tle_file()

    # --- start-up -----------------------------------------------------------------------------------
    def _read_tle_file(self) -> None:
        path = self.tle_file
        try:
            text = path.read_text(encoding="ascii")
        except FileNotFoundError:
            self.notes.append(f"TLE file {path}: none yet (upload one with python -m ground.command ... tle)")
            return
        except (OSError, UnicodeDecodeError) as e:
            self.notes.append(f"TLE file {path}: cannot be read ({e}); no TLE on board")
            return
        lines = [ln for ln in text.splitlines() if ln.strip()]
        try:
            if len(lines) != 2:
                raise tles.TleError(tles.FORMAT, f"{len(lines)} non-empty lines, a TLE has 2")
            self.tle = tles.parse_tle(*lines)
        except tles.TleError as e:
            self.notes.append(f"TLE file {path}: not a valid TLE ({e}); no TLE on board")
            return
        self.tle_persisted = True
        self.notes.append(f"TLE from {path}: satellite {self.tle.satnum}, epoch "
                          f"{_iso(self.tle.epoch_utc_s)} (used once the time is set)")

    # --- the application's contract ------------------------------------------------------------------
    def register(self, router) -> None:
        self._router = router
        router.register(mavlink.MAV_CMD_DEBRIS_TLE_LOAD, self.cmd_tle_load, changes_state=True)

    def register_params(self, params) -> None:
        params.register("TLE_MAX_AGE_D", lambda: self.max_tle_age_s / 86400.0, self._set_max_age, 0.1, 365.0)

    def message_handlers(self) -> dict:
        return {"SYSTEM_TIME": self.on_system_time, "DEBRIS_TLE": self.on_tle, "TIMESYNC": self.on_timesync}

    def tick(self, now_s: float, sample) -> None:
        """Compute the knots around the loop time ahead of need (one batch), when the field is available."""
        f, _ = self.field_now(now_s)
        if f is None:
            return
        k = math.floor(now_s / self.knot_step_s)
        try:
            f.b_eci_T(k * self.knot_step_s + self.knot_step_s * 1.5)  # knots k .. k+3
        except ValueError as e:  # SGP4 cannot propagate (decayed, bad elements): reported, not used
            self.field_errors += 1
            self.last_error = self.last_field_error = f"field along the orbit: {e}"

    def telemetry(self, now_s: float, tlm) -> None:
        tlm.system_time(now_s, self.clock.utc_s(now_s))
        if now_s >= self._next_status_s:
            tlm.time_orbit(now_s, **self.message_fields(now_s))
            self._next_status_s = now_s + self.status_period_s
        if self.tle is not None and now_s >= self._next_tle_s:
            tlm.tle(self.tle.line1, self.tle.line2)
            self._next_tle_s = now_s + self.tle_period_s

    # --- time ----------------------------------------------------------------------------------------
    def on_system_time(self, msg, now_s: float, authenticated: bool) -> None:
        """SYSTEM_TIME from the ground: a time set (authenticated only; MIN_UTC_S or later)."""
        utc_s = float(getattr(msg, "time_unix_usec", 0)) * 1e-6
        if not authenticated:
            self.time_refused += 1
            self._next_status_s = -math.inf
            self.last_error = "time set refused: not signed with the mission key"
            return
        if not (math.isfinite(utc_s) and utc_s >= MIN_UTC_S):
            self.time_refused += 1
            self._next_status_s = -math.inf
            self.last_error = f"time set refused: {utc_s:.0f} s is before 2020"
            return
        self.set_time(now_s, utc_s)

    def on_timesync(self, msg, now_s: float, authenticated: bool):
        """TIMESYNC request (tc1 = 0) → the answer: tc1 = the onboard UTC [ns] (loop time before a set)."""
        if int(getattr(msg, "tc1", 1)) != 0:
            return None  # an answer to someone else's request
        t_ns = int(round((self.clock.utc_s(now_s) if self.clock.known else now_s) * 1e9))
        return mavlink.MAVLink_timesync_message(t_ns, int(msg.ts1))

    def set_time(self, now_s: float, utc_s: float) -> None:
        self.clock.set(now_s, utc_s)
        self._field = None  # rebuilt on the new time
        self._next_status_s = -math.inf

    def utc_s(self, now_s: float) -> float:
        return self.clock.utc_s(now_s)

    # --- orbit ---------------------------------------------------------------------------------------
    def on_tle(self, msg, now_s: float, authenticated: bool) -> None:
        """DEBRIS_TLE: stage the lines (authenticated only) for MAV_CMD_DEBRIS_TLE_LOAD."""
        if not authenticated:
            self._refuse("unsigned", "TLE refused: not signed with the mission key")
            return
        self._staged = (_text(msg.line1), _text(msg.line2))

    def cmd_tle_load(self, msg, now_s: float) -> int:
        """MAV_CMD_DEBRIS_TLE_LOAD: param1 the staged lines' CRC (`tle_crc`)."""
        crc = int_param(msg.param1, 0, 0xFFFFFF, "crc")
        if self._staged is None or tle_crc(*self._staged) != crc:
            return self._refuse("not staged", "TLE load refused: no DEBRIS_TLE staged with this CRC")
        return self.check_and_load(*self._staged, now_s)

    def preset(self, now_s: float, utc_s: float, line1: str | None = None, line2: str | None = None) -> int:
        """What a composition hands the box before the loop (SITL: the scenario's UTC and TLE): the time,
        then the TLE through the same checks as an upload; the MAV_RESULT of the TLE (ACCEPTED without one)."""
        self.set_time(now_s, utc_s)
        if line1 is None or line2 is None:
            return mavlink.MAV_RESULT_ACCEPTED
        return self.check_and_load(line1, line2, now_s)

    def check_and_load(self, line1: str, line2: str, now_s: float) -> int:
        """Format, checksums, epoch against the onboard UTC and the age limit; then in force. MAV_RESULT."""
        try:
            tle = tles.parse_tle(line1, line2)
        except tles.TleError as e:
            return self._refuse(e.reason, f"TLE refused: {e}")
        if not self.clock.known:
            return self._refuse("no time", "TLE refused: no UTC on board to check its epoch (set the time first)",
                                mavlink.MAV_RESULT_TEMPORARILY_REJECTED)
        try:
            tles.check_epoch(tle, self.clock.utc_s(now_s), self.max_tle_age_s)
        except tles.TleError as e:
            return self._refuse(e.reason, f"TLE refused: {e}")
        self.load(tle)
        return mavlink.MAV_RESULT_ACCEPTED

    def load(self, tle: tles.Tle) -> None:
        """Put a checked TLE in force and keep it in the TLE file (a write failure is counted and said)."""
        self.tle = tle
        self.tle_loaded += 1
        self._field = None
        self._next_status_s = self._next_tle_s = -math.inf
        self.tle_persisted = False
        if self.tle_file is not None:
            try:
                write_atomic(self.tle_file, tle.text)
                self.tle_persisted = True
            except OSError as e:
                self.persist_errors += 1
                self.last_error = f"TLE in force but not kept in {self.tle_file}: {e}"

    def _refuse(self, reason: str, text: str, result: int = mavlink.MAV_RESULT_DENIED) -> int:
        self.tle_refused += 1
        self._next_status_s = -math.inf
        self.last_refusal = REFUSAL[reason]
        self.last_error = text
        if self._router is not None:
            self._router.set_result_param2(self.last_refusal)
        return result

    def _set_max_age(self, days: float) -> None:
        self.max_tle_age_s = days * 86400.0

    def tle_age_s(self, now_s: float) -> float:
        if self.tle is None or not self.clock.known:
            return math.nan
        return self.tle.age_s(self.clock.utc_s(now_s))

    def tle_state(self, now_s: float) -> int:
        if self.tle is None:
            return mavlink.DEBRIS_TLE_STATE_NONE
        if not self.clock.known:
            return mavlink.DEBRIS_TLE_STATE_NO_TIME
        age = self.tle_age_s(now_s)
        if age < 0:
            return mavlink.DEBRIS_TLE_STATE_FUTURE
        if age > self.max_tle_age_s:
            return mavlink.DEBRIS_TLE_STATE_STALE
        return mavlink.DEBRIS_TLE_STATE_OK

    # --- field ---------------------------------------------------------------------------------------
    def field_now(self, now_s: float) -> tuple[OnboardOrbitField | None, str]:
        """(the field along the orbit, "") when time and a usable TLE are on board, else (None, why)."""
        state = self.tle_state(now_s)
        if state != mavlink.DEBRIS_TLE_STATE_OK:
            return None, STATE_NAMES[state]
        if self._field is None:
            c = self.clock
            m0 = c.last_set_mono_s
            try:
                self._field = OnboardOrbitField(self.tle.satrec(), affine_utc(m0, c.utc_s(m0), c.drift),
                                                degree=self.degree, knot_step_s=self.knot_step_s,
                                                utc_ref_s=c.utc_s(now_s))
            except ValueError as e:  # outside IGRF-14's span
                self.field_errors += 1
                self.last_error = self.last_field_error = f"field model: {e}"
                return None, str(e)
        return self._field, ""

    # --- telemetry -----------------------------------------------------------------------------------
    def summary_line(self, now_s: float) -> str | None:
        """The end-of-run line, when anything was set or refused (None otherwise)."""
        c = self.clock
        if not (c.sets or self.time_refused or self.tle_loaded or self.tle_refused):
            return None
        utc = f"UTC {_iso(c.utc_s(now_s))} ({c.sets} sets" + (
            f", drift {c.drift_ppm:.1f} ppm)" if math.isfinite(c.drift) else ")") if c.known else "no UTC"
        tle = (f"TLE {self.tle.satnum} epoch {_iso(self.tle.epoch_utc_s)}: {STATE_NAMES[self.tle_state(now_s)]}"
               if self.tle else "no TLE")
        return (f"time and orbit: {utc}; {tle}; refused {self.time_refused} time sets, {self.tle_refused} TLEs"
                + (f" (last: {self.last_error})" if self.tle_refused or self.time_refused else "")
                + (f"; {self.field_errors} field errors (last: {self.last_field_error})" if self.field_errors else ""))

    def message_fields(self, now_s: float) -> dict:
        c = self.clock
        utc = c.utc_s(now_s)
        u16 = 0xFFFF
        return dict(utc_usec=int(round(utc * 1e6)) if c.known else 0,
                    time_set_age=now_s - c.last_set_mono_s if c.known else math.nan,
                    drift_ppm=c.drift_ppm, last_set_residual=c.last_residual_s,
                    time_sets=min(c.sets, u16), time_refused=min(self.time_refused, u16),
                    tle_epoch_usec=int(round(self.tle.epoch_utc_s * 1e6)) if self.tle else 0,
                    tle_age=self.tle_age_s(now_s), tle_state=self.tle_state(now_s),
                    tle_loaded=min(self.tle_loaded, u16), tle_refused=min(self.tle_refused, u16),
                    tle_last_refusal=self.last_refusal, field_degree=self.degree,
                    tle_persisted=1 if self.tle_persisted else 0)


def _iso(utc_s: float) -> str:
    from datetime import datetime, timezone
    return datetime.fromtimestamp(utc_s, timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")
