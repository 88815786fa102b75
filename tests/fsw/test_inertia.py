"""Linear inertia methods (fsw.estimation.inertia) against truth: Euler regressors, sedelnikov2023's
special case and its printed eq. 7, least squares / TLS / errors-in-variables, the torque-free null
space and the scale from an impulse, parallel axes, principal axes, checks, intervals."""
import json

import numpy as np
import pytest

from fsw.estimation import inertia as inr
from hil.dynamics import RigidBody, euler_rhs

AIST = np.diag([175.0, 200.0, 285.0])
ASYM = np.array([[161.1, -27.0, -18.0], [-27.0, 207.6, -39.1], [-18.0, -39.1, 271.2]])


def trajectory(J, omega0_dps, moment_fn, T=300.0, dt=1.0, h=0.05):
    """True ω and ω̇ (from Euler's equations) at 1 s samples of a rigid body, and the moment."""
    body = RigidBody(J, np.array([1.0, 0, 0, 0]), np.radians(omega0_dps))
    Jinv = np.linalg.inv(J)
    n = int(T / dt)
    w, wd, m = np.zeros((n, 3)), np.zeros((n, 3)), np.zeros((n, 3))
    t = 0.0
    for k in range(n):
        M = moment_fn(t)
        w[k], m[k] = body.omega_radps, M
        wd[k] = euler_rhs(J, Jinv, body.omega_radps, M)
        for _ in range(int(round(dt / h))):
            body.step(h, moment_fn(t))
            t += h
    return w, wd, m


def pulses(t):
    """0.2 N·m on x, then y, then z (the Aist-2D scenario's schedule, compressed)."""
    out = np.zeros(3)
    for i, t0 in enumerate((30.0, 110.0, 190.0)):
        if t0 <= t < t0 + 40.0:
            out[i] = 0.2
    return out


@pytest.fixture(scope="module")
def aist():
    return trajectory(AIST, [0.8, -0.5, 1.2], pulses)


@pytest.fixture(scope="module")
def asym():
    return trajectory(ASYM, [1.0, 0.6, -0.9], pulses)


def test_regressor_is_eulers_equations():
    rng = np.random.default_rng(0)
    for _ in range(20):
        A = rng.normal(size=(3, 3))
        J = A @ A.T + 3 * np.eye(3)
        w, wd = rng.normal(size=3), rng.normal(size=3)
        assert np.allclose(inr.euler_regressor(w, wd) @ inr.params(J), J @ wd + np.cross(w, J @ w), atol=1e-12)
    # the cellular paper's printed Φ, first row: [ω̇x, −ωyωz, ωyωz, ω̇y − ωxωz, ω̇z + ωxωy, ωy² − ωz²]
    w, wd = np.array([1.0, 2.0, 3.0]), np.array([0.1, 0.2, 0.3])
    assert np.allclose(inr.euler_regressor(w, wd)[0], [0.1, -6.0, 6.0, 0.2 - 3.0, 0.3 + 2.0, 4.0 - 9.0])
    assert np.allclose(inr.tensor(inr.params(ASYM)), ASYM)


def test_paper_special_case_per_sample_solve_is_exact(aist):
    """With a known moment (the paper assumes it dominates) each sample's 3×3 system gives the truth;
    torque-free samples have M = 0 and a singular system (the true tensor is its null vector)."""
    w, wd, m = aist
    I = inr.solve_diagonal_per_sample(w, wd, m)
    torque = np.linalg.norm(m, axis=1) > 0
    ok = np.all(np.isfinite(I), axis=1)
    assert ok[torque].mean() > 0.9 and ok[~torque].mean() < 0.1
    np.testing.assert_allclose(I[ok], np.tile([175.0, 200.0, 285.0], (ok.sum(), 1)), rtol=1e-6)


def test_printed_eq7_does_not_solve_eq5(aist):
    """sedelnikov2023 eq. 7 as printed disagrees with eq. 5 (physics-and-seeds §4): on exact rates it
    misses the truth by far more than rounding, where the linear solve of eq. 5 is exact."""
    w, wd, m = aist
    I7 = inr.diagonal_printed_eq7(w, wd, m)
    ok = np.all(np.isfinite(I7), axis=1) & (np.linalg.norm(m, axis=1) > 0)
    rel = np.abs(I7[ok] / np.array([175.0, 200.0, 285.0]) - 1)
    assert np.median(rel[:, 2]) > 0.05            # Izz, the line that carries the error
    assert np.mean(np.any(rel > 0.05, axis=1)) > 0.5
    # its x line is eq. 5's first equation solved for Ixx: exact when Iyy, Izz are right
    ixx = (m[:, 0] + w[:, 1] * w[:, 2] * (200.0 - 285.0)) / wd[:, 0]
    good = np.abs(wd[:, 0]) > 1e-5
    np.testing.assert_allclose(ixx[good], 175.0, rtol=1e-6)
    # and eq. 5 with eq. 7's numbers leaves a residual of the order of the moment itself
    A = inr.diagonal_regressor(w[ok], wd[ok])
    resid = np.einsum("nij,nj->ni", A, I7[ok]) - m[ok]
    assert np.median(np.linalg.norm(resid, axis=1)) > 1e-3


def test_least_squares_exact_diag_and_full(aist, asym):
    w, wd, m = aist
    d = inr.least_squares(w, wd, m, full=False)
    np.testing.assert_allclose(d.p[:3], [175.0, 200.0, 285.0], rtol=1e-8)
    assert not d.full and d.flags == inr.FLAG_POSITIVE_DEFINITE | inr.FLAG_TRIANGLE
    w, wd, m = asym
    f = inr.least_squares(w, wd, m, full=True)
    np.testing.assert_allclose(f.J, ASYM, atol=1e-6)
    assert f.flags == 7


def test_ols_is_biased_by_noisy_rates_tls_and_eiv_are_not(aist):
    """Errors in variables: noise in ω̇ (and ω) in the regressor shrinks the least-squares estimate;
    total least squares and the gradient-weighted fit remove most of it."""
    w, wd, m = aist
    rng = np.random.default_rng(7)
    sw, sa = np.radians(0.05), np.radians(0.005)
    ols, tls, eiv = [], [], []
    for _ in range(4):
        wn = w + sw * rng.standard_normal(w.shape)
        an = wd + sa * rng.standard_normal(w.shape)
        ols.append(inr.least_squares(wn, an, m, full=False).p[:3])
        tls.append(inr.total_least_squares(wn, an, m, full=False).p[:3])
        eiv.append(inr.errors_in_variables(wn, an, m, sigma_omega=sw, sigma_omega_dot=sa, full=False).p[:3])
    truth = np.array([175.0, 200.0, 285.0])
    bias = {k: np.mean(v, axis=0) / truth - 1 for k, v in (("ols", ols), ("tls", tls), ("eiv", eiv))}
    assert np.all(bias["ols"] < -0.02)               # shrunk by several per cent
    assert np.all(np.abs(bias["eiv"]) < 0.01)
    assert np.all(np.abs(bias["tls"]) < np.abs(bias["ols"]) / 3)


def test_tls_solve_recovers_exact_system():
    rng = np.random.default_rng(1)
    A = rng.normal(size=(50, 4))
    x = rng.normal(size=4)
    np.testing.assert_allclose(inr.tls_solve(A, A @ x), x, atol=1e-10)


def test_torque_free_null_space_and_kappa_from_impulse():
    w, wd, _ = trajectory(ASYM, [2.0, 1.5, -2.5], lambda t: np.zeros(3), T=200.0)
    p_n, s = inr.null_space_shape(w, wd)
    p_true = inr.params(ASYM)
    np.testing.assert_allclose(p_n, p_true / np.linalg.norm(p_true), atol=1e-8)
    assert s[0] < 1e-9 * s[1]                       # a clear gap: the shape is determined
    # a 1 s impulse (cellular paper: τ = 1 s) fixes the scale: rates just before and after it
    M = np.array([-3.0, 2.0, 4.0])
    w2, _, _ = trajectory(ASYM, [2.0, 1.5, -2.5], lambda t: M if 10.0 <= t < 11.0 else np.zeros(3), T=12.0,
                          h=0.01)
    kappa = inr.kappa_from_impulse(p_n, w2[10], w2[11], M, 1.0)
    assert kappa / np.linalg.norm(p_true) == pytest.approx(1.0, abs=0.015)   # the trapezoid rule's error
    # over an interval longer than the impulse (rates sampled around it)
    kappa = inr.kappa_from_impulse(p_n, w2[9], w2[11], M, 1.0, interval_s=2.0)
    assert kappa / np.linalg.norm(p_true) == pytest.approx(1.0, abs=0.03)


def test_parallel_axis_both_directions_and_the_papers_eq8():
    rng = np.random.default_rng(3)
    r = rng.normal(size=(40, 3))
    mass = rng.uniform(0.5, 2.0, 40)
    com = (mass[:, None] * r).sum(0) / mass.sum()

    def about(point):
        d = r - point
        return sum(mi * (di @ di * np.eye(3) - np.outer(di, di)) for mi, di in zip(mass, d))

    J_c = about(com)
    P = np.array([0.7, -0.2, 0.4])
    J_p = about(P)
    M = mass.sum()
    np.testing.assert_allclose(inr.tensor_about_point_from_com(J_c, M, P - com), J_p, atol=1e-9)
    np.testing.assert_allclose(inr.tensor_about_com_from_point(J_p, M, P - com), J_c, atol=1e-9)
    # eq. 8 adds m·a² to Iyy and Izz for an offset a along x: that is centre of mass → point
    a = 0.9
    eq8 = AIST + np.diag([0.0, 530.0 * a**2, 530.0 * a**2])
    np.testing.assert_allclose(inr.tensor_about_point_from_com(AIST, 530.0, [a, 0, 0]), eq8)
    assert not np.allclose(inr.tensor_about_com_from_point(AIST, 530.0, [a, 0, 0]), eq8)


def test_principal_axes_and_physical_checks():
    I, R = inr.principal_axes(ASYM)
    np.testing.assert_allclose(R @ np.diag(I) @ R.T, ASYM, atol=1e-9)
    assert np.linalg.det(R) == pytest.approx(1.0)
    np.testing.assert_allclose(I, [139.936, 209.982, 289.982], atol=0.01)
    assert inr.physical_checks(ASYM) | {"principal_kgm2": None} == {
        "principal_kgm2": None, "positive_definite": True, "triangle": True,
        "triangle_margin_kgm2": pytest.approx(I[0] + I[1] - I[2])}
    assert not inr.physical_checks(np.diag([1.0, 1.0, 3.0]))["triangle"]
    assert not inr.physical_checks(np.diag([1.0, -1.0, 3.0]))["positive_definite"]
    np.testing.assert_allclose(inr.principal_ratios(AIST), [175 / 285, 200 / 285])


def test_covariance_of_the_principal_ratios_is_their_spread():
    """First-order covariance of (I1/I3, I2/I3) against Monte-Carlo tensors drawn from N(p, C) (products of
    inertia included), and exact for a diagonal tensor with independent moments."""
    p = inr.params(ASYM)
    rng = np.random.default_rng(5)
    A = rng.standard_normal((6, 6))
    C = 0.04 * A @ A.T                                       # ~0.5 kg·m² on each component
    r, cov = inr.principal_ratios_cov(p, C)
    np.testing.assert_allclose(r, inr.principal_ratios(ASYM))
    draws = rng.multivariate_normal(p, C, size=20000)
    R = np.array([inr.principal_ratios(inr.tensor(x)) for x in draws])
    np.testing.assert_allclose(np.sqrt(np.diag(cov)), R.std(axis=0), rtol=0.03)
    assert cov[0, 1] / np.sqrt(cov[0, 0] * cov[1, 1]) == pytest.approx(np.corrcoef(R.T)[0, 1], abs=0.03)
    # diag(175, 200, 285), σ = 1, 2, 3 kg·m²: σ(I1/I3)² = (1/285)² + (175·3/285²)²
    _, c = inr.principal_ratios_cov(inr.params(AIST), np.diag([1.0, 4.0, 9.0, 0, 0, 0]))
    assert c[0, 0] == pytest.approx((1 / 285) ** 2 + (175 * 3 / 285 ** 2) ** 2)
    assert c[0, 1] == pytest.approx(175 * 200 * 9 / 285 ** 4)


def test_intervals_and_their_coverage_in_a_linear_regression():
    """β = 0.95 / 0.99 half-widths (z = 1.960 / 2.576); with noise only in the moment (classical
    regression) the least-squares 95 % intervals cover the truth in about 95 % of Monte-Carlo runs."""
    assert inr.z_value(0.95) == pytest.approx(1.959964, abs=1e-6)
    assert inr.z_value(0.99) == pytest.approx(2.575829, abs=1e-6)
    np.testing.assert_allclose(inr.half_width(np.diag([4.0, 9.0]), 0.95), [2 * 1.959964, 3 * 1.959964], rtol=1e-6)
    rng = np.random.default_rng(11)
    w = rng.normal(scale=0.05, size=(60, 3))
    wd = rng.normal(scale=0.002, size=(60, 3))
    m = inr.euler_moment(AIST, w, wd)
    hits95 = hits99 = 0
    runs = 300
    for _ in range(runs):
        est = inr.least_squares(w, wd, m + 0.01 * rng.standard_normal(m.shape), full=False)
        err = np.abs(est.p[:3] - [175.0, 200.0, 285.0])
        hits95 += np.sum(err <= est.ci95[:3])
        hits99 += np.sum(err <= est.ci99[:3])
    assert 0.92 <= hits95 / (3 * runs) <= 0.98
    assert 0.975 <= hits99 / (3 * runs) <= 1.0


def test_json_has_the_recording_format_fields():
    est = inr.InertiaEstimate(inr.params(ASYM), np.eye(6), "test", 123, True)
    doc = json.loads(json.dumps(est.to_json()))
    assert {"frame", "about", "I_kgm2", "ci95_kgm2", "principal_kgm2", "method", "samples_used"} <= set(doc)
    assert doc["frame"] == "sensor" and doc["about"] == "centre_of_mass"
    np.testing.assert_allclose(doc["I_kgm2"], ASYM)
    np.testing.assert_allclose(doc["ci95_kgm2"], np.full((3, 3), 1.959964), atol=1e-5)
    assert doc["samples_used"] == 123
