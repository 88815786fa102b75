"""The RTS smoother's compiled filter passes (`ground.rts_pass`) against the attitude filter's own updates
(`AttitudeRateKalman.update`, numpy), sample by sample: state, covariance, likelihood and the stored log;
a record with a gap and a non-finite sample takes the filter's own pass whole."""
import math

import numpy as np
import pytest

from fsw.estimation import attitude_kalman as ak
from fsw.estimation import field_motion as fm
from fsw.estimation import rotations as rot
from ground import rts_pass
from ground import smoother as sm

FIELD = fm.OrbitField(fm.CircularOrbitModel(485e3, 97.5, 40.0, 10.0), fm.DipoleModel(2025.5))


def record(n=90, dt=1.0, seed=3):
    """A torque-free tumble seen by a magnetometer (0.5 µT noise) along the orbit's field."""
    rng = np.random.default_rng(seed)
    t = 50.0 + dt * np.arange(n)
    J = np.array([1.0, 1.6, 2.3])
    q, w = np.array([1.0, 0.0, 0.0, 0.0]), np.radians([9.0, -14.0, 6.0])
    b = np.zeros((n, 3))
    for k in range(n):
        b[k] = rot.quat_to_dcm(q).T @ FIELD(t[k]) + rng.normal(0.0, 0.5e-6, 3)
        for _ in range(10):  # Euler + kinematics, small steps
            w = w + (dt / 10) * (-np.cross(w, J * w) / J)
            q = rot.quat_mul(q, rot.quat_exp(w * dt / 10))
    return t, b


def filt(with_field, tau, store, t):
    field = sm.tabulated(FIELD, t) if with_field else None
    tun = ak.AttitudeKalmanTuning(kappa=0.3, rate_accel_radps2=1e-3, adapt_max=1.0, rate_tau_s=tau)
    return ak.AttitudeRateKalman(0.6e-6, field_eci_T=field, tuning=tun, angle_about_b_rad=1.0, store=store)


def reference(kf, t, b, start):
    kf.start(t[0], b[0], **start)
    for k in range(1, len(t)):
        kf.update(t[k], b[k])
    return kf


def same_log(got, ref, rtol: float) -> None:
    """The two passes' logs (predicted and filtered states, covariances, transitions, NIS) equal."""
    for name in ("qp", "xp", "Pp", "F", "q", "x", "P", "nis"):
        a, c = np.array(got.log[name]), np.array(ref.log[name])
        assert a.shape == c.shape, name
        np.testing.assert_allclose(a, c, rtol=rtol, atol=1e-12, err_msg=name)


@pytest.mark.parametrize("with_field", [True, False])
@pytest.mark.parametrize("tau", [math.inf, 30.0])
def test_compiled_pass_equals_the_filters_updates(with_field, tau):
    t, b = record()
    ref = reference(filt(with_field, tau, True, t), t, b, {})
    got = rts_pass.forward(filt(with_field, tau, True, t), t, b, {})
    assert rts_pass.compiled(got)
    np.testing.assert_allclose(got.q, ref.q, rtol=0, atol=1e-12)
    np.testing.assert_allclose(got.w, ref.w, rtol=0, atol=1e-14)  # rad/s
    np.testing.assert_allclose(got.P, ref.P, rtol=1e-9, atol=1e-20)
    assert got.nll == pytest.approx(ref.nll, rel=1e-12, abs=1e-9)
    same_log(got, ref, rtol=1e-9)
    assert list(got.log["restart"]) == list(ref.log["restart"])
    np.testing.assert_array_equal(np.array(got.log["t"]), np.array(ref.log["t"]))


def test_pass_from_a_start_equals_the_filters():
    t, b = record(seed=5)
    back = reference(filt(True, math.inf, False, t), t, b, {})
    start = {"q": back.q, "omega_radps": back.w, "P": 10.0 * back.P}
    ref = reference(filt(True, math.inf, False, t), t, b, start)
    got = rts_pass.forward(filt(True, math.inf, False, t), t, b, start)
    np.testing.assert_allclose(got.w, ref.w, rtol=0, atol=1e-14)
    assert got.nll == pytest.approx(ref.nll, rel=1e-12, abs=1e-9)


def test_a_gap_and_a_missing_sample_take_the_filters_own_pass():
    t, b = record(n=60)
    t = t.copy()
    t[30:] += 100.0  # a gap beyond max_gap_s: the filter restarts
    b = b.copy()
    b[12] = np.nan  # a sample lost
    ref = reference(filt(True, math.inf, True, t), t, b, {})
    got = rts_pass.forward(filt(True, math.inf, True, t), t, b, {})
    assert ref.resets == 1 and got.resets == 1
    assert list(got.log["restart"]) == list(ref.log["restart"]) and sum(ref.log["restart"]) == 2
    np.testing.assert_array_equal(got.w, ref.w)
    assert got.nll == ref.nll


def test_rts_smooth_same_with_and_without_the_compiled_passes(monkeypatch):
    t, b = record(n=70, dt=2.0, seed=9)
    fast = sm.rts_smooth(t, b, 0.6e-6, field_eci_T=FIELD, accels_radps2=(1e-4, 1e-2), rate_taus_s=(math.inf, 30.0),
                         angles=3)
    monkeypatch.setattr(rts_pass, "compiled", lambda kf: False)
    slow = sm.rts_smooth(t, b, 0.6e-6, field_eci_T=FIELD, accels_radps2=(1e-4, 1e-2), rate_taus_s=(math.inf, 30.0),
                         angles=3)
    for k in ("kappa", "rate_accel_radps2", "sigma_factor", "rate_tau_s", "angle_about_b_rad"):
        assert fast.info[k] == slow.info[k], k
    np.testing.assert_allclose(fast.w_radps, slow.w_radps, rtol=0, atol=1e-12)  # rad/s
    np.testing.assert_allclose(fast.sigma_radps, slow.sigma_radps, rtol=1e-8)


@pytest.mark.parametrize("tensor", [False, True])
def test_euler_pass_equals_the_filters_updates(tensor):
    """The Euler RTS smoother's passes: Euler's equations from the start, the shape estimated or J known."""
    t, b = record(seed=11)
    J = np.diag([1.0, 1.6, 2.3]) if tensor else None

    def euler_filter():
        tun = ak.AttitudeKalmanTuning(rate_accel_radps2=1e-4, adapt_max=1.0, max_substep_rad=0.25, max_substeps=400)
        return ak.AttitudeRateKalman(0.6e-6, field_eci_T=sm.tabulated(FIELD, t), inertia_kgm2=J,
                                     estimate_inertia=J is None, store=True, tuning=tun)
    n = euler_filter().n
    P0 = np.zeros((n, n))
    P0[:3, :3] = 0.1 ** 2 * np.eye(3)
    P0[3:6, 3:6] = 0.05 ** 2 * np.eye(3)
    start = {"q": np.array([1.0, 0.0, 0.0, 0.0]), "omega_radps": np.radians([9.0, -14.0, 6.0]), "P": P0}
    if J is None:
        P0[6:8, 6:8] = 0.05 ** 2 * np.eye(2)
        start["p"] = np.log([1.55, 2.4])
    ref = reference(euler_filter(), t, b, start)
    got = rts_pass.forward(euler_filter(), t, b, start)
    assert rts_pass.compiled(got) and got.euler and ref.euler and ref.resets == 0
    np.testing.assert_allclose(got.w, ref.w, rtol=0, atol=1e-13)  # rad/s
    np.testing.assert_allclose(got.p, ref.p, rtol=0, atol=1e-12)
    np.testing.assert_allclose(got.P, ref.P, rtol=1e-8, atol=1e-20)
    assert got.nll == pytest.approx(ref.nll, rel=1e-12, abs=1e-9)
    same_log(got, ref, rtol=1e-8)


def rts_reference(log: dict, n_att: int = 3):
    """The RTS backward pass in numpy (as ground.smoother.rts computed it before it was compiled)."""
    q_f, x_f, P_f = np.array(log["q"]), np.array(log["x"]), np.array(log["P"])
    q_p, x_p, P_p, F = np.array(log["qp"]), np.array(log["xp"]), np.array(log["Pp"]), np.array(log["F"])
    restart = log["restart"]
    q_s, x_s, P_s = q_f.copy(), x_f.copy(), P_f.copy()
    for k in range(len(q_f) - 2, -1, -1):
        if restart[k + 1]:
            continue
        C = np.linalg.solve(P_p[k + 1], F[k + 1] @ P_f[k]).T
        d = np.concatenate([rot.quat_log(rot.quat_mul(rot.quat_conj(q_p[k + 1]), q_s[k + 1])),
                            x_s[k + 1] - x_p[k + 1]])
        dx = C @ d
        q_s[k] = rot.quat_mul(q_f[k], rot.quat_exp(dx[:n_att]))
        x_s[k] = x_f[k] + dx[n_att:]
        P_s[k] = P_f[k] + C @ (P_s[k + 1] - P_p[k + 1]) @ C.T
    return q_s, x_s, P_s


@pytest.mark.parametrize("gap", [False, True])
def test_compiled_backward_pass_equals_numpy(gap):
    t, b = record(n=60)
    if gap:
        t = t.copy()
        t[30:] += 100.0  # the filter restarts: the pass does not link the two stretches
    kf = reference(filt(False, math.inf, True, t), t, b, {})
    assert sum(kf.log["restart"]) == (2 if gap else 1)
    for a, c in zip(sm.rts(kf.log), rts_reference(kf.log)):
        np.testing.assert_allclose(a, c, rtol=1e-9, atol=1e-15)
