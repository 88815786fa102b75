"""The onboard filter's compiled step against the textbook numpy forms (estimation_reference) with
F, Q and H built independently from the model's definition."""
import math

import numpy as np
import pytest

import estimation_reference as reference
from fsw.estimation import rate_kf
from fsw.estimation import rotations as rot


def spd(rng, n):
    A = rng.normal(size=(n, n))
    return A @ A.T + n * np.eye(n)


@pytest.mark.parametrize("seed,dt,phi", [(0, 0.01, 1.0), (1, 1.0, 1.0), (2, 3.0, 0.9), (3, 1e-4, 1.0)])
def test_predict_is_F_P_Ft_plus_Q(seed, dt, phi):
    rng = np.random.default_rng(seed)
    x = np.concatenate([rng.normal(scale=30.0, size=3), rng.normal(scale=0.3, size=3)])
    P = spd(rng, 6) * 1e-3
    q_w, q_b = 1e-6, 1e-4
    # independent truth: F = [[E, G], [0, ϕI]], Q from its blocks
    w = x[3:]
    E = rot.so3_exp(-w * dt)
    b_next = E @ x[:3]
    G = dt * rot.skew(b_next) @ rot.so3_right_jacobian(w * dt)
    F = np.block([[E, G], [np.zeros((3, 3)), phi * np.eye(3)]])
    Bx = rot.skew(b_next)
    Q = np.block([[q_w * dt**2 / 3 * Bx @ Bx.T + q_b * np.eye(3), q_w * dt / 2 * Bx],
                  [q_w * dt / 2 * Bx.T, q_w * np.eye(3)]])
    x_ref, P_ref = reference.predict(x, P, F, Q, fx=np.concatenate([b_next, phi * w]))
    work = np.zeros((6, 6)), np.zeros((6, 6))
    rate_kf.predict(x, P, dt, q_w, q_b, phi, *work)
    np.testing.assert_allclose(x, x_ref, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(P, P_ref, rtol=1e-10, atol=1e-13)
    np.testing.assert_array_equal(P, P.T)


def test_update_matches_the_joseph_form():
    rng = np.random.default_rng(5)
    x = np.concatenate([rng.normal(scale=30.0, size=3), rng.normal(scale=0.3, size=3)])
    P = spd(rng, 6) * 1e-2
    z = x[:3] + rng.normal(scale=0.1, size=3)
    r = 0.05 ** 2
    H = np.hstack([np.eye(3), np.zeros((3, 3))])
    x_ref, P_ref, y, S = reference.update(x, P, z, H, r * np.eye(3))
    nis_ref = float(y @ np.linalg.solve(S, y))
    K, T = np.zeros((6, 3)), np.zeros((6, 6))
    nis = rate_kf.update(x, P, z, r, K, T)
    np.testing.assert_allclose(x, x_ref, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(P, P_ref, rtol=1e-8, atol=1e-12)
    assert nis == pytest.approx(nis_ref, rel=1e-10)
    np.testing.assert_array_equal(P, P.T)


@pytest.mark.parametrize("th", [0.0, 1e-4, 0.5, 3.0])
def test_jr_coefficients(th):
    a, c = rot.jr_coefficients(th * th)
    if th > 1e-3:
        assert a == pytest.approx((1 - math.cos(th)) / th**2, rel=1e-12)
        assert c == pytest.approx((th - math.sin(th)) / th**3, rel=1e-12)
    else:
        assert a == pytest.approx(0.5, abs=1e-8) and c == pytest.approx(1 / 6, abs=1e-8)
