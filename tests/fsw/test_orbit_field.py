"""Circular orbit, Earth rotation and the IGRF-14 dipole field along the orbit."""

from __future__ import annotations

import numpy as np
import pytest

from hil.field import (
    DipoleField,
    FieldAlongOrbit,
    MU0_NA2,
    FieldModel,
    b_eci_from_model_T,
    field_eci_T,
)
from hil.orbit import (
    A_WGS84_M,
    F_WGS84,
    MU_EARTH_M3S2,
    OMEGA_EARTH_RADPS,
    R_EARTH_M,
    CircularOrbit,
    earth_rotation_angle_rad,
    ecef_to_eci,
    eci_to_ecef,
    eci_to_ecef_matrix,
)

SIDEREAL_DAY_S = 86164.0905  # s, one Earth rotation relative to the stars
MU0 = MU0_NA2  # N/A²; whatever its value, it cancels between m = 4π a³ g/μ0 and the formula


def dipole_formula_T(m_Am2: np.ndarray, r_m: np.ndarray) -> np.ndarray:
    """Textbook point dipole B = (μ0/4π)(3 (m·r̂) r̂ − m)/r³, vectorised over r (..., 3)."""
    r = np.linalg.norm(r_m, axis=-1, keepdims=True)
    r_hat = r_m / r
    return MU0 / (4 * np.pi) * (3 * np.sum(m_Am2 * r_hat, axis=-1, keepdims=True) * r_hat - m_Am2) / r**3


def geodetic_lat_deg(geocentric_lat_deg: float) -> float:
    """Geodetic latitude of the WGS-84 surface point with the given geocentric latitude."""
    e2 = F_WGS84 * (2.0 - F_WGS84)
    return float(np.degrees(np.arctan(np.tan(np.radians(geocentric_lat_deg)) / (1.0 - e2))))


# --- orbit ---------------------------------------------------------------------------


def test_isoi_orbit_radius_period_and_speed() -> None:
    orbit = CircularOrbit(485e3, 97.5)
    r = A_WGS84_M + 485e3
    assert orbit.radius_m == r
    assert orbit.period_s == pytest.approx(2 * np.pi * np.sqrt(r**3 / MU_EARTH_M3S2), rel=1e-14)
    assert orbit.period_s / 60 == pytest.approx(94.307, abs=0.001)  # min
    t = np.linspace(0.0, 2 * orbit.period_s, 97)
    pos, vel = orbit.position_eci_m(t), orbit.velocity_eci_mps(t)
    np.testing.assert_allclose(np.linalg.norm(pos, axis=1), r, rtol=1e-14)
    np.testing.assert_allclose(np.linalg.norm(vel, axis=1), np.sqrt(MU_EARTH_M3S2 / r), rtol=1e-14)
    np.testing.assert_allclose(np.sum(pos * vel, axis=1), 0.0, rtol=0, atol=1e-6 * r * 7600)
    # back where it started after one period
    np.testing.assert_allclose(
        orbit.position_eci_m(orbit.period_s), orbit.position_eci_m(0.0), rtol=0, atol=1e-6
    )


def test_orbit_obeys_newtonian_gravity_by_finite_differences() -> None:
    orbit = CircularOrbit(600e3, 51.6, raan_deg=40.0, arg_lat0_deg=-30.0)
    h = 0.5
    for t in (0.0, 777.0, 4000.0):
        r_m, r_0, r_p = orbit.position_eci_m(np.array([t - h, t, t + h]))
        v_fd = (r_p - r_m) / (2 * h)
        a_fd = (r_p - 2 * r_0 + r_m) / h**2
        assert np.linalg.norm(v_fd - orbit.velocity_eci_mps(t)) < 1e-3  # m/s
        a_grav = -MU_EARTH_M3S2 * r_0 / np.linalg.norm(r_0) ** 3
        assert np.linalg.norm(a_fd - a_grav) < 1e-4 * np.linalg.norm(a_grav)  # m/s²


@pytest.mark.parametrize("incl_deg, raan_deg", [(97.5, 0.0), (51.6, 123.0), (10.0, -60.0), (180.0, 30.0)])
def test_orbit_elements_are_recovered_from_the_state(incl_deg: float, raan_deg: float) -> None:
    orbit = CircularOrbit(485e3, incl_deg, raan_deg=raan_deg)
    r0, v0 = orbit.position_eci_m(0.0), orbit.velocity_eci_mps(0.0)
    h_vec = np.cross(r0, v0)
    assert np.degrees(np.arccos(h_vec[2] / np.linalg.norm(h_vec))) == pytest.approx(incl_deg, abs=1e-9)
    if 0.0 < incl_deg < 180.0:
        node = np.cross([0.0, 0.0, 1.0], h_vec)
        assert np.degrees(np.arctan2(node[1], node[0])) == pytest.approx(raan_deg, abs=1e-9)
        # u0 = 0 is the ascending node: on the equator, moving north
        assert abs(r0[2]) < 1e-6 and v0[2] > 0.0
    # maximum latitude reached is the inclination (or its supplement)
    pos = orbit.position_eci_m(np.linspace(0.0, orbit.period_s, 3601))
    max_lat = np.degrees(np.max(np.arcsin(pos[:, 2] / orbit.radius_m)))
    assert max_lat == pytest.approx(min(incl_deg, 180.0 - incl_deg), abs=0.01)


def test_arg_lat0_places_the_satellite_along_the_orbit() -> None:
    base = CircularOrbit(485e3, 97.5, raan_deg=15.0)
    shifted = CircularOrbit(485e3, 97.5, raan_deg=15.0, arg_lat0_deg=90.0)
    np.testing.assert_allclose(
        shifted.position_eci_m(0.0), base.position_eci_m(base.period_s / 4), rtol=0, atol=1e-6
    )
    assert shifted.position_eci_m(0.0)[2] == pytest.approx(shifted.radius_m * np.sin(np.radians(97.5)))


def test_orbit_is_vectorised_over_time() -> None:
    orbit = CircularOrbit(485e3, 97.5, 10.0, 20.0)
    t = np.array([0.0, 100.0, 3000.0])
    np.testing.assert_array_equal(orbit.position_eci_m(t)[1], orbit.position_eci_m(100.0))
    np.testing.assert_array_equal(orbit.velocity_eci_mps(t)[2], orbit.velocity_eci_mps(3000.0))
    assert orbit.position_eci_m(5.0).shape == (3,)


def test_orbit_input_validation() -> None:
    with pytest.raises(ValueError, match="altitude"):
        CircularOrbit(-1.0, 97.5)
    with pytest.raises(ValueError, match="inclination"):
        CircularOrbit(485e3, 181.0)


# --- Earth rotation ----------------------------------------------------------------


def test_earth_turns_once_per_sidereal_day_eastward() -> None:
    era0 = 1.234
    assert earth_rotation_angle_rad(0.0, era0) == pytest.approx(era0)
    angle = earth_rotation_angle_rad(SIDEREAL_DAY_S, era0)
    assert np.angle(np.exp(1j * (angle - era0))) == pytest.approx(0.0, abs=1e-6)
    # a point fixed on the Earth (equator, Greenwich) moves east in ECI at ω_E × r
    p_ecef = np.array([A_WGS84_M, 0.0, 0.0])
    h, t = 1.0, 5000.0
    v_fd = (ecef_to_eci(p_ecef, t + h, era0) - ecef_to_eci(p_ecef, t - h, era0)) / (2 * h)
    expected = np.cross([0.0, 0.0, OMEGA_EARTH_RADPS], ecef_to_eci(p_ecef, t, era0))
    np.testing.assert_allclose(v_fd, expected, rtol=0, atol=1e-6)  # m/s
    assert np.linalg.norm(expected) == pytest.approx(465.1, abs=0.1)  # equatorial surface speed


def test_eci_ecef_round_trip_matrix_and_vectorisation() -> None:
    rng = np.random.default_rng(3)
    v = rng.normal(size=(5, 3)) * 7e6
    t = rng.uniform(0.0, 1e5, size=5)
    back = ecef_to_eci(eci_to_ecef(v, t, 0.3), t, 0.3)
    np.testing.assert_allclose(back, v, rtol=0, atol=1e-8)
    for k in range(5):
        np.testing.assert_allclose(
            eci_to_ecef(v, t, 0.3)[k], eci_to_ecef_matrix(t[k], 0.3) @ v[k], rtol=0, atol=1e-8
        )
        np.testing.assert_allclose(eci_to_ecef(v[k], t[k], 0.3), eci_to_ecef(v, t, 0.3)[k], rtol=0, atol=0)
    C = eci_to_ecef_matrix(1234.0, 0.1)
    np.testing.assert_allclose(C @ C.T, np.eye(3), rtol=0, atol=1e-15)
    assert np.linalg.det(C) == pytest.approx(1.0)
    # ECI x axis seen from ECEF after a quarter turn lies along −y (Earth turned east under it)
    quarter = (np.pi / 2) / OMEGA_EARTH_RADPS
    np.testing.assert_allclose(
        eci_to_ecef(np.array([1.0, 0.0, 0.0]), quarter), [0.0, -1.0, 0.0], rtol=0, atol=1e-12
    )


# --- IGRF-14 dipole ---------------------------------------------------------------------


def test_igrf14_degree1_coefficients_and_secular_variation() -> None:
    f = DipoleField()
    assert (f.g10_nT, f.g11_nT, f.h11_nT) == (-29350.0, -1410.3, 4545.5)
    f30 = DipoleField(2030.0)
    assert f30.g10_nT == pytest.approx(-29350.0 + 5 * 12.6)
    assert f30.g11_nT == pytest.approx(-1410.3 + 5 * 10.0)
    assert f30.h11_nT == pytest.approx(4545.5 - 5 * 21.5)
    f20 = DipoleField(2020.0)
    assert (f20.g10_nT, f20.g11_nT, f20.h11_nT) == pytest.approx((-29403.41, -1451.37, 4653.35))
    assert DipoleField(2022.5).g10_nT == pytest.approx((-29403.41 - 29350.0) / 2)
    for bad in (2019.9, 2030.1):
        with pytest.raises(ValueError, match="epoch_year"):
            DipoleField(bad)


@pytest.mark.parametrize(
    "epoch, lat_deg, lon_deg",
    [
        (2020.0, 80.65, -72.68),  # IGRF-13 paper (Alken et al. 2021, EPS 73:49), Table 4, WGS-84 geodetic
        (2025.0, 80.85, -72.76),  # IGRF-14 published north geomagnetic pole for 2025.0
    ],
)
def test_north_geomagnetic_pole_matches_published_position(
    epoch: float, lat_deg: float, lon_deg: float
) -> None:
    field = DipoleField(epoch)
    lat_gc, lon = field.north_geomagnetic_pole_deg()
    assert geodetic_lat_deg(lat_gc) == pytest.approx(lat_deg, abs=0.02)
    assert lon == pytest.approx(lon_deg, abs=0.02)
    # the pole is where the dipole field is vertical, pointing into the ground
    lat, lo = np.radians(lat_gc), np.radians(lon)
    r_hat = np.array([np.cos(lat) * np.cos(lo), np.cos(lat) * np.sin(lo), np.sin(lat)])
    b = field.b_ecef_T(R_EARTH_M * r_hat)
    np.testing.assert_allclose(b / np.linalg.norm(b), -r_hat, rtol=0, atol=1e-12)
    assert np.linalg.norm(b) == pytest.approx(2 * field.b0_T, rel=1e-12)


def test_dipole_moment_points_south_with_textbook_magnitude() -> None:
    field = DipoleField()
    m = field.dipole_moment_Am2
    assert m[2] < 0.0  # g10 < 0: the moment points into the southern hemisphere
    assert 7.6e22 < np.linalg.norm(m) < 7.8e22  # A·m², Earth's present dipole moment
    assert field.b0_T == pytest.approx(29733.4e-9, abs=0.1e-9)


def test_field_strength_on_dipole_equator_and_axis_at_reference_radius() -> None:
    field = DipoleField()
    m_hat = field.dipole_moment_Am2 / np.linalg.norm(field.dipole_moment_Am2)
    # orthonormal dipole frame (e1, e2, m̂)
    e1 = np.cross(m_hat, [0.0, 0.0, 1.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(m_hat, e1)
    for psi in np.linspace(0.0, 2 * np.pi, 9):
        r = R_EARTH_M * (np.cos(psi) * e1 + np.sin(psi) * e2)
        b = field.b_ecef_T(r)
        assert np.linalg.norm(b) == pytest.approx(field.b0_T, rel=1e-12)
        # horizontal, antiparallel to m
        np.testing.assert_allclose(b / field.b0_T, -m_hat, rtol=0, atol=1e-12)
    for sign in (+1.0, -1.0):
        b = field.b_ecef_T(sign * R_EARTH_M * m_hat)
        np.testing.assert_allclose(b, 2 * field.b0_T * m_hat, rtol=0, atol=1e-12 * field.b0_T)


def test_field_falls_off_as_inverse_cube() -> None:
    field = DipoleField()
    r = np.array([3.1e6, -5.2e6, 2.9e6])
    for factor in (0.5, 2.0, 7.3):
        np.testing.assert_allclose(field.b_ecef_T(factor * r), field.b_ecef_T(r) / factor**3, rtol=1e-12)


def test_spherical_harmonic_form_matches_point_dipole_formula() -> None:
    field = DipoleField(2027.3)
    rng = np.random.default_rng(5)
    directions = rng.normal(size=(12, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    points = directions * rng.uniform(R_EARTH_M, 4 * R_EARTH_M, size=(12, 1))
    points = np.vstack([points, [[0.0, 0.0, 7e6], [0.0, 0.0, -7e6], [7e6, 0.0, 0.0]]])  # poles, Greenwich
    expected = dipole_formula_T(field.dipole_moment_Am2, points)
    got = field.b_ecef_T(points)
    scale = np.linalg.norm(expected, axis=1, keepdims=True)
    np.testing.assert_allclose(got / scale, expected / scale, rtol=0, atol=1e-12)


def test_field_is_curl_and_divergence_free() -> None:
    field = DipoleField()
    rng = np.random.default_rng(9)
    h = 1.0e3  # m
    for _ in range(5):
        d = rng.normal(size=3)
        r0 = (A_WGS84_M + 485e3) * d / np.linalg.norm(d)
        grad = np.empty((3, 3))  # grad[i, j] = ∂B_i/∂x_j
        for j in range(3):
            e = np.zeros(3)
            e[j] = h
            grad[:, j] = (field.b_ecef_T(r0 + e) - field.b_ecef_T(r0 - e)) / (2 * h)
        scale = np.linalg.norm(field.b_ecef_T(r0)) / np.linalg.norm(r0)  # T/m
        assert abs(np.trace(grad)) < 1e-6 * scale
        assert np.max(np.abs(grad - grad.T)) < 1e-6 * scale


def test_eci_field_is_the_earth_fixed_dipole_turned_with_the_earth() -> None:
    field = DipoleField()
    era0 = 0.7
    r_eci = np.array([4.0e6, -3.0e6, 4.5e6])
    for t in (0.0, 3600.0, 40000.0):
        m_eci = ecef_to_eci(field.dipole_moment_Am2, t, era0)
        np.testing.assert_allclose(
            field.b_eci_T(r_eci, t, era0), dipole_formula_T(m_eci, r_eci), rtol=1e-12, atol=1e-18
        )
    # the same point sees the field change as the Earth turns under it
    assert np.linalg.norm(field.b_eci_T(r_eci, 0.0, era0) - field.b_eci_T(r_eci, 21600.0, era0)) > 1e-6


def test_field_along_isoi_orbit_is_within_dipole_bounds() -> None:
    field = DipoleField()
    orbit = CircularOrbit(485e3, 97.5)
    t = np.arange(0.0, 86400.0, 10.0)  # one day, vectorised
    b = field_eci_T(orbit, field, t, era0_rad=0.4)
    strength = np.linalg.norm(b, axis=1)
    assert 18e-6 < strength.min() and strength.max() < 52e-6
    b_eq = field.b0_T * (R_EARTH_M / orbit.radius_m) ** 3  # 23.79 µT at 485 km
    assert b_eq * (1 - 1e-12) <= strength.min() < 1.01 * b_eq
    assert 1.9 * b_eq < strength.max() <= 2 * b_eq * (1 + 1e-12)
    # consistent with the other entry points
    along = FieldAlongOrbit(orbit, field, era0_rad=0.4)
    np.testing.assert_array_equal(along.b_eci_T(t[123]), b[123])
    b_first = b_eci_from_model_T(field, orbit.position_eci_m(t[:7]), t[:7], 0.4)
    np.testing.assert_allclose(b_first, b[:7], rtol=0, atol=0)
    assert isinstance(field, FieldModel)


def test_field_direction_turns_about_twice_per_orbit() -> None:
    # physics-and-seeds §3: the field rotates at about twice the orbital rate in LEO
    field = DipoleField()
    orbit = CircularOrbit(485e3, 97.5)
    t = np.linspace(0.0, orbit.period_s, 2001)
    u = field_eci_T(orbit, field, t)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    turned_deg = np.degrees(np.sum(np.arccos(np.clip(np.sum(u[1:] * u[:-1], axis=1), -1.0, 1.0))))
    assert 650.0 < turned_deg < 790.0
    mean_rate_dps = turned_deg / orbit.period_s
    assert 0.1 < mean_rate_dps < 0.2
