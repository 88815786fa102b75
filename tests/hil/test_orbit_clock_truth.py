"""Orbit truth from a TLE (SGP4, TEME, GMST) and the box's clock against true time."""
import dataclasses
from datetime import datetime

import numpy as np
import pytest
from sgp4.api import Satrec, jday

from hil import scenario
from hil.box_clock import BoxClock
from hil.field import IgrfField, b_eci_from_model_T
from hil.orbit import TleOrbit
from hil.sim import Simulator
from hil.sitl import SitlConfig, build

# Vallado, Crawford, Hujsak, Kelso, "Revisiting Spacetrack Report #3" (AIAA 2006-6753), test case 00005
# (the sgp4 package's own verification set): TEME position at tsince = 0
VALLADO_00005 = ("1 00005U 58002B   00179.78495062  .00000023  00000-0  28098-4 0  4753",
                 "2 00005  34.2682 348.7242 1859667 331.7664  19.3264 10.82419157413667")
VALLADO_00005_R0_KM = (7022.46529266, -1400.08296755, 0.03995155)


def test_tle_orbit_is_sgp4_in_teme():
    sat = Satrec.twoline2rv(*VALLADO_00005)
    # utc0 = the TLE's epoch: 2000 day 179.78495062
    epoch = datetime(2000, 6, 27, 18, 50, 19, 733568)
    orbit = TleOrbit(*VALLADO_00005, epoch)
    np.testing.assert_allclose(orbit.position_eci_m(0.0) / 1e3, VALLADO_00005_R0_KM, atol=1e-3)
    assert orbit.epoch_age_s == pytest.approx(0.0, abs=1e-3)
    jd, fr = jday(2000, 6, 27, 18, 50, 19.733568)
    e, r, v = sat.sgp4(jd, fr + 3600.0 / 86400.0)
    np.testing.assert_allclose(orbit.position_eci_m(3600.0), np.array(r) * 1e3, atol=1e-3)
    np.testing.assert_allclose(orbit.velocity_eci_mps(3600.0), np.array(v) * 1e3, atol=1e-6)
    assert orbit.position_eci_m(np.arange(3.0)).shape == (3, 3)


def test_gmst_at_utc0():
    # GMST at 2000-01-01 12:00 UT1 (J2000.0) is 280.46061837 deg (IAU 1982, Vallado eq. 3-47)
    orbit = TleOrbit(*VALLADO_00005, datetime(2000, 1, 1, 12, 0, 0))
    assert np.degrees(orbit.era0_rad) == pytest.approx(280.46061837, abs=1e-6)


def test_sgp4_scenario_flies_the_tle_and_turns_the_field_with_gmst():
    scn = scenario.load("isoi_sgp4")
    assert scn.tle is not None and scn.utc0 == datetime(2025, 7, 1, 12, 0, 0)
    sim = Simulator(scn)
    assert isinstance(sim.orbit, TleOrbit) and isinstance(sim.field, IgrfField)
    assert sim.box_tle == scn.box_tle != scn.tle          # the box's knowledge is the older TLE
    r = sim.orbit.position_eci_m(0.0)
    t_orbit = np.linspace(0.0, sim.orbit.period_s, 200, endpoint=False)
    mean_alt = np.mean(np.linalg.norm(sim.orbit.position_eci_m(t_orbit), axis=1)) - 6378137.0
    assert mean_alt == pytest.approx(485e3, abs=10e3)       # the TLE was made for 485 km
    # the field at t is the Earth-fixed model at r rotated by GMST(utc0) + ω t
    t = 600.0
    want = b_eci_from_model_T(sim.field, sim.orbit.position_eci_m(t), t, sim.orbit.era0_rad)
    np.testing.assert_allclose(sim.b_eci_T(t), want, rtol=0, atol=0.1e-9)
    # the older TLE propagated to utc0 is km off the truth (what a stale TLE costs)
    box = TleOrbit(*scn.box_tle, scn.utc0)
    assert box.epoch_age_s == pytest.approx(3 * 86400.0)
    assert 1e3 < np.linalg.norm(box.position_eci_m(0.0) - r) < 50e3


@pytest.mark.parametrize("edit,message", [
    (("00000-0  10000-3 0    05", "00000-0  10000-3 0    06"), "checksum"),
    (('utc0 = 2025-07-01T12:00:00Z\n', ""), "utc0"),
    (("utc0 = 2025-07-01T12:00:00Z", 'utc0 = "2025-07-01"'), "date-time"),
    (('tle = ["1 99991', 'tle = ["3 99991'), "line 1"),
])
def test_bad_tle_keys_are_refused(tmp_path, edit, message):
    text = (scenario.SCENARIO_DIR / "isoi_sgp4.toml").read_text()
    assert edit[0] in text
    p = tmp_path / "bad.toml"
    p.write_text(text.replace(edit[0], edit[1]))
    with pytest.raises(scenario.ScenarioError, match=message):
        scenario.load(str(p))


def test_box_clock_maps_both_ways():
    c = BoxClock(offset_s=2.0, drift_ppm=20.0)
    assert c.box_s(0.0) == 2.0
    assert c.box_s(1e4) == pytest.approx(2.0 + 1e4 * (1 + 20e-6))   # 0.2 s gained in 10,000 s
    assert c.true_s(c.box_s(1234.5)) == pytest.approx(1234.5, abs=1e-9)
    with pytest.raises(ValueError):
        BoxClock(drift_ppm=5000.0)
    with pytest.raises(ValueError):
        BoxClock(offset_s=float("nan"))


def test_sitl_flight_software_sees_the_box_clock():
    """The loop's time is the box's: the simulator is advanced to the true time it means, and the truth
    handed to the flight software is looked up at the true time of the box's time stamp."""
    scn = dataclasses.replace(scenario.load("isoi"), clock=BoxClock(offset_s=2.0, drift_ppm=50.0))
    s = build(SitlConfig(scenario=scn), ident=False)
    try:
        assert s.t0_s == 2.0
        box_t = 2.0 + 10.0 * (1 + 50e-6)      # the box's clock after 10 true seconds
        s.advance(box_t)
        assert s.sim.t_s == pytest.approx(10.0, abs=1e-9)
        assert s.truth(box_t).t_s == pytest.approx(10.0, abs=1e-9)
        assert s.truth(2.0 + 5.0 * (1 + 50e-6)).t_s == pytest.approx(5.0, abs=1e-9)
        assert "box clock: offset 2 s, drift 50 ppm" in s.header()
    finally:
        s.flight.close()


def test_a_box_clock_off_and_drifting_does_not_change_what_is_scored():
    """The same world with the box's clock 2 s behind and 50 ppm fast: the loop runs on the box's time,
    the simulator on true time, and the rate errors against the truth are those of the true clock (the
    scoring looks the truth up at the true time of each sample's box time stamp)."""
    from io import StringIO

    from fsw.config import RunConfig
    from hil.sitl import run
    from support import flight_assumptions

    errs = []
    for clock in (BoxClock(), BoxClock(offset_s=-2.0, drift_ppm=50.0)):
        scn = dataclasses.replace(flight_assumptions("isoi"), clock=clock)
        r = run(SitlConfig(run=RunConfig(speed=0.0, duration_s=30.0, quiet=True, link="udpout:127.0.0.1:9"),
                           scenario=scn), out=StringIO())
        assert r.sitl.sim.t_s == pytest.approx(clock.true_s(r.loop.t_s), abs=1e-9)
        errs.append(np.degrees(r.score.rms_max(r.score.boer_err)[0]))
    assert errs[0] < 1.2
    assert errs[1] == pytest.approx(errs[0], abs=0.05)   # °/s
