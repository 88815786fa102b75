"""The RTS smoothers' filter passes, compiled: the attitude filter
(:class:`fsw.estimation.attitude_kalman.AttitudeRateKalman`) over a record, sample by sample, with ω a random
walk or a Gauss–Markov process (:func:`ground.smoother.rts_smooth`) or with Euler's equations from the start
(:func:`ground.smoother.euler_rts_smooth`), keeping what the smoothers read — the state, its covariance, the
likelihood, and with `store` the log of predictions, transitions and updates for the RTS pass.

:func:`ground.smoother.rts_smooth` runs some 80 such passes per record (its grid search over the noise
levels and the angles about B), which in Python were most of the smoother's time. The arithmetic is the
filter's own compiled kernels (:mod:`fsw.estimation.mekf`: the random-walk step, the process noise, the
measurement update; Euler's equations through :func:`fsw.estimation.euler_step.propagate`), with the
divergence, NIS and shape checks of ``update`` and ``_publish``, on the path every sample of a sane record
takes; a sample off that path (not
finite, out of order, after a gap of more than `max_gap_s`, a diverged state, three NIS outliers in a row, a
shape no body has) ends the compiled pass and :func:`forward` runs the whole pass again in Python, so a
restart behaves exactly as the filter's. The published estimate (ω, its floored σ, flags) is not kept: the
smoothers do not read it. The filter's own code is the reference in tests/ground/test_rts_pass.py.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from fsw.estimation import attitude_kalman as ak
from fsw.estimation import euler_step as es
from fsw.estimation import mekf
from fsw.estimation import rate_kalman as rk
from fsw.estimation.rotations import quat_exp_nb as _qexp
from fsw.estimation.rotations import quat_mul_nb as _qmul


@njit(cache=True, error_model="numpy")
def _log(lq, lx, lP, k, q, w, p, beta, P, npar):
    """Sample k's state (q; ω, shape, field; P) into the pass's log."""
    lq[k] = q
    lx[k, :3] = w
    lx[k, 3:3 + npar] = p
    lx[k, 3 + npar:] = beta
    lP[k] = P


@njit(cache=True, error_model="numpy")
def passes(t, z, b_i, q, w, p, beta, P, nll, t_s, dt_nominal, bhat, bad, r_var, kappa, accel, tau, field_rate,
           max_gap_s, max_rate, max_step_angle, nis_reset, store, mode, J, K, max_substep_rad, max_substeps,
           shape_rate):
    """Samples 1… of a pass whose first sample the filter took (its start): (k, q, ω, β, P, nll, nis, t_s,
    dt_nominal, b̂, log arrays qp, xp, Pp, F, q, x, P, nis). k = len(t) when every sample was taken, else the
    first sample off the common path (nothing after it taken). z in µT; b_i (N, 3) µT or no rows (β in the
    state). `mode` −1: ω a random walk / Gauss–Markov; else Euler's equations (euler_step.SHAPE with
    the shape p in the state, or TENSOR with J, K = J⁻¹ as 9-arrays)."""
    N = len(t)
    nb = beta.shape[0]
    npar = p.shape[0]
    ib = 6 + npar
    n = ib + nb
    nl = N if store else 0
    nxs = 3 + npar + nb
    lqp, lxp, lPp, lF = np.zeros((nl, 4)), np.zeros((nl, nxs)), np.zeros((nl, n, n)), np.zeros((nl, n, n))
    lq, lx, lP, lnis = np.zeros((nl, 4)), np.zeros((nl, nxs)), np.zeros((nl, n, n)), np.zeros(nl)
    R = r_var * np.eye(3)
    nis = 0.0
    gm = math.isfinite(tau)
    for k in range(1, N):
        if not (math.isfinite(z[k, 0]) and math.isfinite(z[k, 1]) and math.isfinite(z[k, 2])):
            return k, q, w, p, beta, P, nll, nis, t_s, dt_nominal, bhat, lqp, lxp, lPp, lF, lq, lx, lP, lnis
        dt = t[k] - t_s
        if not dt > 0 or dt > max_gap_s:
            return k, q, w, p, beta, P, nll, nis, t_s, dt_nominal, bhat, lqp, lxp, lPp, lF, lq, lx, lP, lnis
        dtn = min(dt_nominal, dt)
        if mode < 0:  # propagate: ω a random walk / Gauss–Markov
            if gm:
                x = dt / tau
                decay, mean = math.exp(-x), -math.expm1(-x) / x
            else:
                decay, mean = 1.0, 1.0
            q1, w1, F = mekf.rw_propagate(q, w, decay, mean, dt, n)
            # process noise (κ|ω||ω⊥| with the previous sample's field direction)
            q_w = accel ** 2 * dt
            if gm:
                q_w *= -math.expm1(-2.0 * dt / tau) * tau / (2.0 * dt)
            w2 = w1[0] * w1[0] + w1[1] * w1[1] + w1[2] * w1[2]
            wb = w1[0] * bhat[0] + w1[1] * bhat[1] + w1[2] * bhat[2]
            q_w += kappa ** 2 * w2 * max(w2 - wb * wb, 0.0) / 3.0 * dt
        else:  # Euler's equations, RK4 substeps (the filter's propagate)
            wn = math.sqrt(w[0] * w[0] + w[1] * w[1] + w[2] * w[2])
            if not (math.isfinite(wn) and np.all(np.isfinite(p))):
                return k, q, w, p, beta, P, nll, nis, t_s, dt_nominal, bhat, lqp, lxp, lPp, lF, lq, lx, lP, lnis
            j2, j3 = (math.exp(p[0]), math.exp(p[1])) if mode == es.SHAPE else (1.0, 1.0)
            m = min(max_substeps, max(1, int(math.ceil(wn * dt / max_substep_rad))))
            q1, w1, F = es.propagate(q, w, dt, m, mode, j2, j3, J, K, npar, n, es.TORQUE_FREE)
            q_w = accel ** 2 * dt
        P1 = mekf.predict_covariance(F, P, mekf.process_noise(n, npar, q_w, dt, shape_rate, field_rate, beta))
        if store:
            _log(lqp, lxp, lPp, k, q1, w1, p, beta, P1, npar)
            lF[k] = F
        zk = z[k]
        nz = max(math.sqrt(zk[0] * zk[0] + zk[1] * zk[1] + zk[2] * zk[2]), 1e-30)
        bh1 = zk / nz
        q2, w3, p1, beta1, P2, nis1, dnll = mekf.update(q1, w1, p, beta, P1, zk, beta if nb else b_i[k], R)
        nll1 = nll + dnll
        # the filter's checks: diverged (update), not finite or three outliers in a row (_publish)
        wn = math.sqrt(w3[0] * w3[0] + w3[1] * w3[1] + w3[2] * w3[2])
        if not (np.all(np.isfinite(P2)) and wn < max_rate and wn * min(dt, dtn) < max_step_angle
                and np.all(np.isfinite(q2)) and np.all(np.isfinite(w3)) and (npar == 0 or ak.physical_shape(p1))):
            return k, q, w, p, beta, P, nll, nis, t_s, dt_nominal, bhat, lqp, lxp, lPp, lF, lq, lx, lP, lnis
        bad1 = bad + 1 if nis1 > nis_reset else 0
        if bad1 >= 3:
            return k, q, w, p, beta, P, nll, nis, t_s, dt_nominal, bhat, lqp, lxp, lPp, lF, lq, lx, lP, lnis
        q, w, p, beta, P, nll, nis, t_s, dt_nominal, bhat, bad = q2, w3, p1, beta1, P2, nll1, nis1, t[k], dtn, \
            bh1, bad1
        if store:
            _log(lq, lx, lP, k, q, w, p, beta, P, npar)
            lnis[k] = nis
    return N, q, w, p, beta, P, nll, nis, t_s, dt_nominal, bhat, lqp, lxp, lPp, lF, lq, lx, lP, lnis


def compiled(kf: ak.AttitudeRateKalman) -> bool:
    """Whether :func:`passes` is this filter's arithmetic: ω a random walk or Gauss–Markov (no inertia), or
    Euler's equations from the start (the Euler RTS smoother's passes); no torque, no noise adaptation, no
    floor about B inside the filter."""
    tun = kf.tuning
    return (kf.torque is None and (kf.euler if kf.euler_model else kf.n_p == 0) and not tun.adapt_max > 1.0
            and not tun.about_b_sigma_rad > 0)


def forward(kf: ak.AttitudeRateKalman, t: np.ndarray, b_T: np.ndarray, start: dict) -> ak.AttitudeRateKalman:
    """The pass of `kf` over (t, b_T) from `start` (kf.start's keywords) at the first sample: compiled when
    it can be (:func:`compiled`, every sample on the common path), else the filter's own updates. The
    filter returned holds the state, P, nll, nis and, with `store`, the log; with the compiled pass its
    published ω, σ and flags are those of the first sample."""
    t = np.ascontiguousarray(t, dtype=float)
    b_T = np.asarray(b_T, float)
    kf.start(t[0], b_T[0], **start)
    if not (compiled(kf) and kf._started and len(t) > 1):
        return _python_pass(kf, t, b_T)
    snapshot = kf.clone()
    snapshot.store, snapshot.log = kf.store, {k: list(v) for k, v in kf.log.items()}
    z = np.ascontiguousarray(b_T * rk.UT_PER_T)
    if kf.field is not None:
        b_i = np.ascontiguousarray(np.array([np.asarray(kf.field(x), float) for x in t]).reshape(len(t), 3)
                                   * rk.UT_PER_T)
    else:
        b_i = np.zeros((0, 3))
    tun = kf.tuning
    bhat = getattr(kf, "_bhat", np.zeros(3))
    mode, _, _, J, K = kf.euler_args() if kf.euler else (-1, 1.0, 1.0, es.NO_TENSOR, es.NO_TENSOR)
    with np.errstate(all="ignore"):
        out = passes(t, z, b_i, np.asarray(kf.q, float), np.asarray(kf.w, float), np.asarray(kf.p, float),
                     np.asarray(kf.beta, float),
                     np.asarray(kf.P, float), float(kf.nll), float(kf.t_s), float(kf._dt_nominal),
                     np.asarray(bhat, float), int(kf._bad), float(kf.R[0, 0]), float(tun.kappa),
                     float(tun.rate_accel_radps2), float(tun.rate_tau_s), float(tun.field_rate_radps),
                     float(tun.max_gap_s), float(tun.max_rate_radps), float(tun.max_step_angle_rad),
                     float(tun.nis_reset), bool(kf.store), mode, J, K, float(tun.max_substep_rad),
                     int(tun.max_substeps), float(tun.inertia_shape_rate))
    k = out[0]
    if k < len(t):  # a sample off the common path: the filter's own pass, restarts and all
        return _python_pass(snapshot, t, b_T, first=1)
    kf.q, kf.w, kf.p, kf.beta, kf.P, kf.nll, kf.nis, kf.t_s, kf._dt_nominal, kf._bhat = (
        out[1], out[2], out[3], out[4], out[5], float(out[6]), float(out[7]), float(out[8]), float(out[9]), out[10])
    if kf.store:
        lg = kf.log
        for name, arr in zip(("qp", "xp", "Pp", "F", "q", "x", "P", "nis"), out[11:]):
            lg[name] = list(lg[name]) + list(arr[1:])
        lg["t"] = list(lg["t"]) + list(t[1:])
        lg["restart"] = list(lg["restart"]) + [False] * (len(t) - 1)
    return kf




def _python_pass(kf: ak.AttitudeRateKalman, t, b_T, first: int = 1) -> ak.AttitudeRateKalman:
    for k in range(first, len(t)):
        kf.update(t[k], b_T[k])
    return kf


@njit(cache=True, error_model="numpy")
def _qlog(q):
    """rotations.quat_log: the rotation vector of a unit quaternion, the shorter way round."""
    if q[0] < 0:
        q = -q
    s = math.sqrt(q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    if s < 1e-12:
        return 2.0 * q[1:]
    return (2.0 * math.atan2(s, q[0]) / s) * q[1:]


@njit(cache=True, error_model="numpy")
def backward(q_f, x_f, P_f, q_p, x_p, P_p, F, restart, n_att):
    """The RTS backward pass of :func:`ground.smoother.rts` (its docstring has the equations): smoothed
    attitudes, additive states and covariances."""
    N = q_f.shape[0]
    q_s, x_s, P_s = q_f.copy(), x_f.copy(), P_f.copy()
    conj = np.array((1.0, -1.0, -1.0, -1.0))
    for k in range(N - 2, -1, -1):
        if restart[k + 1]:
            continue
        C = np.linalg.solve(P_p[k + 1], F[k + 1] @ P_f[k]).T
        d = np.concatenate((_qlog(_qmul(q_p[k + 1] * conj, q_s[k + 1])), x_s[k + 1] - x_p[k + 1]))
        dx = C @ d
        q_s[k] = _qmul(q_f[k], _qexp(dx[:n_att]))
        x_s[k] = x_f[k] + dx[n_att:]
        P_s[k] = P_f[k] + C @ (P_s[k + 1] - P_p[k + 1]) @ C.T
    return q_s, x_s, P_s
