"""The compiled propagation with Euler's equations — the batch fit's (`ground.euler_trajectory.trajectory`,
through `ground.smoother.batch_fit._trajectory`) and the attitude filter's (`AttitudeRateKalman.propagate`,
fsw.estimation.euler_step) —
against the propagation on tuples of floats it was compiled from (estimation_reference.propagate) and the
filter's measurement, sample by sample: the trajectory, the transition matrices, the residuals and their
Jacobian."""
import math

import numpy as np
import pytest

import estimation_reference as reference_euler
from fsw.estimation import attitude_kalman as ak
from fsw.estimation import rate_kalman as rk
from fsw.estimation import field_motion as fm
from ground import smoother as sm
from ground.smoother import batch_fit as bf

FIELD = fm.OrbitField(fm.CircularOrbitModel(485e3, 97.5, 40.0, 10.0), fm.DipoleModel(2025.5))


def reference(kf: ak.AttitudeRateKalman, t, z_uT, sb_uT, n):
    """The filter's propagation sample by sample: (q, ω, Φ, r, Jr), as the batch fit computed them before."""
    q0, w0 = kf.q.copy(), kf.w.copy()
    nn = kf.n
    Q, W, r = np.zeros((n, 4)), np.zeros((n, 3)), np.zeros((n, 3))
    Phi, Jr = np.zeros((n, nn, nn)), np.zeros((n, 3, nn))
    F = np.eye(nn)
    kf.t_s = t[0]
    for k in range(n):
        if k:
            kf.q, kf.w, Fk = reference_euler.propagate(kf, t[k] - t[k - 1])
            F = Fk @ F
            kf.t_s = t[k]
        h, H = kf.measurement(t[k])
        Q[k], W[k], Phi[k] = kf.q, kf.w, F
        r[k] = (z_uT[k] - h) / sb_uT
        Jr[k] = -(H @ F) / sb_uT
    kf.q, kf.w, kf.t_s = q0, w0, t[0]
    return Q, W, Phi, r, Jr


def _filter(with_field: bool, tensor: bool, t):
    field = sm.tabulated(FIELD, t) if with_field else None
    J = np.array([[1.0, 0.05, -0.02], [0.05, 1.7, 0.03], [-0.02, 0.03, 2.4]]) if tensor else None
    kf = ak.AttitudeRateKalman(1e-6, field_eci_T=field, inertia_kgm2=J, estimate_inertia=J is None,
                               tuning=ak.AttitudeKalmanTuning(max_substep_rad=0.25, max_substeps=400))
    q = np.array([0.3, -0.5, 0.7, 0.4])
    kf.set_nominal(t[0], q / np.linalg.norm(q), np.radians([12.0, -25.0, 31.0]),
                   p=None if tensor else np.array([0.45, 0.9]), beta_uT=np.array([20.0, -31.0, 12.0]), euler=True)
    return kf


@pytest.mark.parametrize("with_field", [True, False])
@pytest.mark.parametrize("tensor", [False, True])
def test_compiled_trajectory_equals_the_filters_propagation(with_field, tensor):
    rng = np.random.default_rng(7)
    t = 100.0 + np.cumsum(rng.uniform(0.5, 3.0, 60))  # uneven steps, 1–6 substeps each at ~40 °/s
    kf = _filter(with_field, tensor, t)
    z = rng.normal(0.0, 30.0, (len(t), 3))
    sb = 0.7
    n = 50
    ref = reference(kf, t, z, sb, n)
    got = bf._trajectory(kf, t, z, sb, n)
    assert kf.n == 6 + (0 if tensor else 2) + (0 if with_field else 3)
    for name, a, b in zip(("q", "w", "Phi", "r", "Jr"), ref, (got.q, got.w, got.Phi, got.r, got.Jr)):
        assert a.shape == b.shape, name
        scale = max(1.0, float(np.max(np.abs(a))))
        assert np.max(np.abs(a - b)) <= 1e-11 * scale, name
    # residuals in µT/σ: 1e-11 of 30 µT / 0.7 is far below the noise (σ = 1)
    cheap = bf._trajectory(kf, t, z, sb, n, jacobian=False)
    assert np.array_equal(cheap.r, got.r) and np.array_equal(cheap.q, got.q)
    assert cheap.Phi.shape[0] == 0 and cheap.Jr.shape[0] == 0


@pytest.mark.parametrize("tensor", [False, True])
def test_the_filters_compiled_propagation_equals_the_reference(tensor):
    """AttitudeRateKalman.propagate (compiled) against the propagation on floats, with a torque for the known
    tensor (a magnetic moment in a field that turns)."""
    t = np.array([100.0, 101.3])
    kf = _filter(True, tensor, t)
    if tensor:
        kf.torque = lambda x: np.array([0.02 * math.sin(0.3 * x), -0.01, 0.015 * math.cos(0.2 * x)])
    q, w, F = reference_euler.propagate(kf, 1.3, kf.torque)
    F2 = kf.propagate(1.3)
    np.testing.assert_allclose(kf.q, q, rtol=0, atol=1e-13)
    np.testing.assert_allclose(kf.w, w, rtol=0, atol=1e-13)   # rad/s
    np.testing.assert_allclose(F2, F, rtol=0, atol=1e-12)
    if tensor:  # the torque took part: without it the rate is elsewhere
        fresh = _filter(True, tensor, t)
        kf.q, kf.w = fresh.q, fresh.w
        kf.torque = None
        kf.propagate(1.3)
        assert np.linalg.norm(kf.w - w) > 1e-6


def test_compiled_trajectory_refuses_a_non_finite_state():
    t = np.arange(10.0)
    kf = _filter(True, False, t)
    kf.w = np.array([np.inf, 0.0, 0.0])
    with pytest.raises(ValueError):
        bf._trajectory(kf, t, np.zeros((10, 3)), 1.0, 10)
    kf.w = np.zeros(3)
    for p in ([math.nan, 0.0], [-1000.0, 0.0], [0.0, 800.0]):  # a ratio NaN, 0 or inf: an LM trial's step
        kf.p = np.array(p)
        with pytest.raises(ValueError):
            bf._trajectory(kf, t, np.zeros((10, 3)), 1.0, 10)


def test_field_table_is_the_models_values():
    t = np.linspace(0.0, 500.0, 40)
    model = FIELD
    table = bf._field_at_samples(sm.tabulated(model, t), t, 30)
    direct = bf._field_at_samples(lambda s: model(s), t, 30)  # no table: the model at each time
    np.testing.assert_allclose(table, direct, rtol=1e-13, atol=0.0)
    assert np.max(np.abs(table)) > 10.0 and table.shape == (30, 3)  # µT
    assert rk.UT_PER_T == 1e6
