"""The field along the orbit as the box knows it: its TLE through SGP4, its UTC, IGRF-14 at the flight
degree, evaluated on a grid of knots and interpolated in between.

:class:`OnboardOrbitField` has the interface of `field_motion.OrbitField` (``b_eci_T(t_s)``, calling it,
``turn_rate_radps``), with t in the flight software's own (monotonic) time: UTC(t) comes from a frozen
snapshot of the onboard time estimate (`utc_clock.UtcEstimator`), so a field handed to an estimator or
to the identification fit stays one function of t even when the time is set again (the owner builds a
new one then).

Per knot (every `knot_step_s` of loop time, 60 s by default): SGP4 position (TEME, taken as inertial),
Greenwich mean sidereal time of the UTC (UT1 ≈ UTC: 0.9 s at most, 0.004° of Earth rotation), the IGRF
field at the Earth-fixed position, turned back to inertial axes. Between knots: cubic Lagrange
interpolation over the four knots around t (the field along an orbit is smooth: the interpolation
error is measured against direct evaluation in tests/fsw/test_onboard_field.py). Knots are computed
when first needed, a batch at a time, and cached (at most `max_knots`; the cache starts afresh when
full).
"""
from __future__ import annotations

import math
from typing import Callable

import numpy as np

from .field_motion import CircularOrbitModel, OrbitField, TleOrbitModel, gmst_rad, rot_z
from .igrf import FLIGHT_DEGREE, IgrfModel, unix_to_decimal_year

_JD_UNIX_EPOCH = 2440587.5
#: the knot spacing flown (loop time between two direct evaluations of orbit and field)
KNOT_STEP_S = 60.0


def flight_field(orbit, epoch_year: float) -> OrbitField:
    """The box's field model along `orbit` (``position_eci_m(t)``): IGRF-14 at the flight degree at the
    decimal year `epoch_year` (ValueError outside IGRF-14's span)."""
    return OrbitField(orbit, IgrfModel(epoch_year, FLIGHT_DEGREE))


class KnotField:
    """Knots of a field along the orbit (`direct_b_eci_T`, a subclass's) every `knot_step_s`, cubic
    Lagrange interpolation in between (the interface of `field_motion.OrbitField`)."""

    def __init__(self, knot_step_s: float = KNOT_STEP_S, max_knots: int = 8192) -> None:
        self.knot_step_s = float(knot_step_s)
        self.max_knots = int(max_knots)
        self._knots: dict[int, np.ndarray] = {}
        self.knots_evaluated = 0
        # the last scalar time asked and its field: every filter of a bank (a shape trial's 35, the rate
        # models' 6) asks for the same sample's time in turn
        self._last: tuple[float, np.ndarray] | None = None

    def direct_b_eci_T(self, t_s) -> np.ndarray:
        raise NotImplementedError

    def b_eci_T(self, t_s) -> np.ndarray:
        """B_I at t, interpolated between knots."""
        if np.ndim(t_s) == 0 and self._last is not None and self._last[0] == t_s:
            return self._last[1].copy()
        t = np.asarray(t_s, float)
        x = t.ravel() / self.knot_step_s
        k0 = np.floor(x).astype(np.int64)
        u = x - k0
        idx = k0[:, None] + np.arange(-1, 3)[None, :]
        self._ensure(np.unique(idx))
        knots = self._knots
        vals = np.array([knots[int(i)] for i in idx.ravel()]).reshape(idx.shape + (3,))
        # cubic Lagrange weights on nodes -1, 0, 1, 2
        w = np.stack((-u * (u - 1) * (u - 2) / 6, (u + 1) * (u - 1) * (u - 2) / 2,
                      -(u + 1) * u * (u - 2) / 2, (u + 1) * u * (u - 1) / 6), axis=-1)
        b = np.einsum("nk,nkj->nj", w, vals).reshape(t.shape + (3,))
        if t.ndim == 0:
            self._last = (float(t), b.copy())
        return b

    __call__ = b_eci_T
    turn_rate_radps = OrbitField.turn_rate_radps

    def _ensure(self, ks: np.ndarray) -> None:
        """Every knot of `ks` in the table; when it would grow past `max_knots`, the knots not asked for now
        are dropped first (a flight of more than `max_knots` × `knot_step_s`: 5.7 days at 60 s)."""
        missing = [int(k) for k in ks if int(k) not in self._knots]
        if not missing:
            return
        if len(self._knots) + len(missing) > self.max_knots:
            knots = self._knots
            self._knots = {int(k): knots[int(k)] for k in ks if int(k) in knots}
        b = self.direct_b_eci_T(np.array(missing, float) * self.knot_step_s)
        self._knots.update(zip(missing, b))
        self.knots_evaluated += len(missing)


class OnboardOrbitField(KnotField):
    """B_I(t) [T, inertial axes] along the orbit of `satrec` (an sgp4 Satrec), with UTC(t) = `utc_of(t)`."""

    def __init__(self, satrec, utc_of: Callable[[np.ndarray], np.ndarray], *, field=None,
                 degree: int = FLIGHT_DEGREE, knot_step_s: float = KNOT_STEP_S, max_knots: int = 8192,
                 utc_ref_s: float | None = None) -> None:
        """`field`: an Earth-fixed model with ``b_ecef_T`` (default: IGRF-14 at `degree` at the decimal
        year of `utc_ref_s`, else of UTC(0)); ValueError outside IGRF-14's span."""
        self.sat = satrec
        self.utc_of = utc_of
        if field is None:
            ref = float(utc_of(np.array([0.0]))[0]) if utc_ref_s is None else float(utc_ref_s)
            field = IgrfModel(unix_to_decimal_year(ref), degree)
        self.field = field
        super().__init__(knot_step_s, max_knots)

    def direct_b_eci_T(self, t_s) -> np.ndarray:
        """B_I at t, evaluated directly (SGP4 + GMST + the field model); ValueError on an SGP4 error."""
        t = np.atleast_1d(np.asarray(t_s, float))
        utc = np.asarray(self.utc_of(t), float)
        days = utc / 86400.0
        whole = np.floor(days)
        jd, fr = whole + _JD_UNIX_EPOCH, days - whole
        err, r_km, _ = self.sat.sgp4_array(jd, fr)
        if np.any(err):
            raise ValueError(f"SGP4 error codes {sorted(set(err[err != 0].tolist()))}")
        theta = gmst_rad(jd + fr)
        b = rot_z(self.field.b_ecef_T(rot_z(r_km * 1e3, -theta)), theta)
        return b[0] if np.ndim(t_s) == 0 else b.reshape(np.shape(t_s) + (3,))

class InterpolatedOrbitField(KnotField):
    """An `field_motion.OrbitField` (a fixed orbit and model, e.g. IGRF-14 at the flight degree along a
    circular orbit) evaluated at knots and interpolated: a sample a second costs 0.1 ms, not 2 ms."""

    def __init__(self, orbit_field: OrbitField, knot_step_s: float = KNOT_STEP_S, max_knots: int = 8192) -> None:
        super().__init__(knot_step_s, max_knots)
        self.orbit_field = orbit_field

    def direct_b_eci_T(self, t_s) -> np.ndarray:
        return self.orbit_field.b_eci_T(t_s)


def affine_utc(mono0_s: float, utc0_s: float, drift: float = 0.0) -> Callable[[np.ndarray], np.ndarray]:
    """UTC(t) = utc0 + (t − mono0)(1 + drift): a frozen snapshot of an onboard time estimate."""
    d = 0.0 if math.isnan(drift) else float(drift)

    def utc_of(t):
        return utc0_s + (np.asarray(t, float) - mono0_s) * (1.0 + d)
    return utc_of


def field_from_metadata(md: dict) -> OrbitField | None:
    """The field along the orbit of a recording's metadata (recording-format.md): a TLE
    (``tle_line1``, ``tle_line2`` with ``utc0``) or a circular orbit (``orbit_altitude_km``,
    ``orbit_inclination_deg``, ``orbit_raan_deg``, ``orbit_arg_lat0_deg``); IGRF-14 at the flight degree at
    ``field_epoch_year`` (else the year of ``utc0``, else 2025). None when no orbit is given;
    ValueError when one is given but cannot be used."""
    from datetime import datetime

    utc = None
    if md.get("utc0"):
        try:
            utc = datetime.fromisoformat(md["utc0"])
        except ValueError:
            raise ValueError(f"utc0 {md['utc0']!r} is not ISO 8601") from None
    try:
        epoch = (float(md["field_epoch_year"]) if "field_epoch_year" in md
                 else utc.year + (utc.timetuple().tm_yday - 1) / 365.25 if utc else 2025.0)
        if md.get("tle_line1") and md.get("tle_line2"):
            if utc is None:
                raise ValueError("a TLE needs utc0 (the UTC of t = 0)")
            orbit = TleOrbitModel(md["tle_line1"], md["tle_line2"], (utc.year, utc.month, utc.day, utc.hour,
                                                                     utc.minute, utc.second + utc.microsecond * 1e-6))
        elif all(k in md for k in ("orbit_altitude_km", "orbit_inclination_deg", "orbit_raan_deg",
                                   "orbit_arg_lat0_deg")):
            orbit = CircularOrbitModel(float(md["orbit_altitude_km"]) * 1e3, float(md["orbit_inclination_deg"]),
                                       float(md["orbit_raan_deg"]), float(md["orbit_arg_lat0_deg"]))
        else:
            return None
        return flight_field(orbit, epoch)
    except (TypeError, KeyError) as e:
        raise ValueError(str(e)) from None
