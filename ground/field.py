"""The field along a recording's orbit, for the ground's refinements: from a SITL scenario (its orbit and
field epoch, the scenario files being the simulated mission's description), from a TLE, or from the
recording's own metadata. The models are the box's (`fsw.estimation.field_motion` orbits, IGRF-14 at the
flight degree, `fsw.estimation.igrf`), so the ground refines with exactly what the box would compute."""
from __future__ import annotations

from datetime import datetime

from fsw.estimation import field_motion as fm
from fsw.estimation.onboard_field import flight_field


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
