"""The ground smoothers' 1-σ and the information limit of the benchmark: the innovations' variance of
unit weight against the χ² law, the Euler RTS smoother carrying the fitted shape's uncertainty, the
posterior Cramér–Rao bound's scaling laws, and the coverage's own spread over runs."""
import math

import numpy as np
import pytest

from fsw.estimation import attitude_kalman as ak
from fsw.estimation import field_motion as fm
from fsw.estimation import rotations as rot
from ground import smoother as sm
from bench import accuracy as acc
from hil import dynamics

FIELD = fm.OrbitField(fm.CircularOrbitModel(485e3, 97.5, 40.0, 10.0), fm.DipoleModel(2025.5))
ASYM = np.diag([175.0, 200.0, 285.0])


def tumble(J, w0_dps, dt_s, n, noise_T, seed):
    rng = np.random.default_rng(seed)
    body = dynamics.RigidBody(J, rot.quat_normalize(rng.normal(size=4)), np.radians(w0_dps))
    t = np.arange(n) * dt_s
    b, w, q = np.zeros((n, 3)), np.zeros((n, 3)), np.zeros((n, 4))
    for k in range(n):
        if k:
            for _ in range(int(round(dt_s / 0.05))):
                body.step(0.05, np.zeros(3))
        b[k] = rot.quat_to_dcm(body.q).T @ FIELD.b_eci_T(t[k])
        w[k], q[k] = body.omega_radps, body.q
    return t, b + rng.normal(scale=noise_T, size=b.shape), w, q


def test_variance_scale_skips_the_prior_and_never_shrinks():
    nis = [30.0] * 5 + [6.0] * 20 + [30.0] * 3 + [6.0] * 20
    restart = [True] + [False] * 24 + [True] + [False] * 22
    # after each (re)start the first 5 samples are the prior's; the rest have NIS 6 → ĉ = 2
    assert sm.variance_scale({"nis": nis, "restart": restart}, skip=5) == pytest.approx(2.0)
    assert sm.variance_scale({"nis": [1.0] * 40, "restart": [True] + [False] * 39}) == 1.0
    assert sm.variance_scale({"nis": [], "restart": []}) == 1.0


@pytest.mark.parametrize("factor, lo, hi", [(1.0, 0.0, 1.3), (2.0, 2.8, 5.5)])
def test_variance_scale_is_the_noise_ratio_squared(factor, lo, hi):
    """A spherical body (ω constant, the random walk exact): NIS ~ χ²₃ when the filter is told the true
    σ_B (scale ≈ 1); told σ_B / 2 the innovations are twice too large and the scale ≈ 4 (the random
    walk absorbs a little of it)."""
    t, b, w, q = tumble(np.eye(3), [5.0, -4.0, 6.0], 1.0, 150, 1.0e-6, 8)
    kf = ak.AttitudeRateKalman(1.0e-6 / factor, field_eci_T=FIELD, store=True,
                               tuning=ak.AttitudeKalmanTuning(kappa=0.03, rate_accel_radps2=1e-4, adapt_max=1.0))
    # started near the truth (the linear regime the χ² law is about)
    kf.start(t[0], b[0], q=q[0], omega_radps=w[0], P=np.diag([1e-4] * 3 + [1e-6] * 3))
    for k in range(1, len(t)):
        kf.update(t[k], b[k])
    assert len(kf.log["nis"]) == len(t)
    c = sm.variance_scale(kf.log, skip=30)
    assert lo <= c <= hi


def test_euler_rts_carries_the_fitted_shape_and_its_uncertainty():
    """Started from a fit with the true shape (and a covariance for it), the Euler RTS smoother keeps the
    shape as states: it returns the shape, its σ grows with the shape's uncertainty, and it tracks ω."""
    t, b, w, q = tumble(ASYM, [8.0, -6.0, 7.0], 2.0, 40, 0.5e-6, 5)
    shape = np.diag(ASYM) / ASYM[0, 0]
    out = []
    for sig_p in (1e-4, 0.1):
        cov = np.zeros((8, 8))
        cov[6:8, 6:8] = sig_p ** 2 * np.eye(2)
        init = sm.Smoothed(t, w, np.zeros_like(w), q, "truth", inertia_shape=shape, info={"cov_x0": cov})
        out.append(sm.euler_rts_smooth(t, b, 0.5e-6, field_eci_T=FIELD, init=init, accels_radps2=(1e-5,)))
    tight, loose = out
    for res in out:
        assert res.inertia_shape is not None and len(res.inertia_shape) == 3
        np.testing.assert_allclose(res.inertia_shape, shape, rtol=0.05)
        assert math.degrees(float(np.sqrt(np.mean(np.sum((res.w_radps - w) ** 2, axis=1))))) < 0.2
        assert res.info["variance_scale"] >= 1.0
    assert np.mean(loose.sigma_radps) > 1.01 * np.mean(tight.sigma_radps)  # the record fixes most of it


def _orbital_run(sigma_T, seed=3):
    return acc.simulate("orbital", "asymmetric", 1.0, sigma_T, np.random.default_rng(seed),
                        record_samples=60, warmup_s=0.0)


def test_information_limit_scales_with_the_noise_and_the_process():
    """Linear-Gaussian bound with a diffuse prior: ∝ σ_B when the motion is known up to a constant offset
    (a → 0); larger for a looser random walk; the component along B is the poorly observed one."""
    run = _orbital_run(0.5e-6)
    a = acc.information_limit(run, 0.5e-6, accel_radps2=1e-9)
    b = acc.information_limit(run, 1.0e-6, accel_radps2=1e-9)
    assert b["rms_full_radps"] == pytest.approx(2.0 * a["rms_full_radps"], rel=0.05)
    loose = acc.information_limit(run, 0.5e-6, accel_radps2=1e-3)
    looser = acc.information_limit(run, 0.5e-6, accel_radps2=1e-2)
    assert a["rms_full_radps"] < loose["rms_full_radps"] < looser["rms_full_radps"]
    # along B carries most of the bound (the perpendicular part is seen sample by sample)
    assert loose["rms_along_b_radps"] ** 2 > 0.5 * loose["rms_full_radps"] ** 2
    assert loose["rms_causal_full_radps"] >= loose["rms_full_radps"]
    # default process level: the truth's own |Δω|
    d = acc.information_limit(run, 0.5e-6)
    dw = np.diff(run.w_true_radps[run.record], axis=0)
    assert d["accel_radps2"] == pytest.approx(math.sqrt(np.mean(np.sum(dw ** 2, axis=1)) / 3.0))


def test_coverage_spread_over_runs():
    s = acc.coverage_spread([0.5, 0.7, 0.9])
    assert s["coverage_se"] == pytest.approx(0.2 / math.sqrt(3))
    assert s["runs_for_coverage_pm10"] == math.ceil((1.96 * 0.2 / 0.1) ** 2)
    assert "coverage_se" not in acc.coverage_spread([0.6])
