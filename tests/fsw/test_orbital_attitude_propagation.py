"""The orbital-attitude filter's compiled propagation (`orbital_attitude._propagate`) against the same model
written with numpy (`transition`, `torque_body_Nm` and the midpoint rule, here), step by step."""
import math

import numpy as np
import pytest

from fsw.estimation import orbital_attitude as oa
from fsw.estimation.field_motion import MU_EARTH_M3S2
from fsw.estimation.rotations import quat_exp, quat_mul, quat_to_dcm, skew, so3_exp


def torque_body_Nm(R_bi: np.ndarray, u: oa.Inputs, model: oa.SpacecraftModel, J: np.ndarray) -> np.ndarray:
    """Gravity gradient + the sail's aerodynamic moment + the kit's p × B, body axes, at attitude R_bi."""
    r_b = R_bi.T @ u.r_eci_m
    r = math.sqrt(float(r_b @ r_b))
    rh = r_b / r
    m = (3.0 * MU_EARTH_M3S2 / r ** 3) * np.cross(rh, J @ rh)
    v_b = R_bi.T @ u.v_eci_mps
    speed = math.sqrt(float(v_b @ v_b))
    if speed > 0.0 and model.density_kgm3 > 0.0:
        vh = v_b / speed
        area = model.sail_area_m2 * abs(float(np.dot(model.sail_normal_body, vh))) + model.body_area_m2
        force = -0.5 * model.density_at_kgm3(r) * speed * speed * model.drag_coefficient * area * vh
        m = m + np.cross(np.asarray(model.cp_offset_m, float), force)
    return m + np.cross(u.dipole_body_Am2, R_bi.T @ u.b_eci_T)


def transition(R_bi: np.ndarray, w: np.ndarray, h: float, u: oa.Inputs, model: oa.SpacecraftModel, J: np.ndarray,
               Jinv: np.ndarray) -> np.ndarray:
    """Φ (9×9) of the error (δθ, δω, δβ) over `h`: I + Fh + (Fh)²/2 with F_θθ = −[ω]ₓ, F_θω = I,
    F_ωω = J⁻¹([Jω]ₓ − [ω]ₓJ), F_ωθ = J⁻¹ ∂M/∂δθ (central differences: gravity gradient, sail, p × B)."""
    F = np.zeros((9, 9))
    F[:3, :3] = -skew(w)
    F[:3, 3:6] = np.eye(3)
    F[3:6, 3:6] = Jinv @ (skew(J @ w) - skew(w) @ J)
    eps = 1e-4
    for i in range(3):
        d = np.zeros(3)
        d[i] = eps
        mp = torque_body_Nm(R_bi @ so3_exp(d), u, model, J)
        mm = torque_body_Nm(R_bi @ so3_exp(-d), u, model, J)
        F[3:6, i] = Jinv @ (mp - mm) / (2.0 * eps)
    Fh = F * h
    return np.eye(9) + Fh + 0.5 * Fh @ Fh


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
        return Jinv @ (torque_body_Nm(R, u, model, J) - np.cross(w, J @ w))

    for _ in range(n):
        R = quat_to_dcm(q)
        Phi = transition(R, w, h, u, model, J, Jinv)
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
