"""The field on board against independent evaluations: IGRF-14 truncated here vs ppigrf's own full
evaluation, the chosen degree vs degree 13 along a 485 km / 97.5° orbit, the interpolation between
knots vs direct evaluation, the dipole's cost."""
import datetime

import numpy as np
import ppigrf
import pytest

from fsw.estimation.field_motion import DipoleModel
from fsw.estimation.igrf import FLIGHT_DEGREE, IgrfModel, unix_to_decimal_year
from fsw.estimation.onboard_field import KNOT_STEP_S, OnboardOrbitField, affine_utc
from fsw.estimation.tle import parse_tle
from support import circular_tle

RNG = np.random.default_rng(11)


def ppigrf_ecef_T(r_ecef_m, when):
    """ppigrf's own degree-13 evaluation (geocentric r, θ, φ → its Br, Bθ, Bφ), in Earth-fixed axes."""
    r = np.linalg.norm(r_ecef_m, axis=-1)
    th = np.arccos(r_ecef_m[:, 2] / r)
    ph = np.arctan2(r_ecef_m[:, 1], r_ecef_m[:, 0])
    br, bt, bp = (x[0] for x in ppigrf.igrf_gc(r / 1e3, np.degrees(th), np.degrees(ph), when))
    return 1e-9 * np.stack((br * np.sin(th) * np.cos(ph) + bt * np.cos(th) * np.cos(ph) - bp * np.sin(ph),
                            br * np.sin(th) * np.sin(ph) + bt * np.cos(th) * np.sin(ph) + bp * np.cos(ph),
                            br * np.cos(th) - bt * np.sin(th)), axis=-1)


def random_points(n, r_min_m=6.6e6, r_max_m=7.4e6):
    u = RNG.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    return u * RNG.uniform(r_min_m, r_max_m, size=(n, 1))


@pytest.mark.parametrize("when", [datetime.datetime(y, m, 1) for y, m in ((2021, 7), (2025, 1), (2026, 1))])
def test_degree_13_is_ppigrfs_own_evaluation(when):
    year = unix_to_decimal_year(when.replace(tzinfo=datetime.timezone.utc).timestamp())
    r = random_points(200)
    got = IgrfModel(year, 13).b_ecef_T(r)
    want = ppigrf_ecef_T(r, when)
    # 0.5 nT: the coefficients are interpolated linearly in decimal years here, in days by ppigrf (a leap
    # day in a 5-year span: 0.001 yr × ~20 nT/yr of secular variation); at a model year they agree to 1e-10 nT
    assert np.max(np.linalg.norm(got - want, axis=1)) < 0.5e-9


def test_degree_1_is_the_dipole_of_the_same_coefficients():
    r = random_points(50)
    np.testing.assert_allclose(IgrfModel(2025.0, 1).b_ecef_T(r), DipoleModel(2025.0).b_ecef_T(r), atol=1e-12)


def along_the_orbit(hours=24.0, step_s=20.0):
    """(t, the orbit field at FLIGHT_DEGREE without interpolation, the same at degree 13, the dipole)."""
    l1, l2 = circular_tle(485.0, 97.5)
    tle = parse_tle(l1, l2)
    utc = affine_utc(0.0, tle.epoch_utc_s + 1800.0)
    t = np.arange(0.0, hours * 3600.0, step_s)
    fields = [OnboardOrbitField(tle.satrec(), utc, field=f)
              for f in (IgrfModel(2026.33, FLIGHT_DEGREE), IgrfModel(2026.33, 13), DipoleModel(2026.33))]
    return t, fields


def rms_uT(d):
    return float(np.sqrt(np.mean(np.sum(d ** 2, axis=-1)))) * 1e6


def test_flight_degree_against_degree_13_and_what_the_dipole_costs():
    t, (flight, full, dipole) = along_the_orbit()
    ref = full.direct_b_eci_T(t)
    assert rms_uT(flight.direct_b_eci_T(t) - ref) <= 0.2          # the target at the chosen degree
    assert 7.0 < rms_uT(dipole.direct_b_eci_T(t) - ref) < 10.0     # ~8.6 µT RMS: the dipole's cost


def test_interpolation_between_knots_against_direct_evaluation():
    t, (flight, _, _) = along_the_orbit(hours=12.0, step_s=7.3)
    d = np.linalg.norm(flight.b_eci_T(t) - flight.direct_b_eci_T(t), axis=-1) * 1e6
    assert d.max() <= 0.05
    assert flight.knots_evaluated <= 12 * 3600 / KNOT_STEP_S + 4   # one evaluation per knot, cached
    # on the knots themselves the interpolation is the evaluation
    k = np.arange(0, 100) * KNOT_STEP_S
    np.testing.assert_allclose(flight.b_eci_T(k), flight.direct_b_eci_T(k), atol=1e-15)


def test_a_full_table_of_knots_keeps_the_ones_asked_for():
    """A flight longer than the table (`max_knots` × `KNOT_STEP_S`, 5.7 days by default) goes on with the
    same field: when the table is full the knots not asked for are dropped, never the ones in use."""
    l1, l2 = circular_tle(485.0, 97.5)
    tle = parse_tle(l1, l2)
    utc = affine_utc(0.0, tle.epoch_utc_s + 1800.0)
    small = OnboardOrbitField(tle.satrec(), utc, field=IgrfModel(2026.33, FLIGHT_DEGREE), max_knots=16)
    large = OnboardOrbitField(tle.satrec(), utc, field=IgrfModel(2026.33, FLIGHT_DEGREE))
    t = np.arange(0.0, 40 * KNOT_STEP_S, 7.3)
    got = np.array([small.b_eci_T(x) for x in t])                   # one sample at a time, as a filter asks
    np.testing.assert_allclose(got, large.b_eci_T(t), rtol=0, atol=1e-15)
    assert len(small._knots) <= 16
    np.testing.assert_allclose(small.b_eci_T(t), large.b_eci_T(t), rtol=0, atol=1e-15)   # a span over the table


def test_a_time_asked_again_is_the_same_field_and_a_caller_cannot_change_it():
    """A filter bank asks for one sample's time once per member: the answer is the direct interpolation's
    (against the SGP4 and IGRF evaluation at the knots), whoever asked first or wrote into it."""
    t, (flight, _, _) = along_the_orbit(hours=1.0, step_s=60.0)
    first = flight.b_eci_T(1234.5)
    first[:] = 0.0                                                 # a caller scribbling on its copy
    again = flight.b_eci_T(1234.5)
    assert np.linalg.norm(again - flight.direct_b_eci_T(1234.5)) * 1e6 <= 0.05
    assert np.array_equal(again, flight.b_eci_T(np.array([1234.5]))[0])


def test_the_onboard_field_turns_like_the_field_and_has_the_estimators_interface():
    t, (flight, full, _) = along_the_orbit(hours=2.0, step_s=60.0)
    b = flight(t)
    assert b.shape == (t.size, 3) and flight(0.0).shape == (3,)
    w = flight.turn_rate_radps(t)
    assert np.all((w > 0) & (w < 4 * 2 * np.pi / 5660.0))  # of the order of twice the orbital rate
    assert 15e-6 < np.linalg.norm(b, axis=1).min() and np.linalg.norm(b, axis=1).max() < 60e-6


def test_outside_igrf14s_span_the_model_says_so():
    with pytest.raises(ValueError, match="outside IGRF-14"):
        IgrfModel(2031.0)
    with pytest.raises(ValueError, match="degree"):
        IgrfModel(2026.0, 14)
