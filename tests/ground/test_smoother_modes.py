"""The batch Euler fit's search for other minima as good as the best (ground.smoother, _Minimum.finish): a
start that begins where one already polished did is not polished again, and the modes, weights and σ are
those of polishing every start."""
import math

import numpy as np
import pytest

from bench import accuracy as acc
from ground import smoother as sm
from ground.smoother import batch_fit as bf


@pytest.mark.slow
def test_the_mode_search_polishes_a_start_once_and_finds_what_polishing_all_finds(monkeypatch):
    rng = np.random.default_rng([5, 1])
    run = acc.simulate("undirected", "asymmetric", 1.0, 0.5e-6, rng, record_samples=40, warmup_s=0.0)
    sigma = math.hypot(0.5e-6, acc.CHIP_NOISE_T)
    t, b = run.t_s[run.record], run.b_T[run.record]
    m = bf._euler_minimum(t, b, sigma, field_eci_T=sm.tabulated(run.field, t))
    calls = []
    real_lm = bf._lm

    def counted(*args, **kwargs):
        calls.append(1)
        return real_lm(*args, **kwargs)
    monkeypatch.setattr(bf, "_lm", counted)
    once = m.finish()
    n_once = len(calls)
    monkeypatch.setattr(bf, "_same_start", lambda a, b, tol_rad=0.02: False)   # every start polished, as before
    calls.clear()
    every = m.finish()
    # most of the 24 starts end in the best minimum: polished again they find it again
    assert n_once <= len(calls) / 3
    assert once.info["modes_dchi2"] == pytest.approx(every.info["modes_dchi2"], abs=1e-6)
    assert once.info["modes_weight"] == pytest.approx(every.info["modes_weight"], abs=1e-6)
    np.testing.assert_array_equal(once.w_radps, every.w_radps)
    np.testing.assert_allclose(once.sigma_radps, every.sigma_radps, rtol=1e-6)
    # the truth within the fit's own 4 σ (rad/s)
    assert np.all(np.abs(once.w_radps - run.w_true_radps[run.record]) < 4 * once.sigma_radps + 1e-4)
