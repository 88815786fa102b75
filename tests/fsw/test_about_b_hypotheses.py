"""The flown Euler filter's hypotheses over the attitude's angle about the field
(fsw.estimation.filter_banks.EulerAcquisitionKalman with `about_b_hypotheses`): each hypothesis's σ about B
set without breaking its covariance, and the published rate's σ holding the hypotheses' spread — against the
accuracy benchmark's simulated truth."""
import math

import numpy as np
import pytest

from fsw.estimation import filter_banks as fb
from fsw.estimation.attitude_kalman import AttitudeRateKalman
from support import accuracy_record

pytestmark = pytest.mark.fsw


def _correlated_filter(seed: int) -> AttitudeRateKalman:
    """A filter whose attitude about one axis is strongly correlated with its rate (as after a few minutes of
    a tumble with the angle about B unseen): a random positive-definite covariance with that structure."""
    kf = AttitudeRateKalman(0.5e-6, field_eci_T=lambda t: np.array([2e-5, 0.0, 3e-5]), estimate_inertia=True)
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(kf.n, kf.n)) * 0.05
    A[:3, :3] += np.diag([2.0, 0.1, 0.1])          # wide about x
    A[3:6, 0] += np.array([0.05, -0.04, 0.03])     # the rate follows that angle
    kf.P = A @ A.T + 1e-8 * np.eye(kf.n)
    return kf


@pytest.mark.parametrize("seed", range(5))
def test_the_sigma_about_b_is_set_by_conditioning_and_the_covariance_stays_positive_definite(seed):
    u = np.array([1.0, 0.0, 0.0])
    sigma = 2.0 * math.pi / fb.ABOUT_B_HYPOTHESES / math.sqrt(12.0)
    kf = _correlated_filter(seed)
    v = float(u @ kf.P[:3, :3] @ u)
    assert v > 4 * sigma ** 2                       # the premise: the variance is lowered
    naive = kf.P.copy()
    naive[:3, :3] += (sigma ** 2 - v) * np.outer(u, u)
    assert np.linalg.eigvalsh(naive).min() < 0      # overwriting it in place breaks the covariance
    fb._condition_about_b(kf, u, sigma)
    assert float(u @ kf.P[:3, :3] @ u) == pytest.approx(sigma ** 2, rel=1e-9)
    assert np.linalg.eigvalsh(kf.P).min() > -1e-12
    assert np.allclose(kf.P, kf.P.T)
    # raised: added along u alone
    wide = 3.0
    fb._condition_about_b(kf, u, wide)
    assert float(u @ kf.P[:3, :3] @ u) == pytest.approx(wide ** 2, rel=1e-9)
    assert np.linalg.eigvalsh(kf.P).min() > -1e-12


def test_a_libration_the_euler_filter_does_not_fit_does_not_spin_it_up():
    """The accuracy benchmark's IGRF row orbital/near_symmetric/1 s/1.5 µT, run 12: a 1.5 °/s libration, on which
    the Euler filter locks on wrongly (12 °/s). Its hypotheses about B once had their σ about B overwritten
    in place: the covariance went indefinite (a rate variance below zero), the published σ NaN, and the filter
    spun up to 120–137 °/s with a σ of 5 °/s. Now it stays within the Euler filter's own misfit and every
    published σ is finite."""
    t, b, w, _, sb, fld = accuracy_record("orbital", "near_symmetric", 1.0, 1.5, 12, world="igrf", whole=True)
    kf = fb.EulerAcquisitionKalman(sb, field_eci_T=fld, about_b_hypotheses=fb.ABOUT_B_HYPOTHESES)
    err, sig = [], []
    for k in range(len(t)):
        kf.update(t[k], b[k])
        if kf.euler:
            err.append(np.linalg.norm(kf.omega_radps - w[k]))
            sig.append(kf.sigma_radps.copy())
    assert kf.about_b_switches >= 1                 # the hypotheses did take over
    assert np.all(np.isfinite(sig))
    assert math.degrees(max(err)) < 15.0
