"""The geomagnetic field on board: IGRF-14 from ppigrf's coefficients, truncated to a chosen degree.

ppigrf (IGRF-14 coefficients included) always evaluates its whole series (degree 13) and re-reads
its coefficient file on every call (pandas): far too slow for a loop. Here the Gauss coefficients are
read once with ppigrf's reader (`ppigrf.ppigrf.read_shc`), interpolated linearly in time to the epoch (as
ppigrf and the IGRF definition do; after 2025 the file's 2030 column is the 2025 model plus five
years of secular variation), truncated to `degree`, and the Schmidt-normalised series is evaluated
with ppigrf's Legendre helper (`ppigrf.ppigrf.get_legendre`):

    B = −∇V,  V = a Σₙ (a/r)ⁿ⁺¹ Σₘ (gₙᵐ cos mφ + hₙᵐ sin mφ) Pₙᵐ(cos θ),  a = 6371.2 km,

geocentric (r, colatitude θ, east longitude φ), returned in Earth-fixed Cartesian axes (the
`b_ecef_T` interface of `field_motion.DipoleModel`).

Cost and accuracy (`python -m fsw.estimation.igrf`, one evaluation at one point, and the RMS
difference from degree 13 along a 485 km / 97.5° circular orbit over a day; the README's table)
choose the flight degree, `FLIGHT_DEGREE`. Outside IGRF-14's span (1900–2030) the model refuses
(ValueError) rather than extrapolate.
"""
from __future__ import annotations

import math

import numpy as np

R_REF_M = 6371200.0
#: the degree flown (see the module docstring and the README's table)
FLIGHT_DEGREE = 8
MAX_DEGREE = 13


def _year_fraction(dt) -> float:
    from datetime import datetime
    start = datetime(dt.year, 1, 1)
    return dt.year + (dt - start).total_seconds() / (datetime(dt.year + 1, 1, 1) - start).total_seconds()


_COEFFS: tuple | None = None


def _coefficients() -> tuple[np.ndarray, list[tuple[int, int]], np.ndarray, np.ndarray]:
    """(years, [(n, m)], g[year, k], h[year, k]) from ppigrf's IGRF-14 file, read once per process."""
    global _COEFFS
    if _COEFFS is None:
        from ppigrf.ppigrf import read_shc
        g, h = read_shc()
        years = np.array([_year_fraction(t.to_pydatetime()) for t in g.index])
        keys = [tuple(int(x) for x in k) for k in g.columns]
        _COEFFS = (years, keys, g.to_numpy(float), h.to_numpy(float))
    return _COEFFS


def load_coefficients() -> None:
    """Read the coefficients now (ppigrf imports pandas and parses its file: ~0.5 s), before a loop runs."""
    _coefficients()


def unix_to_decimal_year(utc_s: float) -> float:
    from datetime import datetime, timezone
    return _year_fraction(datetime.fromtimestamp(float(utc_s), timezone.utc).replace(tzinfo=None))


class IgrfModel:
    """IGRF-14 truncated at `degree` (1..13) at the decimal year `epoch_year`; `b_ecef_T(r_ecef_m)`."""

    def __init__(self, epoch_year: float, degree: int = FLIGHT_DEGREE) -> None:
        if not 1 <= int(degree) <= MAX_DEGREE:
            raise ValueError(f"IGRF degree {degree!r}: must be 1 to {MAX_DEGREE}")
        years, keys, g, h = _coefficients()
        if not years[0] <= epoch_year <= years[-1]:
            raise ValueError(f"epoch {epoch_year:.3f} outside IGRF-14's span [{years[0]:g}, {years[-1]:g}]")
        self.degree = int(degree)
        self.epoch_year = float(epoch_year)
        sel = [i for i, (n, _) in enumerate(keys) if n <= self.degree]
        self.keys = [keys[i] for i in sel]
        self.g_nT = np.array([np.interp(epoch_year, years, g[:, i]) for i in sel])
        self.h_nT = np.array([np.interp(epoch_year, years, h[:, i]) for i in sel])
        self.n = np.array([k[0] for k in self.keys], float)
        self.m = np.array([k[1] for k in self.keys], float)

    def b_ecef_T(self, r_ecef_m: np.ndarray) -> np.ndarray:
        from ppigrf.ppigrf import get_legendre
        r_vec = np.asarray(r_ecef_m, float)
        pts = r_vec.reshape(-1, 3)
        x, y, z = pts[:, 0], pts[:, 1], pts[:, 2]
        r = np.sqrt(x * x + y * y + z * z)
        theta = np.clip(np.arccos(np.clip(z / r, -1.0, 1.0)), 1e-9, math.pi - 1e-9)  # P/sin θ: its limit on the axis
        phi = np.arctan2(y, x)
        p, dp = get_legendre(np.degrees(theta), self.keys)
        ratio = (R_REF_M / r)[:, None] ** (self.n + 2.0)
        cos_mp, sin_mp = np.cos(phi[:, None] * self.m), np.sin(phi[:, None] * self.m)
        gc = self.g_nT * cos_mp + self.h_nT * sin_mp
        gs = -self.g_nT * sin_mp + self.h_nT * cos_mp
        b_r = np.sum(ratio * (self.n + 1.0) * p * gc, axis=1)
        b_th = -np.sum(ratio * dp * gc, axis=1)
        sin_t = np.sin(theta)
        b_ph = -np.sum(ratio * self.m * p * gs, axis=1) / sin_t
        ct, st, cp, sp = np.cos(theta), sin_t, np.cos(phi), np.sin(phi)
        b = np.stack((b_r * st * cp + b_th * ct * cp - b_ph * sp,
                      b_r * st * sp + b_th * ct * sp + b_ph * cp,
                      b_r * ct - b_th * st), axis=-1) * 1e-9
        return b.reshape(r_vec.shape)


def _measure(repeats: int = 200) -> list[tuple[int, float, float, float]]:
    """(degree, µs per one-point evaluation, RMS and max |ΔB| vs degree 13 [µT]) along a 485 km / 97.5°
    orbit over a day at 2026.0 (the README's table)."""
    import time

    from .field_motion import A_WGS84_M, OMEGA_EARTH_RADPS, CircularOrbitModel, DipoleModel, rot_z
    orbit = CircularOrbitModel(485e3, 97.5, 30.0, 0.0)
    t = np.arange(0.0, 86400.0, 20.0)
    r_ecef = rot_z(orbit.position_eci_m(t), -OMEGA_EARTH_RADPS * t)
    ref = IgrfModel(2026.0, MAX_DEGREE).b_ecef_T(r_ecef)
    one = np.array([A_WGS84_M + 485e3, 0.0, 0.0])
    rows = []
    for deg in (1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13):
        model = IgrfModel(2026.0, deg)
        model.b_ecef_T(one)
        t0 = time.perf_counter()
        for _ in range(repeats):
            model.b_ecef_T(one)
        us = (time.perf_counter() - t0) / repeats * 1e6
        d = np.linalg.norm(model.b_ecef_T(r_ecef) - ref, axis=-1) * 1e6
        rows.append((deg, us, float(np.sqrt(np.mean(d ** 2))), float(d.max())))
    d = np.linalg.norm(DipoleModel(2026.0).b_ecef_T(r_ecef) - ref, axis=-1) * 1e6
    rows.append((0, math.nan, float(np.sqrt(np.mean(d ** 2))), float(d.max())))
    return rows


if __name__ == "__main__":
    print("degree  us/eval  |dB| vs 13: RMS uT  max uT   (485 km / 97.5 deg, one day, 2026.0)")
    for deg, us, rms, mx in _measure():
        name = f"{deg:6d}" if deg else "dipole"
        print(f"{name}  {us:7.0f}  {rms:17.3f}  {mx:7.3f}")
