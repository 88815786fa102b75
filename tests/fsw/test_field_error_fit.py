"""The field model's error fitted with the tensor (fsw.estimation.euler_fit.field_error), against a rigid
body integrated by hil.dynamics whose field is the fit's model plus a smooth inertial offset: the fit
that takes its model as exact is confidently wrong, the one that fits the error covers the truth."""
import numpy as np
import pytest

from fsw.estimation import euler_fit as ef
from fsw.estimation import inertia as inr
from fsw.estimation.euler_fit import field_error as fe
from fsw.estimation.rotations import quat_to_dcm
from hil.dynamics import RigidBody
from hil.field import DipoleField, FieldAlongOrbit
from hil.orbit import CircularOrbit

FIELD = FieldAlongOrbit(CircularOrbit(600e3, 97.8, 30.0, 45.0), DipoleField(2025.5))
ASYM = np.array([[161.1, -27.0, -18.0], [-27.0, 207.6, -39.1], [-18.0, -39.1, 271.2]])
PULSE = (60.0, 120.0)
M_PULSE = np.array([0.0, 0.2, -0.1])
Q0 = np.array([0.9, 0.1, -0.3, 0.3]) / np.linalg.norm([0.9, 0.1, -0.3, 0.3])
T_S, SIGMA_T = 400.0, 0.2e-6
#: the true field's offset from the model: constant + linear over the record, inertial axes [T]
OFFSET_T = np.array([[1.5e-6, -1.0e-6, 0.8e-6], [-1.2e-6, 0.9e-6, 1.4e-6]])


def true_field(t):
    x = 2.0 * t / T_S - 1.0
    return FIELD.b_eci_T(t) + OFFSET_T[0] + OFFSET_T[1] * x


def record(seed=0):
    body = RigidBody(ASYM, Q0, np.radians([1.0, 0.6, -0.9]))
    rng = np.random.default_rng(seed)
    t, out_t, out_b, h = 0.0, [], [], 0.25
    while t < T_S - 1e-9:
        body.step(h, M_PULSE if PULSE[0] <= t + h / 2 < PULSE[1] else np.zeros(3))
        t += h
        if abs((t - 0.5) % 1.0) < 1e-9:
            out_t.append(t)
            out_b.append(quat_to_dcm(body.q).T @ true_field(t) + SIGMA_T * rng.standard_normal(3))
    return np.array(out_t), np.array(out_b)


@pytest.fixture(scope="module")
def fits():
    t, b = record()
    action = ef.KnownAction.pulses([(PULSE[0], PULSE[1] - PULSE[0], M_PULSE)])
    guess = np.array([150.0] * 3 + [0.0] * 3)
    exact = ef.identify(t, b[None], FIELD.b_eci_T, action, SIGMA_T, guess, ef.FitOptions())[0]
    fitted = ef.identify(t, b[None], FIELD.b_eci_T, action, SIGMA_T, guess,
                         ef.FitOptions(field_error_degree=1))[0]
    return t, exact, fitted


def z(fit):
    return (fit.p - inr.params(ASYM)) / np.sqrt(np.diag(fit.cov_p))


@pytest.mark.slow
def test_a_fit_that_takes_its_field_model_as_exact_is_confidently_wrong_one_that_fits_its_error_is_not(fits):
    _, exact, fitted = fits
    assert np.max(np.abs(z(exact))) > 4.0, z(exact)           # the white-noise intervals exclude the truth
    assert np.max(np.abs(z(fitted))) < 3.0, z(fitted)
    assert np.max(np.abs(fitted.p - inr.params(ASYM))) < np.max(np.abs(exact.p - inr.params(ASYM)))
    e = fitted.field_error
    assert e.degree == 1 and e.coef_T.shape == (2, 3) and e.drift_T.shape == (1, 3)
    # 6 coefficients of the inertial offset, 3 of the host's drift (soft iron not asked for)
    assert fitted.dof == exact.dof - 9 and fitted.chi2 < exact.chi2 and e.soft_iron is None
    assert 0.7 < fitted.s2 < 1.3
    assert 0.2e-6 < e.rms_T < 5e-6          # |B| shows an error (the fitted offset takes a part of it)


def test_degree_grows_with_the_record_and_the_basis_is_legendre():
    assert [fe.degree_for(s) for s in (300.0, 900.0, 1500.0, 3000.0, 6000.0)] == [1, 1, 2, 3, 5]
    t = np.linspace(10.0, 110.0, 5)
    np.testing.assert_allclose(fe.basis(t, 2), np.column_stack([np.ones(5), np.linspace(-1, 1, 5),
                                                                 0.5 * (3 * np.linspace(-1, 1, 5) ** 2 - 1)]))
    # ∂B_body/∂c: the inertial unit vectors seen in body axes, times the polynomial
    q = np.tile(Q0, (5, 1))
    cols = fe.columns(t, q, 1)
    R = quat_to_dcm(Q0)
    np.testing.assert_allclose(cols[1], np.outer(np.ones(5), R.T @ [0.0, 1.0, 0.0]))
    np.testing.assert_allclose(cols[3 + 2], np.outer(np.linspace(-1, 1, 5), R.T @ [0.0, 0.0, 1.0]))


def test_the_field_errors_rms_from_b_magnitude_does_not_depend_on_the_attitude():
    """|B| against the model's |B|: a smooth error of known RMS is found under white noise ten times its
    size, whatever the attitude; white noise alone gives (nearly) none."""
    rng = np.random.default_rng(4)
    t = np.arange(0.5, 3000.0, 1.0)
    b_model = np.column_stack([30e-6 + 5e-6 * np.sin(t / 900.0), 10e-6 * np.cos(t / 700.0), 15e-6 + 0 * t])
    err = 0.3e-6 * np.sqrt(2.0) * np.sin(2 * np.pi * t / 1400.0)          # RMS 0.3 µT along B
    u = b_model / np.linalg.norm(b_model, axis=1, keepdims=True)
    spin = np.radians(5.0) * t                                             # a tumble about z: |B| unchanged
    rot = np.array([[np.cos(spin), -np.sin(spin), 0 * t], [np.sin(spin), np.cos(spin), 0 * t],
                    [0 * t, 0 * t, 1 + 0 * t]]).transpose(2, 0, 1)
    truth = np.einsum("nij,nj->ni", rot, b_model + err[:, None] * u)
    noise = 1.5e-6 * rng.standard_normal(truth.shape)
    norm = np.linalg.norm(b_model, axis=1)
    assert fe.error_rms_T(t, truth + noise, norm) == pytest.approx(0.3e-6, rel=0.25)
    quiet = np.einsum("nij,nj->ni", rot, b_model) + noise
    assert fe.error_rms_T(t, quiet, norm) < 0.1e-6


def test_host_columns_are_a_drift_and_the_soft_iron_acting_on_the_field():
    t = np.linspace(0.0, 100.0, 5)
    b = np.column_stack([np.linspace(1, 2, 5), np.linspace(-1, 0, 5), np.full(5, 3.0)]) * 1e-5
    c = fe.body_columns(t, b, 2, 1e-6, soft_iron=True)
    assert c.shape == (3 * 2 + 9, 5, 3)
    np.testing.assert_allclose(c[0], np.outer(np.linspace(-1, 1, 5), [1.0, 0.0, 0.0]))   # P1, body x
    np.testing.assert_allclose(c[6 + 3 * 1 + 2][:, 1], b[:, 2] / 1e-6)                 # δS_yz · B_z → y
    np.testing.assert_allclose(np.delete(c[6 + 3 * 1 + 2], 1, axis=1), 0.0)
    assert fe.body_columns(t, b, 1, 1e-6, soft_iron=False).shape == (3, 5, 3)


def _ar1_record(rho, n=20000, seed=3):
    """Whitened residuals (n, 3) whose first axis is AR(1) with correlation `rho` per 1-s sample (unit
    variance), and the Jacobian (2, n, 3) of a constant and a slope on that axis."""
    rng = np.random.default_rng(seed)
    e = rng.standard_normal((n, 3))
    x = np.empty(n)
    x[0] = e[0, 0]
    for i in range(1, n):
        x[i] = rho * x[i - 1] + np.sqrt(1.0 - rho * rho) * e[i, 0]
    r = e.copy()
    r[:, 0] = x
    Ja = np.zeros((2, n, 3))
    Ja[0, :, 0] = 1.0
    Ja[1, :, 0] = np.linspace(-1.0, 1.0, n)
    return np.arange(n, dtype=float), Ja, r


@pytest.mark.parametrize("rho", [0.0, 0.8])
def test_the_robust_covariance_is_the_long_run_variance_of_correlated_residuals(rho):
    # the mean of an AR(1) series of unit variance has the variance (1 + ρ)/(1 − ρ)/n, not 1/n
    t, Ja, r = _ar1_record(rho)
    H = np.einsum("kna,lna->kl", Ja, Ja)
    Hinv = np.linalg.inv(H)
    cov = fe.robust_cov(Hinv.copy(), Hinv, Ja, r, t)
    factor = cov[0, 0] / Hinv[0, 0]
    expected = (1.0 + rho) / (1.0 - rho)
    assert factor >= 1.0                                    # never below the curvature
    assert abs(factor - expected) <= 0.35 * expected + (0.3 if rho == 0 else 0.0)
    assert cov[0, 1] / np.sqrt(cov[0, 0] * cov[1, 1]) == pytest.approx(
        Hinv[0, 1] / np.sqrt(Hinv[0, 0] * Hinv[1, 1]), abs=1e-12)   # the correlations stay the curvature's
