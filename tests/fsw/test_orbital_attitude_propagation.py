"""The orbital-attitude filter's compiled propagation (`orbital_attitude._propagate`) against the same model
written with numpy (`transition`, `torque_body_Nm` and the midpoint rule), step by step."""
import math

import numpy as np
import pytest

from fsw.estimation import orbital_attitude as oa
from fsw.estimation.rotations import quat_exp, quat_mul, quat_to_dcm


def reference_predict(q, w, P, dt_s, u, model, tuning):
    J = model.J()
    Jinv = np.linalg.inv(J)
    n = max(1, int(math.ceil(dt_s / tuning.max_step_s)))
    h = dt_s / n
    qa, qb = tuning.accel_psd, tuning.bias_psd_T2_per_s * oa.UT_PER_T ** 2
    Q = np.zeros((9, 9))
    Q[:3, :3] = qa * h ** 3 / 3.0 * np.eye(3)
    Q[:3, 3:6] = Q[3:6, :3] = qa * h ** 2 / 2.0 * np.eye(3)
    Q[3:6, 3:6] = qa * h * np.eye(3)
    Q[6:, 6:] = qb * h * np.eye(3)

    def wdot(R, w):
        return Jinv @ (oa.torque_body_Nm(R, u, model, J) - np.cross(w, J @ w))

    for _ in range(n):
        R = quat_to_dcm(q)
        Phi = oa.transition(R, w, h, u, model, J, Jinv)
        P = Phi @ P @ Phi.T + Q
        k1 = wdot(R, w)
        wm = w + 0.5 * h * k1
        k2 = wdot(quat_to_dcm(quat_mul(q, quat_exp(0.5 * h * w))), wm)
        q = quat_mul(q, quat_exp(h * wm))
        q = q / np.linalg.norm(q)
        w = w + h * k2
    return q, w, 0.5 * (P + P.T)


@pytest.mark.parametrize("density", [1.454e-13, 0.0])
def test_compiled_propagation_is_the_numpy_model(density):
    rng = np.random.default_rng(7)
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    w = rng.normal(size=3) * 2e-3
    A = rng.normal(size=(9, 9))
    P = A @ A.T * 1e-4
    u = oa.Inputs(np.array([6.978e6, 1e5, 2e4]), np.array([-100.0, 7500.0, 1000.0]),
                  np.array([2e-5, -1e-5, 3e-5]), np.array([0.0, 15.0, -15.0]))
    model = oa.SpacecraftModel(inertia_kgm2=(18.0, 20.7, 15.3), density_kgm3=density)
    tuning = oa.OrbitalAttitudeTuning()
    for dt in (0.5, 1.0, 7.3):  # one step and several
        qc, wc, Pc = oa.predict(q, w, P, dt, u, model, tuning)
        qr, wr, Pr = reference_predict(q, w, P, dt, u, model, tuning)
        assert np.allclose(qc, qr, rtol=0, atol=1e-13)  # rad: float noise
        assert np.allclose(wc, wr, rtol=0, atol=1e-15)  # rad/s
        assert np.allclose(Pc, Pr, rtol=1e-11, atol=1e-16)
        assert not np.allclose(qc, q, atol=1e-9)  # it did move
