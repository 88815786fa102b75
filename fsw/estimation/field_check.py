"""Is a recording's field the Earth's field in µT? The magnitude, against physics and the orbit's model.

Every rate and inertia estimator scales with the field it is given and none can tell the units: a
recording in nT gives the same rates as in µT with a noise estimated from it, but any fixed σ_B, the
sample gate's full scale and the field model's comparison are then off by 1000; a zero field gives
ω = 0 with σ = 0. So the tools check the median |B| before estimating.

Refused (:data:`PLAUSIBLE_UT`, 5–800 µT): the geomagnetic field is 22–67 µT at the surface and 18–65 µT
in LEO (the centred dipole falls as r⁻³: ×0.65 at 1000 km); the lab recordings in ../shared/data have
medians of 43.5–44.3 µT (1st–99th percentile 37–47, the disturbed one down to 17.5 with a magnet
near). Below 5 µT — a quarter of the weakest LEO field, room for an offset that cancels part of it —
is not a field in µT: tesla (2e-5–7e-5), gauss (0.2–0.7) or a dead sensor (0). Above 800 µT, the
MMC5983MA's full scale (±8 G per axis), the chip cannot have read it: nT (18 000–67 000).
Milligauss (180–670) cannot be told from a strong hard-iron offset by the magnitude alone: it is
warned about, outside :data:`NEAR_EARTH_UT` (10–100 µT, the Earth's field with a few tens of µT of
offset), and, when the orbit is known, when the median |B| differs from the field model's along the
orbit at the same times by more than :data:`MODEL_RATIO_MAX` (the dipole model is within ~25 % of
IGRF in magnitude; an offset adds to that).
"""
from __future__ import annotations

from typing import Callable

import numpy as np

#: Median |B| [µT] a magnetometer near the Earth can report; outside, the recording is refused.
PLAUSIBLE_UT = (5.0, 800.0)
#: Median |B| [µT] of the Earth's field from the ground to LEO with some offset; outside, a warning.
NEAR_EARTH_UT = (10.0, 100.0)
#: Measured / model median |B| (or its inverse) above which a warning is given.
MODEL_RATIO_MAX = 1.5
#: Samples of the model evaluated at most (spread over the record).
MODEL_SAMPLES = 2000


class FieldMagnitudeError(ValueError):
    """The field of a recording is not a magnetometer's reading of the Earth's field in µT."""


def median_uT(b_T: np.ndarray) -> float:
    """Median |B| of (N, 3) tesla samples, µT (NaN rows ignored; NaN when none)."""
    mag = np.linalg.norm(np.asarray(b_T, float).reshape(-1, 3), axis=1)
    mag = mag[np.isfinite(mag)]
    return float(np.median(mag)) * 1e6 if mag.size else float("nan")


def refusal(med_uT: float) -> str | None:
    """Why a recording with median |B| ``med_uT`` is refused (one line, with a hint), or None."""
    lo, hi = PLAUSIBLE_UT
    where = f"outside the {lo:g}–{hi:g} µT a magnetometer near the Earth reads (LEO 18–65 µT)"
    if not np.isfinite(med_uT):
        return "no finite field sample"
    if med_uT < 1e-6:
        return f"median |B| is {med_uT:.3g} µT, {where}: no field at all (a dead, disconnected or zeroed sensor?)"
    if med_uT < lo:
        return (f"median |B| is {med_uT:.3g} µT, {where}: the field columns look like tesla or gauss, not µT "
                "(in tesla? ×1e6; in gauss? ×100)")
    if med_uT > hi:
        return f"median |B| is {med_uT:.4g} µT, {where}: the field columns look like nT, not µT (in nT? ÷1000)"
    return None


def check(b_T: np.ndarray, source: str, *, t_s: np.ndarray | None = None,
          field: Callable[[np.ndarray], np.ndarray] | None = None) -> list[str]:
    """Check the field magnitude of a recording named ``source``: raise :class:`FieldMagnitudeError`
    (one line naming it, the median found, the range and a hint) when it cannot be µT; return the
    warnings (one line each): outside the Earth's range, or far from the model ``field`` (B_I(t) in
    tesla along the orbit, at the times ``t_s``)."""
    med = median_uT(b_T)
    why = refusal(med)
    if why:
        raise FieldMagnitudeError(f"{source}: {why}")
    out = []
    lo, hi = NEAR_EARTH_UT
    if med < lo:
        out.append(f"{source}: median |B| {med:.3g} µT is weaker than the Earth's field from the ground to LEO "
                   "(18–67 µT): an offset that cancels part of it, or the wrong scale?")
    elif med > hi:
        out.append(f"{source}: median |B| {med:.3g} µT is stronger than the Earth's field (18–67 µT): an "
                   "uncorrected hard-iron offset, a magnet near the sensor, or milligauss (÷10)?")
    if field is not None and t_s is not None and len(t_s):
        t = np.asarray(t_s, float)
        t = t[np.unique(np.linspace(0, len(t) - 1, min(len(t), MODEL_SAMPLES)).astype(int))]
        try:
            model = median_uT(np.asarray(field(t), float))
        except ValueError as e:
            return out + [f"{source}: the field model failed ({e}): |B| not compared with it"]
        ratio = med / model if model > 0 else float("inf")
        if not 1.0 / MODEL_RATIO_MAX <= ratio <= MODEL_RATIO_MAX:
            out.append(f"{source}: median |B| {med:.3g} µT is {ratio:.3g} × the field model's {model:.3g} µT "
                       "along the orbit at the same times: milligauss (÷10), an uncorrected offset, or the "
                       "wrong orbit or epoch?")
    return out


def check_recording(b_T: np.ndarray, source: str, t_s: np.ndarray, metadata: dict | None = None, *,
                    field: Callable[[np.ndarray], np.ndarray] | None = None) -> list[str]:
    """:func:`check` with the field model ``field``, else the one of the recording's orbit metadata
    (`onboard_field.field_from_metadata`); metadata that cannot be used is a warning, not an error."""
    notes = []
    if field is None and metadata:
        from .onboard_field import field_from_metadata
        try:
            field = field_from_metadata(metadata)
        except ValueError as e:
            notes.append(f"{source}: orbit metadata not usable ({e}): |B| not compared with a field model")
    return check(b_T, source, t_s=t_s, field=field) + notes
