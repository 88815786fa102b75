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
    # the offset itself comes out (the sampled record spans t = 0.5 … 399.5 s, the offset's x is over 0 … T_S)
    e = fitted.field_error
    assert e.degree == 1 and e.coef_T.shape == (2, 3)
    x = 2.0 * np.array([0.5, T_S - 0.5]) / T_S - 1.0
    ends_true = OFFSET_T[0] + np.outer(x, OFFSET_T[1])
    ends_fit = e.coef_T[0] + np.outer([-1.0, 1.0], e.coef_T[1])
    np.testing.assert_allclose(ends_fit, ends_true, atol=4 * float(np.max(e.sigma_T)) + 0.1e-6)
    assert fitted.dof == exact.dof - 6 and fitted.chi2 < exact.chi2
    assert 0.7 < fitted.s2 < 1.3


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
