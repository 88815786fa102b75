"""What the box said it knew while it recorded, as a recording's metadata (docs/spec/recording-format.md,
"Metadata"): the ground refines a recording with the orbit, the time and the calibration the box flew.

From the box's telemetry, per run of its flight software (`ground.streams.Segment.knowledge`):

- ``utc0``: the UTC of the run's t = 0 (the flight software's loop time 0), ISO 8601 to the µs, from the
  box's UTC estimate. DEBRIS_TIME_ORBIT gives the onboard UTC ``utc_usec`` at loop time ``time_usec`` and
  the clock's drift: the box's time is affine, UTC(t) = utc + (1 + drift)(t − time), so
  utc0 = utc − (1 + drift) · time. Without it, SYSTEM_TIME (``time_unix_usec`` at ``time_boot_ms``: 1 ms).
  The latest estimate is the one kept (a new time set from the ground moves it).
- ``tle_line1``, ``tle_line2``: the TLE in force on board (DEBRIS_TLE sent by the box, every minute and
  when one is put in force), checked as an upload is (format, checksums: `fsw.estimation.tle`); a bad one
  is counted and not used. ``tle_state``: what DEBRIS_TIME_ORBIT said of it (``ok``, ``stale``, ...).
- ``field_model``: ``igrf14:D``, the degree of the box's field model (DEBRIS_TIME_ORBIT.field_degree).
- ``magcal_hard_iron_uT`` (x, y, z), ``magcal_soft_iron`` (D, nine numbers row-major: B = (I + D)(B_meas − b)),
  ``magcal_hard_iron_sigma_uT``, ``magcal_state``, ``magcal_t_s`` (its loop time): the last calibration the
  box applied on board (DEBRIS_MAGCAL once one exists). The box sends its sensor's own samples, so it is
  *not* applied to the recording's samples: the format's ``hard_iron_uT`` / ``soft_iron`` (already applied)
  are not written. The ground tools apply it by default (`ground.magcal`).

Nothing is inferred: a key the box did not say is absent.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from datetime import datetime, timedelta, timezone

import numpy as np

from fsw.estimation.tle import TleError, parse_tle
from fsw.telemetry.dialect import mavlink

#: the keys this module writes (a recording's metadata keys), in the order written
TIME_KEYS = ("utc0",)
ORBIT_KEYS = ("tle_line1", "tle_line2", "tle_state", "field_model")
MAGCAL_KEYS = ("magcal_hard_iron_uT", "magcal_soft_iron", "magcal_hard_iron_sigma_uT", "magcal_state",
               "magcal_t_s")
KEYS = TIME_KEYS + ORBIT_KEYS + MAGCAL_KEYS

_EPOCH = datetime(1970, 1, 1, tzinfo=timezone.utc)
#: a UTC of t = 0 outside these years is not a time the box could have had (a damaged or hostile frame)
UTC0_RANGE_S = ((datetime(2000, 1, 1, tzinfo=timezone.utc) - _EPOCH).total_seconds(),
                (datetime(2200, 1, 1, tzinfo=timezone.utc) - _EPOCH).total_seconds())
#: DEBRIS_MAGCAL states in which a calibration is applied (with finite σ)
_CALIBRATED = {mavlink.DEBRIS_MAGCAL_STATE_CONVERGED, mavlink.DEBRIS_MAGCAL_STATE_UNCERTAIN,
               mavlink.DEBRIS_MAGCAL_STATE_REJECTED}


def iso_utc(utc_s: float) -> str:
    """POSIX seconds as ISO 8601 UTC to the microsecond (``2026-11-21T12:00:00.250000Z``)."""
    t = _EPOCH + timedelta(microseconds=round(utc_s * 1e6))
    return t.strftime("%Y-%m-%dT%H:%M:%S.%fZ")


def _enum_name(enum: str, value: int, prefix: str) -> str:
    entry = mavlink.enums[enum].get(int(value))
    return entry.name.removeprefix(prefix).lower() if entry else str(int(value))


def _numbers(values) -> str:
    return ", ".join(str(np.float32(v)) for v in values)


@dataclass
class BoxKnowledge:
    """The latest of what one run of the box's flight software said it knew."""

    utc0_s: float | None = None
    utc0_from: str = ""  # "DEBRIS_TIME_ORBIT" or "SYSTEM_TIME"
    tle: tuple[str, str] | None = None
    tle_state: str | None = None
    field_degree: int | None = None
    magcal: dict[str, str] = field(default_factory=dict)
    #: the loop time of the calibration held (for how often the recorder restates it)
    magcal_t_s: float | None = None
    magcal_state: str | None = None
    #: loop time of the latest time message taken: an older one (sent again after an outage) says less
    time_us: int = -1

    def time_orbit(self, msg) -> bool:
        """DEBRIS_TIME_ORBIT; False when its values cannot be used (counted by the caller)."""
        if msg.time_usec < self.time_us and self.utc0_from == "DEBRIS_TIME_ORBIT":
            return True
        self.time_us = int(msg.time_usec)
        drift_ppm = float(msg.drift_ppm)
        if msg.utc_usec:
            drift = drift_ppm * 1e-6 if math.isfinite(drift_ppm) else 0.0
            utc0 = msg.utc_usec * 1e-6 - (1.0 + drift) * msg.time_usec * 1e-6
            if not UTC0_RANGE_S[0] <= utc0 < UTC0_RANGE_S[1]:  # also NaN
                return False
            self.utc0_s, self.utc0_from = utc0, "DEBRIS_TIME_ORBIT"
        self.tle_state = _enum_name("DEBRIS_TLE_STATE", msg.tle_state, "DEBRIS_TLE_STATE_") if msg.tle_epoch_usec \
            else None
        self.field_degree = int(msg.field_degree) or None
        return True

    def system_time(self, msg) -> bool:
        """SYSTEM_TIME: the UTC of t = 0 to 1 ms, unless DEBRIS_TIME_ORBIT has given it; False when it is
        not a time the box could have had."""
        if msg.time_unix_usec and self.utc0_from != "DEBRIS_TIME_ORBIT":
            utc0 = msg.time_unix_usec * 1e-6 - msg.time_boot_ms * 1e-3
            if not UTC0_RANGE_S[0] <= utc0 < UTC0_RANGE_S[1]:
                return False
            self.utc0_s, self.utc0_from = utc0, "SYSTEM_TIME"
        return True

    def tle_lines(self, msg) -> bool:
        """DEBRIS_TLE from the box; False (not kept) when the lines are not a valid TLE."""
        try:
            tle = parse_tle(_text(msg.line1), _text(msg.line2))
        except TleError:
            return False
        self.tle = (tle.line1, tle.line2)
        return True

    def calibration(self, msg) -> bool:
        """DEBRIS_MAGCAL; kept when a calibration is applied (state with finite σ); False when its values are
        not finite."""
        if msg.state not in _CALIBRATED or (self.magcal_t_s is not None and msg.time_usec * 1e-6 < self.magcal_t_s):
            return True
        b, terms, sb = list(msg.hard_iron), list(msg.soft_iron), list(msg.hard_iron_sigma)
        if not all(map(math.isfinite, b + terms + sb)):
            return False
        d11, d22, d33, d12, d13, d23 = terms
        D = (d11, d12, d13, d12, d22, d23, d13, d23, d33)
        self.magcal_t_s = msg.time_usec * 1e-6
        self.magcal_state = _enum_name("DEBRIS_MAGCAL_STATE", msg.state, "DEBRIS_MAGCAL_STATE_")
        self.magcal = {"magcal_hard_iron_uT": _numbers(b), "magcal_soft_iron": _numbers(D),
                       "magcal_hard_iron_sigma_uT": _numbers(sb), "magcal_state": self.magcal_state,
                       "magcal_t_s": f"{self.magcal_t_s:.6f}"}
        return True

    def summary(self) -> str:
        """One line of what is known ("" when nothing), for the decoder's summary."""
        parts = []
        if self.utc0_s is not None:
            parts.append(f"UTC of t = 0 {iso_utc(self.utc0_s)} ({self.utc0_from})")
        if self.tle is not None:
            parts.append(f"TLE {self.tle[0][2:7].strip()}" + (f" ({self.tle_state})" if self.tle_state else ""))
        if self.magcal:
            parts.append(f"calibration {self.magcal_state} at t = {self.magcal_t_s:.0f} s, hard iron "
                         f"{self.magcal['magcal_hard_iron_uT']} µT")
        return "; ".join(parts)

    def metadata(self) -> dict[str, str]:
        """The recording's ``# key: value`` entries for what is known (in `KEYS` order)."""
        out: dict[str, str] = {}
        if self.utc0_s is not None:
            out["utc0"] = iso_utc(self.utc0_s)
        if self.tle is not None:
            out["tle_line1"], out["tle_line2"] = self.tle
            if self.tle_state:
                out["tle_state"] = self.tle_state
        if self.field_degree:
            out["field_model"] = f"igrf14:{self.field_degree}"
        out.update(self.magcal)
        return out


def _text(raw) -> str:
    if isinstance(raw, (bytes, bytearray)):
        return bytes(raw).split(b"\x00", 1)[0].decode("ascii", errors="replace")
    return str(raw).split("\x00", 1)[0]
