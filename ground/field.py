"""The field along a recording's orbit, for the ground's refinements: from a SITL scenario (its orbit and
field epoch, the scenario files being the simulated mission's description), from a TLE, or from the
recording's own metadata. The models are the box's (`fsw.estimation.field_motion` orbits, IGRF-14 at the
flight degree, `fsw.estimation.igrf`), so the ground refines with exactly what the box would compute.

`recording_field` is the tools' one choice: ``--scenario``, ``--tle``/``--utc0``, ``--utc0`` alone (the
recording's TLE at another t = 0), else the recording's metadata (``tle_line1``/``tle_line2`` with ``utc0``,
as `ground.decode` writes them, or a circular orbit), else none — the field's direction then assumed fixed
in inertial space, which on a low orbit it is not: it turns at about twice the orbital rate
(`LEO_FIELD_TURN_DPS`), and the tools widen their intervals for it."""
from __future__ import annotations

from datetime import datetime

import math

from fsw.estimation import field_motion as fm
from fsw.estimation.onboard_field import field_from_metadata, flight_field
from fsw.estimation.rate_formulas import LEO_FIELD_TURN_RADPS

#: how fast the field's direction turns in inertial space along a low orbit: about twice the orbital rate
#: (`fsw.estimation.rate_formulas.LEO_FIELD_TURN_RADPS`); what a recording without an orbit is allowed for
LEO_FIELD_TURN_DPS = math.degrees(LEO_FIELD_TURN_RADPS)


def scenario_field(name: str):
    """(field along the scenario's orbit, the scenario) for a shipped scenario name or a TOML file."""
    from hil import scenario as scenarios  # the scenario files: the one thing the ground reads of hil

    scn = scenarios.load(name)
    if scn.tle is not None:  # what the box was given: its TLE (possibly older than the truth's), t = 0 at utc0
        u = scn.utc0
        line1, line2 = scn.box_tle or scn.tle
        return tle_field(line1, line2, u), scn
    orbit = fm.CircularOrbitModel(scn.altitude_m, scn.inclination_deg, scn.raan_deg, scn.arg_lat0_deg)
    return flight_field(orbit, scn.epoch_year), scn


def tle_field(line1: str, line2: str, utc0: datetime) -> fm.OrbitField:
    """The field along a TLE's orbit, t = 0 at `utc0`; IGRF-14 at the flight degree of `utc0`'s year."""
    orbit = fm.TleOrbitModel(line1, line2, (utc0.year, utc0.month, utc0.day, utc0.hour, utc0.minute,
                                            utc0.second + utc0.microsecond * 1e-6))
    return flight_field(orbit, utc0.year + (utc0.timetuple().tm_yday - 1) / 365.25)


def recording_field(metadata: dict, *, scenario: str | None = None, tle: tuple[str, str] | None = None,
                    utc0: datetime | None = None) -> tuple[fm.OrbitField | None, str]:
    """(the field along the recording's orbit or None, a line saying which orbit was used): the command
    line's (`scenario`; `tle` with `utc0`; `utc0` alone with the recording's TLE) over the recording's
    metadata. ValueError when an orbit is given but cannot be used."""
    if scenario:
        f, scn = scenario_field(scenario)
        return f, f"orbit of scenario {scn.name} (--scenario; t = 0 at its utc0)"
    if tle:
        return tle_field(tle[0], tle[1], utc0), f"TLE {tle[0][2:7].strip()} of --tle, t = 0 at {utc0.isoformat()}"
    md = dict(metadata)
    if utc0 is not None:
        if not (md.get("tle_line1") and md.get("tle_line2")):
            raise ValueError("--utc0 without --tle needs the recording's TLE (tle_line1, tle_line2 in its metadata)")
        md["utc0"] = utc0.isoformat()
    f = field_from_metadata(md)
    if f is None:
        return None, ("no orbit (none given, none in the recording's metadata): the field's direction assumed "
                      "fixed in inertial space")
    if md.get("tle_line1"):
        src = "--utc0" if utc0 is not None else "the recording's metadata"
        return f, f"TLE {md['tle_line1'][2:7].strip()} from the recording's metadata, t = 0 at {md['utc0']} ({src})"
    return f, "circular orbit from the recording's metadata"
