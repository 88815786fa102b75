"""The attitude about B as a Gaussian sum: the ground's filters and smoother run from several starting angles.

With a field model along the orbit, a filter that carries the attitude (`fsw.estimation.attitude_kalman`
and its banks) knows the attitude about B only through the field's slow turning in inertial space
(twice the orbital rate, ~0.13 °/s in low orbit). A pass started at the wrong angle about B sees the
field turn the wrong way in the body and reads the difference as the body's rate: its ω ⊥ B is off by
up to the field's turning rate times the chord of its attitude error, while its covariance, linearised
on that attitude, does not know it. On `bench.realistic`'s slow heavy tumble (1 °/s, 10 min) passes
from six angles end 0.05–0.2 °/s apart, each claiming ~0.03 °/s, their likelihoods within a few units:
the samples cannot say which, and a single pass's σ covered 16–50 % of its errors.

The honest σ is that of the posterior over the angle (a Gaussian sum; Alspach & Sorenson 1972,
Bar-Shalom et al. 2001 §11.6 for the static multiple-model form): pass i weighted by its likelihood,
wᵢ ∝ exp(−(nllᵢ − min nll)/c) (c: the variance of unit weight, which scales the log-likelihood's
differences as it scales the covariances), the estimate Σ wᵢ ωᵢ and its variance
Σ wᵢ (σᵢ² + (ωᵢ − ω̄)²) (:func:`mixture`). :func:`angle_sum_rate` does it causally, sample by sample,
for a streaming estimator; `ground.smoother.rts_smooth` over whole smoothed passes.
"""
from __future__ import annotations

import math
from typing import Callable

import numpy as np

from fsw.estimation.rate_formulas import unobserved_sigma
from fsw.estimation.rate_kalman import NO_ESTIMATE

#: starting angles about B (evenly spread over the turn)
ANGLES = 6
#: the least temper of the smoother's weights over whole passes (:func:`pass_temper`)
PASS_TEMPER = 3.0


def pass_temper(c: float) -> float:
    """The temper of the Gaussian sum's weights over whole smoothed passes, exp(−Δnll/T): the variance of
    unit weight `c`, and at least :data:`PASS_TEMPER` — the field model's own error (a TLE days old, a clock
    seconds off: the model's field is not the truth's) shifts whole passes' log-likelihoods by a few units
    that say nothing about the angle. On `bench.realistic`'s slow heavy tumble with the box's TLE the pass
    from the right angle (0.013–0.016 °/s off ⊥B) trailed a wrong one by 1.4 and 3.7 (seeds 0, 1), which
    with T = c ≈ 1 took 77–82 % of the weight (0.12 °/s off ⊥B, 1-σ 0.03: covered 33 % on seed 1); with
    T = 3 the sum covers 80 % and 47 % (63 % over both; the flown bank's tempers by 10 over its causal,
    shorter likelihoods: `fsw.estimation.filter_banks.ABOUT_B_TEMPER`)."""
    return max(float(c), PASS_TEMPER)


def mixture(nll, w, var, c: float = 1.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Gaussian sum of M hypotheses at N samples: `nll` (M,) or (M, N) negative log-likelihoods, `w` and
    `var` (M, N, 3) their estimates and variances (NaN: no estimate there, left out). Returns the mean
    (N, 3), the variance (N, 3) about it and the weights (M, N) (see the module docstring)."""
    w_all = np.asarray(w, float)
    var_all = np.clip(np.asarray(var, float), 0.0, None)
    m, n = w_all.shape[:2]
    d = np.broadcast_to(np.asarray(nll, float).reshape(m, -1), (m, n)).copy()
    ok = np.all(np.isfinite(w_all), axis=2) & np.isfinite(d)
    d[~ok] = math.inf
    best = np.min(d, axis=0)
    with np.errstate(invalid="ignore"):
        wt = np.where(ok, np.exp(-(d - np.where(np.isfinite(best), best, 0.0)) / max(c, 1.0)), 0.0)
    tot = wt.sum(axis=0)
    wt = np.divide(wt, tot, out=np.zeros_like(wt), where=tot > 0)
    w0 = np.where(ok[..., None], w_all, 0.0)
    mean = np.einsum("mk,mkj->kj", wt, w0)
    with np.errstate(invalid="ignore"):
        spread = np.where(ok[..., None], var_all + (w0 - mean) ** 2, 0.0)
    total = np.einsum("mk,mkj->kj", wt, spread)
    none = tot <= 0
    mean[none], total[none] = np.nan, np.nan
    return mean, total, wt


def _filters(est) -> list:
    """The attitude filters inside a streaming estimator (itself, a bank's members, its publisher)."""
    out = list(getattr(est, "members", ()))
    main = getattr(est, "main", None)
    if main is not None:
        out.append(main)
    return out or [est]


def angle_sum_rate(make: Callable[[float], object], t_s: np.ndarray, b_T: np.ndarray, sigma_b_T: float,
                   angles: int = ANGLES) -> tuple[np.ndarray, np.ndarray, dict]:
    """Run `make(angle_about_b_rad)` (a streaming estimator: `update(t, b)`, `omega_radps`,
    `sigma_radps`, `flags`, and `nll` on it or on its publishing filter `main`) from `angles` starting
    angles about B, and combine them sample by sample as a Gaussian sum weighted by each one's
    likelihood so far (the sum of its publishing filter's per-sample ½(NIS + ln det S)).
    Returns ω (N, 3), 1-σ (N, 3) as `fsw.estimation.rate_kalman.run_stream` (NaN: no estimate, inf:
    no information) and notes."""
    t = np.asarray(t_s, float)
    b = np.asarray(b_T, float)
    ests = [make(2.0 * math.pi * a / angles) for a in range(angles)]
    n = len(t)
    w = np.full((angles, n, 3), np.nan)
    var = np.full((angles, n, 3), np.nan)
    nll = np.zeros((angles, n))
    with np.errstate(all="ignore"):  # a hypothesis far off may diverge: its likelihood drops it
        for i, est in enumerate(ests):
            total = 0.0
            for k in range(n):
                before = {id(f): f.nll for f in _filters(est)}
                main_before = _main(est).nll
                published = est.update(t[k], b[k])
                pub = _main(est)
                step = pub.nll - before.get(id(pub), main_before)
                total += step if math.isfinite(step) else 1e6
                nll[i, k] = total
                if published and not est.flags & NO_ESTIMATE:
                    w[i, k] = est.omega_radps
                    var[i, k] = np.asarray(est.sigma_radps, float) ** 2
    mean, v, wt = mixture(nll, w, var)
    sig = unobserved_sigma(np.sqrt(v), b, sigma_b_T)
    final = wt[:, -1]
    return mean, sig, {"angles_about_b": f"{angles} starting angles as a Gaussian sum, final weights "
                                         + " ".join(f"{x:.2f}" for x in final)}


def _main(est):
    return getattr(est, "main", est)
