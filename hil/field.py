"""Geomagnetic main field for the simulator: IGRF-14 to degree 13 (the default truth) and its centred,
tilted dipole.

Source of the coefficients: IGRF-14, International Association of Geomagnetism and
Aeronomy (2024), file ``igrf14coeffs.txt``, doi:10.5281/zenodo.14012302, distributed by
NOAA/NCEI (https://www.ncei.noaa.gov/products/international-geomagnetic-reference-field).
Schmidt semi-normalised Gauss coefficients of degree 1 [nT]:

=====  ===============  ===============  ====================
coef   DGRF 2020.0      IGRF 2025.0      SV 2025-2030 [nT/yr]
=====  ===============  ===============  ====================
g10    -29403.41        -29350.0         12.6
g11     -1451.37         -1410.3         10.0
h11      4653.35          4545.5        -21.5
=====  ===============  ===============  ====================

Degree-1 potential (IGRF definition, a = 6371.2 km, θ geocentric colatitude,
φ east longitude)::

    V = a (a/r)² [g10 cos θ + (g11 cos φ + h11 sin φ) sin θ],     B = −∇V

which is exactly the field of a centred dipole. Writing ``g = (g11, h11, g10)`` in
ECEF axes, ``V = a³ (g·r)/r³`` and ``B = a³ (3 (g·r̂) r̂ − g)/r³``. Comparing with
``B = (μ0/4π)(3 (m·r̂) r̂ − m)/r³`` gives the dipole moment

    m = +(4π a³ / μ0) · (g11, h11, g10)      (with the coefficients in tesla)

with a plus sign: g10 < 0, so m points to the southern hemisphere and the north
geomagnetic pole (where field lines enter the ground) lies along −m, at
geocentric latitude 90° − arccos(−g10/B0), longitude atan2(−h11, −g11),
B0 = sqrt(g10² + g11² + h11²) (≈ 80.80° N, 72.76° W for 2025.0).

The full IGRF-14 (to degree 13), :class:`IgrfField`, replaces :class:`DipoleField` anywhere a
:class:`FieldModel` is accepted; it is the simulator's default (scenario ``[field] model =
"igrf14"``). Its coefficients and Legendre functions come from ``ppigrf`` (K. M. Laundal, MIT
licence; the IAGA file ``IGRF14.shc`` ships with it): a pure-numpy implementation, evaluated here
in geocentric coordinates (no geodetic conversion is needed for a position in ECEF). The Gauss
coefficients are interpolated linearly in time to the epoch once, at construction (the IGRF rule;
ppigrf does the same per call), and the field is vectorised over positions.

Along a 485 km / 97.5° circular orbit over a day, the dipole differs from the degree-13 field by
8.6 µT RMS (vector), 10.6° RMS in direction, 35° at worst (tests/hil/test_igrf.py pins the figures).

Cost (measured with ``timeit`` on the development machine, a shared 2-core VM): one position per call
≈ 4 ms (ppigrf's Legendre recursion is a Python loop over (n, m)); 1000 positions in one call ≈ 17 µs
each. The simulator therefore tabulates B_ECI along its prescribed orbit in batches at 1 s and
interpolates (:class:`FieldTable`, error < 0.1 nT).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np

from hil.orbit import CircularOrbit, R_EARTH_M, ecef_to_eci, eci_to_ecef

__all__ = [
    "MU0_NA2",
    "IGRF14_DGRF2020_NT",
    "IGRF14_IGRF2025_NT",
    "IGRF14_SV_2025_2030_NTPYR",
    "FieldModel",
    "FIELD_MODELS",
    "igrf14_degree1_nT",
    "DipoleField",
    "IgrfField",
    "make_field",
    "b_eci_from_model_T",
    "field_eci_T",
    "FieldAlongOrbit",
    "FieldTable",
]

MU0_NA2 = 1.25663706212e-6
"""Vacuum permeability μ0 [N/A²] (CODATA 2018); used only to express the dipole moment."""

# (g10, g11, h11) in nT, from igrf14coeffs.txt (see module docstring)
IGRF14_DGRF2020_NT = (-29403.41, -1451.37, 4653.35)
IGRF14_IGRF2025_NT = (-29350.0, -1410.3, 4545.5)
IGRF14_SV_2025_2030_NTPYR = (12.6, 10.0, -21.5)

_EPOCH_MIN_YEAR = 2020.0
_EPOCH_MAX_YEAR = 2030.0


@runtime_checkable
class FieldModel(Protocol):
    """Any internal field model: B in ECEF axes [T] at ECEF position(s) (..., 3) [m]."""

    def b_ecef_T(self, r_ecef_m: np.ndarray) -> np.ndarray: ...


def igrf14_degree1_nT(epoch_year: float) -> tuple[float, float, float]:
    """(g10, g11, h11) [nT] of IGRF-14 at a decimal year in [2020, 2030].

    IGRF rule: linear interpolation between the 5-yearly models (DGRF 2020.0 ->
    IGRF 2025.0), linear extrapolation with the predictive secular variation
    after 2025.0 (valid to 2030.0).
    """
    if not (_EPOCH_MIN_YEAR <= epoch_year <= _EPOCH_MAX_YEAR):
        raise ValueError(
            f"epoch_year {epoch_year!r} outside the supported IGRF-14 span "
            f"[{_EPOCH_MIN_YEAR}, {_EPOCH_MAX_YEAR}]"
        )
    if epoch_year >= 2025.0:
        dt_yr = epoch_year - 2025.0
        return tuple(c + sv * dt_yr for c, sv in zip(IGRF14_IGRF2025_NT, IGRF14_SV_2025_2030_NTPYR))
    w = (epoch_year - 2020.0) / 5.0
    return tuple((1.0 - w) * c0 + w * c1 for c0, c1 in zip(IGRF14_DGRF2020_NT, IGRF14_IGRF2025_NT))


class DipoleField:
    """Centred tilted dipole from the IGRF-14 degree-1 Gauss coefficients at ``epoch_year``.

    The epoch is fixed at construction (secular variation is ~20 nT/yr, irrelevant
    over a simulated pass). Valid for 2020.0-2030.0.
    """

    def __init__(self, epoch_year: float = 2025.0) -> None:
        self.epoch_year = float(epoch_year)
        self.g10_nT, self.g11_nT, self.h11_nT = igrf14_degree1_nT(self.epoch_year)
        self.reference_radius_m = R_EARTH_M

    @property
    def b0_T(self) -> float:
        """Dipole field strength on the geomagnetic equator at r = a: sqrt(g10² + g11² + h11²) [T]."""
        return 1e-9 * float(np.sqrt(self.g10_nT**2 + self.g11_nT**2 + self.h11_nT**2))

    @property
    def dipole_moment_Am2(self) -> np.ndarray:
        """Dipole moment in ECEF axes: m = (4π a³/μ0) (g11, h11, g10) [A·m²] (points south)."""
        g_T = 1e-9 * np.array([self.g11_nT, self.h11_nT, self.g10_nT])
        return (4.0 * np.pi * self.reference_radius_m**3 / MU0_NA2) * g_T

    def north_geomagnetic_pole_deg(self) -> tuple[float, float]:
        """(geocentric latitude, east longitude) [deg] where the dipole axis meets the northern hemisphere."""
        b0_nT = np.sqrt(self.g10_nT**2 + self.g11_nT**2 + self.h11_nT**2)
        lat = 90.0 - np.degrees(np.arccos(-self.g10_nT / b0_nT))
        lon = np.degrees(np.arctan2(-self.h11_nT, -self.g11_nT))
        return float(lat), float(lon)

    def b_ecef_T(self, r_ecef_m: np.ndarray) -> np.ndarray:
        """Field in ECEF axes [T] at ECEF position(s) ``r_ecef_m`` (..., 3) [m], r > 0.

        Spherical components from B = −∇V (geocentric r, colatitude θ, east longitude φ)::

            B_r = 2 (a/r)³ [g10 cos θ + (g11 cos φ + h11 sin φ) sin θ]
            B_θ =   (a/r)³ [g10 sin θ − (g11 cos φ + h11 sin φ) cos θ]
            B_φ =   (a/r)³ [g11 sin φ − h11 cos φ]

        then ``B = B_r r̂ + B_θ θ̂ + B_φ φ̂`` (regular on the rotation axis too).
        """
        r_vec = np.asarray(r_ecef_m, dtype=float)
        x, y, z = r_vec[..., 0], r_vec[..., 1], r_vec[..., 2]
        rho = np.hypot(x, y)
        r = np.hypot(rho, z)
        theta = np.arctan2(rho, z)
        phi = np.arctan2(y, x)
        ct, st = np.cos(theta), np.sin(theta)
        cp, sp = np.cos(phi), np.sin(phi)

        k = 1e-9 * (self.reference_radius_m / r) ** 3  # nT -> T with the (a/r)^3 decay
        g1_phi = self.g11_nT * cp + self.h11_nT * sp
        b_r = 2.0 * k * (self.g10_nT * ct + g1_phi * st)
        b_theta = k * (self.g10_nT * st - g1_phi * ct)
        b_phi = k * (self.g11_nT * sp - self.h11_nT * cp)

        # r̂ = (sθ cφ, sθ sφ, cθ), θ̂ = (cθ cφ, cθ sφ, −sθ), φ̂ = (−sφ, cφ, 0)
        b_rho = b_r * st + b_theta * ct  # horizontal-plane radial part
        return np.stack((b_rho * cp - b_phi * sp, b_rho * sp + b_phi * cp, b_r * ct - b_theta * st), axis=-1)

    def b_eci_T(self, r_eci_m: np.ndarray, t_s: float | np.ndarray, era0_rad: float = 0.0) -> np.ndarray:
        """Field in ECI axes [T] at ECI position(s) [m] and time(s) t_s (see :func:`b_eci_from_model_T`)."""
        return b_eci_from_model_T(self, r_eci_m, t_s, era0_rad)


@functools.lru_cache(maxsize=4)
def _read_shc(path: str):
    """ppigrf's coefficient tables (g, h) of a .shc file, read once per file (copies are handed out)."""
    from ppigrf import ppigrf as pp

    return pp.read_shc(path)


class IgrfField:
    """IGRF-14 (``ppigrf``'s coefficient file) to ``degree`` (1..13) at a fixed decimal-year epoch.

    Valid for the file's span (1900.0-2030.0: definitive and main-field models, the predictive
    secular variation after 2025.0); an epoch outside it is refused with ValueError. ``coeff_file``:
    another ``.shc`` file (the tests check the evaluation against NOAA's calculator for IGRF-13).
    """

    def __init__(self, epoch_year: float = 2025.0, degree: int = 13, coeff_file: str | None = None) -> None:
        import pandas as pd
        from ppigrf import ppigrf as pp

        if isinstance(degree, bool) or not isinstance(degree, (int, np.integer)) or not 1 <= degree <= 13:
            raise ValueError(f"IGRF degree must be an integer in 1..13, got {degree!r}")
        g, h = _read_shc(coeff_file or pp.shc_fn_igrf14)
        span = (float(g.index[0].year), float(g.index[-1].year))  # the models are at 1 January
        try:
            epoch_year = float(epoch_year)
        except (TypeError, ValueError, OverflowError):
            raise ValueError(f"epoch_year must be a decimal year, got {epoch_year!r}") from None
        if not np.isfinite(epoch_year) or not span[0] <= epoch_year <= span[1]:
            raise ValueError(f"epoch_year {epoch_year!r} outside the IGRF model's validity "
                             f"[{span[0]:.1f}, {span[1]:.1f}]")
        self.epoch_year = float(epoch_year)
        self.degree = int(degree)
        self.reference_radius_m = R_EARTH_M
        date = pd.DatetimeIndex(pp.yearfrac_to_datetime([self.epoch_year])).as_unit(g.index.unit)
        index = g.index.union(date)
        # the IGRF rule: linear in time between the 5-yearly models (as ppigrf.igrf_gc does)
        g_t = g.reindex(index).interpolate(method="time").loc[date].to_numpy()[0]
        h_t = h.reindex(index).interpolate(method="time").loc[date].to_numpy()[0]
        keys = [k for k in g.columns if k[0] <= self.degree]
        cols = [list(g.columns).index(k) for k in keys]
        self._keys = keys
        self._n = np.array([k[0] for k in keys], float)
        self._m = np.array([k[1] for k in keys], float)
        self._g_nT = g_t[cols]
        self._h_nT = h_t[cols]
        self._legendre = pp.get_legendre

    def gauss_nT(self, n: int, m: int) -> tuple[float, float]:
        """(g_n^m, h_n^m) [nT] at the epoch."""
        i = self._keys.index((n, m))
        return float(self._g_nT[i]), float(self._h_nT[i])

    def b_ecef_T(self, r_ecef_m: np.ndarray) -> np.ndarray:
        """Field in ECEF axes [T] at ECEF position(s) ``r_ecef_m`` (..., 3) [m], r > 0.

        Geocentric spherical components (ppigrf's expansion, Schmidt semi-normalised)::

            B_r = Σ (n+1) (a/r)^(n+2) P_n^m(cos θ) (g cos mφ + h sin mφ)
            B_θ = −Σ (a/r)^(n+2) dP_n^m/dθ (g cos mφ + h sin mφ)
            B_φ = −Σ (a/r)^(n+2) m P_n^m (h cos mφ − g sin mφ) / sin θ

        then rotated into ECEF as in :meth:`DipoleField.b_ecef_T`.
        """
        r_vec = np.asarray(r_ecef_m, dtype=float)
        shape = r_vec.shape
        p = r_vec.reshape(-1, 3)
        rho = np.hypot(p[:, 0], p[:, 1])
        r = np.hypot(rho, p[:, 2])
        theta = np.arctan2(rho, p[:, 2])
        phi = np.arctan2(p[:, 1], p[:, 0])
        P, dP = self._legendre(np.degrees(theta), self._keys)
        ar = (self.reference_radius_m / r)[:, None] ** (self._n + 2.0)
        mphi = phi[:, None] * self._m
        cm, sm = np.cos(mphi), np.sin(mphi)
        gc = self._g_nT * cm + self._h_nT * sm
        gs = self._h_nT * cm - self._g_nT * sm
        st, ct = np.sin(theta), np.cos(theta)
        b_r = np.sum(ar * (self._n + 1.0) * P * gc, axis=1)
        b_theta = -np.sum(ar * dP * gc, axis=1)
        b_phi = -np.sum(ar * self._m * P * gs, axis=1) / np.maximum(st, 1e-12)
        cp, sp = np.cos(phi), np.sin(phi)
        b_rho = b_r * st + b_theta * ct
        out = 1e-9 * np.stack((b_rho * cp - b_phi * sp, b_rho * sp + b_phi * cp, b_r * ct - b_theta * st), axis=-1)
        return out.reshape(shape)

    def b_eci_T(self, r_eci_m: np.ndarray, t_s: float | np.ndarray, era0_rad: float = 0.0) -> np.ndarray:
        """Field in ECI axes [T] at ECI position(s) [m] and time(s) t_s (see :func:`b_eci_from_model_T`)."""
        return b_eci_from_model_T(self, r_eci_m, t_s, era0_rad)


#: scenario ``[field] model`` names
FIELD_MODELS = ("igrf14", "igrf14-dipole")


def make_field(model: str = "igrf14", epoch_year: float = 2025.0, degree: int = 13) -> FieldModel:
    """The field model of a scenario: ``igrf14`` (to ``degree``) or ``igrf14-dipole`` (the centred dipole)."""
    if model == "igrf14":
        return IgrfField(epoch_year, degree)
    if model == "igrf14-dipole":
        return DipoleField(epoch_year)
    raise ValueError(f"unknown field model {model!r} (expected one of {FIELD_MODELS})")


def b_eci_from_model_T(
    field: FieldModel, r_eci_m: np.ndarray, t_s: float | np.ndarray, era0_rad: float = 0.0
) -> np.ndarray:
    """Evaluate an ECEF field model at ECI position(s) and express the result in ECI axes [T].

    The Earth (and its field) turns under the inertial frame with the rotation angle
    of :func:`hil.orbit.earth_rotation_angle_rad`.
    """
    r_ecef = eci_to_ecef(r_eci_m, t_s, era0_rad)
    return ecef_to_eci(field.b_ecef_T(r_ecef), t_s, era0_rad)


def field_eci_T(
    orbit: CircularOrbit, field: FieldModel, t_s: float | np.ndarray, era0_rad: float = 0.0
) -> np.ndarray:
    """Geomagnetic field in ECI axes [T] seen along ``orbit`` at time(s) ``t_s``.

    A scalar ``t_s`` gives shape (3,), an array of N times gives (N, 3).
    """
    return b_eci_from_model_T(field, orbit.position_eci_m(t_s), t_s, era0_rad)


@dataclass(frozen=True)
class FieldAlongOrbit:
    """B_inertial(t) for a fixed orbit, field model and Earth rotation angle at t = 0."""

    orbit: CircularOrbit
    field: FieldModel
    era0_rad: float = 0.0

    def b_eci_T(self, t_s: float | np.ndarray) -> np.ndarray:
        """Field in ECI axes [T] at time(s) t_s [s]."""
        return field_eci_T(self.orbit, self.field, t_s, self.era0_rad)


class FieldTable:
    """A function of time tabulated on a grid of ``step_s`` and interpolated linearly, computed lazily in
    vectorised chunks of ``chunk`` points: the simulator's B_ECI(t) along a prescribed orbit when the
    field model is costly (IGRF degree 13: ~4 ms for one position, ~20 µs each in a batch).

    At 1 s the interpolation error is below 0.1 nT along a LEO orbit (the field's finest structure at
    degree 13 passes in minutes); tests/hil/test_igrf.py checks it against direct evaluation.
    """

    def __init__(self, fn, step_s: float = 1.0, chunk: int = 512) -> None:
        self.fn = fn
        self.step_s = float(step_s)
        self.chunk = int(chunk)
        self._chunks: dict[int, np.ndarray] = {}

    def _values(self, k: int) -> np.ndarray:
        """Grid values k·chunk .. (k+1)·chunk (inclusive) as (chunk + 1, 3)."""
        v = self._chunks.get(k)
        if v is None:
            t = (k * self.chunk + np.arange(self.chunk + 1)) * self.step_s
            v = self._chunks[k] = np.asarray(self.fn(t), dtype=float)
            if len(self._chunks) > 64:  # keep memory bounded on a long run: drop the oldest chunk
                self._chunks.pop(next(iter(self._chunks)))
        return v

    def __call__(self, t_s: float | np.ndarray) -> np.ndarray:
        t = np.asarray(t_s, dtype=float)
        flat = np.atleast_1d(t).ravel()
        x = flat / self.step_s
        i = np.floor(x).astype(np.int64)
        f = (x - i)[:, None]
        out = np.empty((len(flat), 3))
        k_all = np.floor_divide(i, self.chunk)
        for k in np.unique(k_all):
            sel = k_all == k
            v = self._values(int(k))
            j = i[sel] - k * self.chunk
            out[sel] = (1.0 - f[sel]) * v[j] + f[sel] * v[j + 1]
        return out[0] if t.ndim == 0 else out.reshape(t.shape + (3,))

    b_eci_T = __call__
