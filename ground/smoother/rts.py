"""The random-walk RTS smoother of the body rate (:func:`rts_smooth`) over the flight software's attitude filter,
the result type every smoother returns (:class:`Smoothed`) and the field model tabulated at the sample times
(:func:`tabulated`); the package's docstring (:mod:`ground.smoother`) says how the smoothers fit together."""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from fsw.estimation import attitude_kalman as ak
from fsw.estimation.rate_formulas import unobserved_sigma
from fsw.estimation import rate_kalman as rk
from fsw.estimation import rotations as rot
from ground import angle_sum
from ground import rts_pass

FieldFn = ak.FieldFn
SHAPE_SIGMA_FLOOR = 0.01  # 1-σ floor of ln(J₂/J₁), ln(J₃/J₁) carried into the Euler RTS smoother


@dataclass
class Smoothed:
    """A smoothed rate history: ω and 1-σ per sample (rad/s), the attitude (body → ECI, or → the first
    sample's body axes with no field model), and what the model says about itself."""

    t_s: np.ndarray
    w_radps: np.ndarray
    sigma_radps: np.ndarray
    q: np.ndarray
    method: str
    chi2_dof: float = math.nan
    inertia_shape: np.ndarray | None = None
    info: dict = field(default_factory=dict)


def tabulated(field_eci_T: FieldFn | None, t_s: np.ndarray) -> FieldFn | None:
    """The field model evaluated once at the sample times (vectorised when it allows), served from a
    table at those times and by the model elsewhere."""
    if field_eci_T is None:
        return None
    t = np.asarray(t_s, float)
    try:
        values = np.asarray(field_eci_T(t), float).reshape(len(t), 3)
    except (TypeError, ValueError):
        values = np.array([np.asarray(field_eci_T(x), float) for x in t])
    table = {float(x): v for x, v in zip(t, values)}

    def field(t_query: float) -> np.ndarray:
        v = table.get(float(t_query))
        return v if v is not None else np.asarray(field_eci_T(t_query), float)
    field.at_samples = (t, values)  # the compiled propagation reads it whole
    return field


# --- RTS over the attitude filter ------------------------------------------------------------------

def rts(log: dict, n_att: int = 3) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rauch–Tung–Striebel backward pass over a stored :class:`AttitudeRateKalman` pass.

    C_k = P_k Φ_{k+1}ᵀ (P⁻_{k+1})⁻¹;  δ_{k+1} = x^s_{k+1} ⊖ x⁻_{k+1} (attitude part: the body-frame
    rotation vector of q⁻⁻¹ ⊗ q^s);  x^s_k = x_k ⊕ C_k δ_{k+1};  P^s_k = P_k + C_k (P^s_{k+1} − P⁻_{k+1}) C_kᵀ.
    Returns the smoothed attitudes (N, 4), additive states (N, m) and covariances (N, n, n). Where the
    filter restarted (a gap, a divergence) the pass does not link the two sides.
    """
    q_f, x_f, P_f = (np.array(log[k], float) for k in ("q", "x", "P"))
    q_p, x_p, P_p, F = (np.array(log[k], float) for k in ("qp", "xp", "Pp", "F"))
    N = len(q_f)
    # where the filter started afresh at k + 1, nothing links the two stretches
    restart = np.array(log.get("restart", [False] * N), bool)
    return rts_pass.backward(q_f, x_f, P_f, q_p, x_p, P_p, F, restart, n_att)  # compiled


def variance_scale(log: dict, skip: int = 10) -> float:
    """Variance of unit weight of a filter pass from its normalised innovations (NIS, 3 per sample):
    ĉ = Σ yᵀS⁻¹y / (3 n) over the samples at least `skip` after a (re)start, where the prior still
    dominates. For a linear-Gaussian model with every covariance (P₀, Q, R) scaled by c, ĉ is the
    maximum-likelihood c (Bar-Shalom et al. 2001 §5.4, the filter's χ² consistency test); the
    smoothed covariance scales by it too. Returns max(1, ĉ): the noise levels are known or fitted
    at least as large, a smaller ĉ is the samples' scatter, not a reason to trust the model more."""
    nis = np.asarray(log.get("nis", []), float)
    restart = np.asarray(log.get("restart", [False] * len(nis)), bool)[:len(nis)]
    since = np.zeros(len(nis), int)
    c = skip
    for k in range(len(nis)):
        c = 0 if restart[k] else c + 1
        since[k] = c
    use = (since >= skip) & np.isfinite(nis)
    if use.sum() < 3:
        return 1.0
    return max(1.0, float(np.mean(nis[use])) / 3.0)


def _forward(t, b, sigma_b_T, field_eci_T, noise, angle, start=None, store=False):
    """One pass of the random-walk attitude filter over (t, b) from `start` (or the first sample);
    `noise` = (κ, rate floor [rad/s²], factor on σ_B, Gauss–Markov time of ω [s], ∞ for a random walk)."""
    kappa, accel, sfac, tau = noise
    kf = ak.AttitudeRateKalman(sigma_b_T * sfac, field_eci_T=field_eci_T,
                               tuning=ak.AttitudeKalmanTuning(kappa=kappa, rate_accel_radps2=accel, adapt_max=1.0,
                                                              rate_tau_s=tau),
                               angle_about_b_rad=angle, store=store)
    return rts_pass.forward(kf, t, b, start or {})  # compiled (the filter's own updates where it cannot be)


def _reversed(t, b, field_eci_T):
    """The record in reversed time τ = −t: the body turns at −ω, the field is B_I(−τ)."""
    fld = None if field_eci_T is None else (lambda tau: field_eci_T(-tau))
    return -t[::-1], b[::-1], fld


def rts_smooth(t_s: np.ndarray, b_T: np.ndarray, sigma_b_T: float, *, field_eci_T: FieldFn | None = None,
               kappas: tuple[float, ...] = (0.03, 0.1, 0.3, 0.6),
               accels_radps2: tuple[float, ...] = (1e-4, 1e-3, 1e-2, 1e-1, 1.0, 10.0, 100.0),
               sigma_factors: tuple[float, ...] = (1.0, 3.0),
               rate_taus_s: tuple[float, ...] = (math.inf, 300.0, 100.0, 30.0, 10.0), angles: int = 6) -> Smoothed:
    """RTS smoother with ω a random walk, or a first-order Gauss–Markov process (ω̇ = −ω/τ + w) for a
    motion bounded about zero such as a libration, whichever the likelihood prefers.

    The pass is linearised where the filter has converged: first a filter runs backwards in time (τ = −t,
    the body turning at −ω) and its end state at t₀ — which has seen the whole record — becomes the
    start of the forward filter, its covariance inflated tenfold (so that the samples it has seen count
    only a tenth again); the RTS pass then runs over that forward filter. The random walk's strength
    (κ for the torque-free part, a floor for other torques: 10⁻⁴ rad/s² for a tumbling body up to
    100 rad/s² for a hand-held sensor), a factor on σ_B (a field that is not quite uniform, a sensor
    not quite calibrated), the Gauss–Markov time τ (∞: the random walk) and, with a field model, the
    starting angle about B are chosen by maximum likelihood on the backward pass (a search over the
    grids: the floor and τ jointly, then κ and the factor, then the floor and τ again). A finite τ matters where
    the samples say little about ω along B (a slow motion:
    B barely turns in the body): that component then falls back to zero with the process's stationary
    spread instead of wandering off.

    With a field model the attitude about B is weakly fixed (by the field's slow turning only): the
    smoothed pass is run from each of the `angles` starting angles and the passes are combined as a
    Gaussian sum weighted by their likelihoods (`ground.angle_sum`): ω the mixture's mean, σ its spread
    with each pass's own; q, χ², `angle_about_b_rad` and ``info["w_pass_radps"]`` are those of the pass
    from the angle the backward search chose (an attitude and a rate that belong together: the batch
    fit starts from them).
    """
    t = np.asarray(t_s, float)
    b = np.asarray(b_T, float)
    field_eci_T = tabulated(field_eci_T, t)
    tr, br, fr = _reversed(t, b, field_eci_T)
    mid = (kappas[len(kappas) // 2], accels_radps2[min(2, len(accels_radps2) - 1)], sigma_factors[0], rate_taus_s[0])
    angle = 0.0
    if fr is not None:
        angle = min((2 * math.pi * a / angles for a in range(angles)),
                    key=lambda g: _forward(tr, br, sigma_b_T, fr, mid, g).nll)
    # search: the floor and the Gauss–Markov time together (the stationary spread a√(τ/2) couples them,
    # and one at a time sticks: a random walk at 10⁻² rad/s² can beat every τ at that floor while
    # τ = 10 s at the same floor beats both), then κ, the measurement-noise factor, and the pair again
    runs = {}

    def nll(n):
        if n not in runs:
            runs[n] = _forward(tr, br, sigma_b_T, fr, n, angle)
        return runs[n].nll

    noise = mid
    for axes, values in (((1, 3), [(a, tau) for a in accels_radps2 for tau in rate_taus_s]),
                         ((0,), [(k,) for k in kappas]), ((2,), [(f,) for f in sigma_factors]),
                         ((1, 3), [(a, tau) for a in accels_radps2 for tau in rate_taus_s])):
        def with_(v, noise=noise, axes=axes):
            n = list(noise)
            for i, x in zip(axes, v):
                n[i] = x
            return tuple(n)
        noise = min((with_(v) for v in values), key=nll)
    if fr is None:
        kf, q_s, x_s, P_s = _smoothed_pass(t, b, sigma_b_T, field_eci_T, noise, runs[noise], angle)
        c = variance_scale(kf.log)
        sig = np.sqrt(c * np.clip(np.einsum("kii->ki", P_s[:, 3:6, 3:6]), 0.0, None))
        w_s, mix = x_s[:, :3].copy(), {}
    else:  # every starting angle about B, as a Gaussian sum (ground.angle_sum)
        passes = [_smoothed_pass(t, b, sigma_b_T, field_eci_T, noise, runs[noise] if g == angle else
                                 _forward(tr, br, sigma_b_T, fr, noise, g), g)
                  for g in (2 * math.pi * a / angles for a in range(angles))]
        # the pass from the angle the backward search chose (as before the sum): its attitude and rate
        # belong together, and the batch fit starts from them
        kf, q_s, x_s, P_s = next(p for p in passes if p[0].angle_about_b_rad == angle)
        c = variance_scale(kf.log)
        w_s, var, wt = angle_sum.mixture([p[0].nll for p in passes], [p[2][:, :3] for p in passes],
                                         [c * np.einsum("kii->ki", p[3][:, 3:6, 3:6]) for p in passes],
                                         angle_sum.pass_temper(c))
        sig = np.sqrt(var)
        mix = {"angle_weights": wt[:, 0].tolist(), "w_pass_radps": x_s[:, :3].copy()}
    chi2 = _chi2(t, b, sigma_b_T * noise[2], q_s, x_s, field_eci_T)
    return Smoothed(t, w_s, unobserved_sigma(sig, b, sigma_b_T), q_s, "smoother",
                    chi2 / max(3 * len(t) - 6, 1), info={"kappa": noise[0], "rate_accel_radps2": noise[1],
                                                          "sigma_factor": noise[2], "rate_tau_s": noise[3],
                                                          "angle_about_b_rad": angle,
                                                          "nll": kf.nll, "variance_scale": c, **mix})


def _smoothed_pass(t, b, sigma_b_T, field_eci_T, noise, back, angle):
    """The forward filter started from a backward pass's end at t₀ and its RTS pass: (filter, q, x, P).
    The backward estimate's covariance (block-diagonal, the reversed rate's sign irrelevant there) is
    inflated tenfold, so that the samples it has seen weigh only a tenth again."""
    P0 = np.zeros_like(back.P)
    for blk in (slice(0, 3), slice(3, 6), slice(6, back.n)):
        P0[blk, blk] = 10.0 * back.P[blk, blk]
    start = {"q": back.q, "omega_radps": -back.w, "P": P0}
    if field_eci_T is None:
        start["beta_uT"] = back.beta
    kf = _forward(t, b, sigma_b_T, field_eci_T, noise, angle, start=start, store=True)
    return (kf, *rts(kf.log))


def _chi2(t, b, sigma_b_T, q, x, field_eci_T) -> float:
    """Σ |z − h|² / σ² of a smoothed trajectory."""
    total = 0.0
    for k in range(len(t)):
        C = rot.quat_to_dcm(q[k])
        b_i = np.asarray(field_eci_T(t[k]), float) if field_eci_T is not None else x[k, -3:] / rk.UT_PER_T
        r = b[k] - C.T @ b_i
        total += float(r @ r)
    return total / sigma_b_T ** 2
