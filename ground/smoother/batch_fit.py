"""The batch output-error fit of the torque-free motion (:func:`euler_fit`, :func:`euler_fit_checked`): the
attitude and rate at the first sample, the inertia shape (or a known tensor) and, without a field model, the
inertial field, fitted to the whole record by Levenberg–Marquardt over growing windows; its other minima as
good kept in σ. The propagation is compiled (`ground.euler_trajectory`).

With `hard_iron_sigma_T` the fit also takes a constant field offset in body axes (what a host calibration
leaves of the hard iron: its 1-σ per axis is the prior) off every sample: on a tumbling body it is told from
the inertial field by the turning, and at the fit's precision (0.04–0.08 °/s at 15 °/s) a 0.15 µT offset
left in doubles the error."""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from fsw.estimation import attitude_kalman as ak
from fsw.estimation import filter_banks as fb
from fsw.estimation.rate_formulas import unobserved_sigma
from fsw.estimation import rate_kalman as rk
from fsw.estimation import rotations as rot
from ground import euler_trajectory as et

from .rts import FieldFn, Smoothed, rts_smooth, tabulated

#: the growing windows' first, in samples
FIRST_WINDOW = 8
#: other minima of the batch fit: polished when within MODE_SEARCH_DCHI2 of the best after their first
#: iterations, kept in σ (weight e^(−Δχ²/2)) when within MODE_KEEP_DCHI2 after polishing
MODE_SEARCH_DCHI2, MODE_KEEP_DCHI2 = 30.0, 20.0


# --- batch output-error fit of the torque-free motion ----------------------------------------------

@dataclass
class _Trajectory:
    q: np.ndarray          # (N, 4) nominal attitudes
    w: np.ndarray          # (N, 3)
    Phi: np.ndarray        # (N, n, n) transition from the first sample
    r: np.ndarray          # (N, 3) residuals / σ
    Jr: np.ndarray         # (N, 3, n) ∂r/∂δx₀


def _trajectory(kf: ak.AttitudeRateKalman, t, z_uT, sb_uT, n, jacobian: bool = True) -> _Trajectory:
    """Propagate the filter's nominal state (no updates, torque-free Euler) across the first n samples,
    compiled (:func:`ground.euler_trajectory.trajectory`; the filter's own propagation is its reference in
    tests/ground/test_euler_trajectory.py). Without `jacobian` only q, ω and r (Φ and Jr empty: an LM
    trial's cost)."""
    if not kf.euler or kf.torque is not None:
        raise NotImplementedError("the batch fit's propagation is torque-free Euler")
    if not np.all(np.abs(kf.p) < _LN_RATIO_MAX):  # NaN too; beyond, a ratio is 0 or inf in floating point
        raise ValueError("non-finite state")
    mode, j2, j3, J, K = kf.euler_args()
    b_i = _NO_FIELD if kf.field is None else _field_at_samples(kf.field, t, n)
    tun = kf.tuning
    bias = _bias(kf)
    z = np.ascontiguousarray(z_uT if bias is None else np.asarray(z_uT, float)[:n] - bias, dtype=float)
    Q, W, Phi, r, Jr, ok = et.trajectory(np.asarray(kf.q, float), np.asarray(kf.w, float), mode, j2, j3, J, K,
                                         int(kf.n_p), np.asarray(kf.beta, float), b_i,
                                         np.ascontiguousarray(t, dtype=float), z, float(sb_uT), int(n),
                                         float(tun.max_substep_rad), int(tun.max_substeps), jacobian)
    if not ok:
        raise ValueError("non-finite state")
    if bias is not None and jacobian:  # r = (z − b − h)/σ: ∂r/∂b = −I/σ at every sample
        Jr = np.concatenate([Jr, np.broadcast_to(-np.eye(3) / sb_uT, (len(Jr), 3, 3))], axis=2)
    return _Trajectory(Q, W, Phi, r, Jr)


def _bias(kf) -> np.ndarray | None:
    """The fitted constant field offset in body axes (µT), None when the fit takes none."""
    return getattr(kf, "bias_uT", None)


def _n_params(kf) -> int:
    """The fit's parameters: the filter's error state and, when fitted, the offset's three."""
    return kf.n + (0 if _bias(kf) is None else 3)


#: |ln J₂/J₁|, |ln J₃/J₁| beyond which exp() is 0 or overflows (an LM trial may step there)
_LN_RATIO_MAX = 700.0
_NO_FIELD = np.zeros((0, 3))


def _field_at_samples(field_eci_T: FieldFn, t: np.ndarray, n: int) -> np.ndarray:
    """B_I (µT) at the first n samples: the table of :func:`tabulated` when it holds these times."""
    table = getattr(field_eci_T, "at_samples", None)
    if table is not None and len(table[0]) >= n and (table[0] is t or np.array_equal(table[0][:n], t[:n])):
        values = table[1][:n]
    else:
        values = np.array([np.asarray(field_eci_T(x), float) for x in t[:n]]).reshape(n, 3)
    return np.ascontiguousarray(values * rk.UT_PER_T)


def euler_fit(t_s: np.ndarray, b_T: np.ndarray, sigma_b_T: float, *, field_eci_T: FieldFn | None = None,
              inertia_kgm2: np.ndarray | None = None, init: Smoothed | None = None,
              first_window: int = FIRST_WINDOW, growth: float = 1.4, iterations: int = 10, starts_about_b: int = 24,
              wahba_rounds: int = 2, max_substep_rad: float = 0.25,
              hard_iron_sigma_T=None) -> Smoothed:
    """Torque-free Euler + kinematics fitted to the whole record: :func:`_euler_minimum`, then the other minima
    as good in σ (:meth:`_Minimum.finish`)."""
    return _euler_minimum(t_s, b_T, sigma_b_T, field_eci_T=field_eci_T, inertia_kgm2=inertia_kgm2, init=init,
                          first_window=first_window, growth=growth, iterations=iterations,
                          starts_about_b=starts_about_b, wahba_rounds=wahba_rounds,
                          max_substep_rad=max_substep_rad, hard_iron_sigma_T=hard_iron_sigma_T).finish()


def _euler_minimum(t_s: np.ndarray, b_T: np.ndarray, sigma_b_T: float, *, field_eci_T: FieldFn | None = None,
                   inertia_kgm2: np.ndarray | None = None, init: Smoothed | None = None,
                   first_window: int = FIRST_WINDOW, growth: float = 1.4, iterations: int = 10,
                   starts_about_b: int = 24, wahba_rounds: int = 2, max_substep_rad: float = 0.25,
                   hard_iron_sigma_T=None) -> "_Minimum":
    """Torque-free Euler + kinematics fitted to the whole record (see the module docstring).

    `init` gives the starting attitude and rate (default: :func:`rts_smooth`). With a field model the
    attitude about B is fixed only by the field's slow turning and the cost has several minima in
    that angle: after the growing windows the whole record is fitted from `starts_about_b` angles
    about B_I(t₀) (a few iterations each), the best is polished, then the attitude at t₀ is solved
    globally for the fitted relative motion (Wahba's problem, :func:`_wahba_start`) and the record
    fitted again from there while that lowers the cost.

    1-σ: the posterior can have several modes as good as the best within a few units of χ² (another
    attitude about B with a slightly different motion: truths 60–100° away in attitude and 0.1–0.2 °/s
    in ω, a Mahalanobis distance of thousands in the best minimum's own covariance). Every other start
    that ends within `MODE_SEARCH_DCHI2` is polished; the distinct minima within `MODE_KEEP_DCHI2` are
    weighted by e^(−Δχ²/2s²) and σ² is the mixture's second moment about the best: Σ wᵢ (σᵢ² +
    (ωᵢ − ω̂)²). The estimate stays the best minimum's.

    `hard_iron_sigma_T` (> 0, one or per axis, with a field model): a constant offset in body axes fitted
    too, prior 1-σ that (a host calibration's hard-iron σ; NaN or none: no offset fitted); its estimate
    and 1-σ in the result's info (`hard_iron_residual_uT`, `hard_iron_residual_sigma_uT`), its
    uncertainty in every σ.
    """
    t = np.asarray(t_s, float)
    b = np.asarray(b_T, float)
    N = len(t)
    field_eci_T = tabulated(field_eci_T, t)
    init = init or rts_smooth(t, b, sigma_b_T, field_eci_T=field_eci_T)
    tun = ak.AttitudeKalmanTuning(max_substep_rad=max_substep_rad, max_substeps=400)

    def filt():
        return ak.AttitudeRateKalman(sigma_b_T, field_eci_T=field_eci_T, inertia_kgm2=inertia_kgm2,
                                     estimate_inertia=inertia_kgm2 is None, tuning=tun)

    kf = filt()
    if field_eci_T is None:  # the first sample's body axes are the frame; β the field in it
        beta = rot.quat_to_dcm(init.q[0]) @ (b[0] * rk.UT_PER_T)
        kf.set_nominal(t[0], np.array([1.0, 0.0, 0.0, 0.0]), init.w_radps[0], beta_uT=beta, euler=True)
    else:
        kf.set_nominal(t[0], init.q[0], _start_rate(init), euler=True)
    z = b * rk.UT_PER_T
    sb = sigma_b_T * rk.UT_PER_T
    hi_sigma = None if hard_iron_sigma_T is None else np.broadcast_to(np.asarray(hard_iron_sigma_T, float), (3,))
    fit_bias = hi_sigma is not None and bool(np.all(hi_sigma > 0)) and field_eci_T is not None
    if fit_bias:
        kf.bias_uT = np.zeros(3)
    nn = _n_params(kf)
    free = np.ones(nn, bool)
    if field_eci_T is None:
        free[:3] = False  # δθ₀ is the gauge
    prior_w = np.zeros(nn)
    prior_w[6:6 + kf.n_p] = 1.0  # weak prior on the shape: 1-σ of a factor e
    if fit_bias:
        prior_w[kf.n:] = 1.0 / (hi_sigma * rk.UT_PER_T)
    windows = []
    n = min(N, max(first_window, 5))
    while True:
        windows.append(n)
        if n >= N:
            break
        n = min(N, int(math.ceil(n * growth)))
    # rate and shape over growing windows, then the angle about B over the whole record: the angle is
    # fixed only by the field's slow turning, so short windows cannot choose it and the cost has
    # several minima in it
    for n in windows:
        kf, cost = _lm(kf, t, z, sb, n, free, prior_w, iterations)
    cands = [(kf, cost)]
    if field_eci_T is not None:
        b_i0 = np.asarray(field_eci_T(t[0]), float)
        axis = b_i0 / np.linalg.norm(b_i0)
        for a in range(1, starts_about_b):
            other = _apply(kf, np.zeros(int(free.sum())), free)
            other.q = rot.quat_mul(rot.quat_exp(axis * (2 * math.pi * a / starts_about_b)), kf.q)
            cands.append(_lm(other, t, z, sb, N, free, prior_w, 3))
        cands.sort(key=lambda kc: kc[1])
        kf, cost = _lm(cands[0][0], t, z, sb, N, free, prior_w, iterations)
        for _ in range(wahba_rounds):
            other = _apply(kf, np.zeros(int(free.sum())), free)
            other.q = _wahba_start(kf, t, z, field_eci_T, N)
            other, c = _lm(other, t, z, sb, N, free, prior_w, iterations)
            if not np.isfinite(c) or c >= cost - 1e-6:
                break
            kf, cost = other, c
        cands.insert(0, (kf, cost))
    cands.sort(key=lambda kc: kc[1])
    return _Minimum(cands, t, z, sb, b, sigma_b_T, N, free, prior_w, windows, iterations)


@dataclass
class _Minimum:
    """The batch fit's best minimum (its χ²/dof final), before the search for other minima as good (which
    widens σ only): :func:`euler_fit_checked` compares two fits by χ²/dof and finishes only the one it keeps."""
    cands: list            # (start, cost) best first
    t: np.ndarray
    z: np.ndarray
    sb: float
    b: np.ndarray
    sigma_b_T: float
    N: int
    free: np.ndarray
    prior_w: np.ndarray
    windows: list
    iterations: int
    chi2_dof: float = math.nan

    def __post_init__(self):
        kf = self.cands[0][0]
        self.local = _local_solution(kf, self.t, self.z, self.sb, self.N, self.free, self.prior_w)
        self.chi2_dof = self.local[3] / max(3 * self.N - int(self.free.sum()), 1)

    def finish(self) -> Smoothed:
        """The fit's result, σ including the other minima as good as the best."""
        t, z, sb, N, free, prior_w, iterations = self.t, self.z, self.sb, self.N, self.free, self.prior_w, \
            self.iterations
        cands = self.cands
        kf, cost = cands[0]
        traj, cov, var, chi2, s2 = self.local
        # other minima as good as this one within a few units of χ² (another attitude about B with a slightly
        # different motion): the posterior has several modes, and the spread between them belongs in σ
        modes = [(0.0, traj.w, var)]
        seen = [kf]  # starts polished, before and after: one that starts where another did ends where it did
        for other, c in cands[1:]:
            if not c - cost < MODE_SEARCH_DCHI2 * s2:
                continue
            if any(_same_start(other, s) for s in seen):
                continue  # its polish would find a minimum already seen (most starts end in the best one)
            seen.append(other)
            other, c = _lm(other, t, z, sb, N, free, prior_w, iterations)
            seen.append(other)
            if not (np.isfinite(c) and c - cost < MODE_KEEP_DCHI2 * s2):
                continue
            o_traj, _, o_var, _, _ = _local_solution(other, t, z, sb, N, free, prior_w, s2)
            if any(np.max(np.abs(o_traj.w - w_m) / np.sqrt(v + 1e-18)) < 0.3 for _, w_m, v in modes):
                continue  # the same minimum again (within a third of its σ)
            modes.append((max(c - cost, 0.0) / s2, o_traj.w, o_var))
        weights = np.exp(-0.5 * np.array([d for d, _, _ in modes]))
        weights /= weights.sum()
        between = sum(wt * (w_m - traj.w) ** 2 for wt, (_, w_m, _) in zip(weights, modes))
        sig = np.sqrt(sum(wt * v for wt, (_, _, v) in zip(weights, modes)) + between)
        shape = kf.inertia_shape if kf.n_p else None
        info = {"s2": s2, "windows": self.windows, "cov_x0": cov, "beta_uT": kf.beta.copy(), "p": kf.p.copy(),
                "minima_chi2": [c for _, c in cands], "modes_dchi2": [d for d, _, _ in modes],
                "modes_weight": weights.tolist(), "modes_var_radps2": between}
        if _bias(kf) is not None:
            info["hard_iron_residual_uT"] = _bias(kf).copy()
            info["hard_iron_residual_sigma_uT"] = np.sqrt(np.clip(np.diag(cov)[kf.n:], 0.0, None))
        return Smoothed(t, traj.w, unobserved_sigma(sig, self.b, self.sigma_b_T), traj.q, "euler", self.chi2_dof,
                        shape, info=info)


def _local_solution(kf, t, z, sb, n, free, prior_w, s2: float | None = None):
    """The trajectory at a minimum, its state covariance s²(JᵀJ + W²)⁻¹ at t₀ (s² = max(1, χ²/dof)
    unless given) and the variance of ω at every sample through the transition matrices;
    (trajectory, covariance, ω variances (n, 3), χ², s²)."""
    nn = _n_params(kf)
    traj = _trajectory(kf, t, z, sb, n)
    A = traj.Jr.reshape(-1, nn)[:, free]
    r = traj.r.reshape(-1)
    chi2 = float(r @ r)
    if s2 is None:
        s2 = max(1.0, chi2 / max(r.size - int(free.sum()), 1))
    cov = np.zeros((nn, nn))
    cov[np.ix_(free, free)] = s2 * np.linalg.pinv(A.T @ A + np.diag(prior_w[free] ** 2))
    cx = cov[:kf.n, :kf.n]  # ω depends on the start state alone (the offset's share is in its marginal)
    Pw = traj.Phi[:, 3:6, :] @ cx @ traj.Phi[:, 3:6, :].transpose(0, 2, 1)
    return traj, cov, np.clip(np.einsum("kii->ki", Pw), 0.0, None), chi2, s2


def euler_fit_from_filter(t_s: np.ndarray, b_T: np.ndarray, sigma_b_T: float, *,
                          field_eci_T: FieldFn | None = None, hard_iron_sigma_T=None
                          ) -> Smoothed | None:
    """:func:`_minimum_from_filter`, finished (the other minima as good in σ); None where it gives none."""
    m = _minimum_from_filter(t_s, b_T, sigma_b_T, field_eci_T=field_eci_T, hard_iron_sigma_T=hard_iron_sigma_T)
    return None if m is None else m.finish()


def _minimum_from_filter(t_s: np.ndarray, b_T: np.ndarray, sigma_b_T: float, *,
                         field_eci_T: FieldFn | None = None, hard_iron_sigma_T=None
                         ) -> "_Reversed | None":
    """The batch fit of :func:`euler_fit` started from where the parallel-hypothesis Euler filter
    (:class:`fsw.estimation.filter_banks.EulerAcquisitionKalman`) ends, for the records where the random-walk
    start leads the fit astray (a 3 s step at 15–28 °/s: the random-walk smoother lags the turning ω).
    The filter's estimate is good at the record's end, not at its start, so the fit runs in reversed
    time: t' = t_N − t, ω'(t') = −ω(t_N − t'), the same attitudes in reverse order; torque-free Euler
    and the kinematics are the same equations in t' (J ω̇' = −ω' × Jω', q̇' = ½ q' ⊗ ω'). The result
    is mapped back. None when the filter did not lock on Euler's equations or a field model is missing
    (without one the attitude's gauge is the first sample's)."""
    if field_eci_T is None:
        return None
    t = np.asarray(t_s, float)
    b = np.asarray(b_T, float)
    kf = fb.EulerAcquisitionKalman(sigma_b_T, field_eci_T=field_eci_T)
    with np.errstate(all="ignore"):  # a wrong hypothesis may diverge: the filter drops it
        for k in range(len(t)):
            kf.update(t[k], b[k])
    if not kf.euler or kf.flags & rk.NO_ESTIMATE:
        return None
    t_end = float(t[-1])
    tr = t_end - t[::-1]
    n = len(t)
    init = Smoothed(tr, np.tile(-kf.omega_radps, (n, 1)), np.tile(kf.sigma_radps, (n, 1)),
                    np.tile(kf.main.q, (n, 1)), "euler_acquisition")
    rev = _euler_minimum(tr, b[::-1], sigma_b_T, field_eci_T=lambda s: field_eci_T(t_end - s), init=init,
                         hard_iron_sigma_T=hard_iron_sigma_T)
    return _Reversed(rev, t)


@dataclass
class _Reversed:
    """A minimum of the fit in reversed time, finished and mapped back to forward time."""
    rev: "_Minimum"
    t: np.ndarray

    @property
    def chi2_dof(self) -> float:
        return self.rev.chi2_dof

    def finish(self) -> Smoothed:
        rev, t = self.rev.finish(), self.t
        return _to_forward_time(rev, t)


def _to_forward_time(rev: Smoothed, t: np.ndarray) -> Smoothed:
    """A reversed-time fit's result in forward time."""
    # the fit's state covariance is at t_N; only the shape's block (time-invariant) holds at t₀
    cov = np.zeros_like(rev.info["cov_x0"])
    cov[6:, 6:] = rev.info["cov_x0"][6:, 6:]
    info = dict(rev.info, reversed=True, cov_x0=cov, modes_var_radps2=rev.info["modes_var_radps2"][::-1].copy())
    return Smoothed(t, -rev.w_radps[::-1].copy(), rev.sigma_radps[::-1].copy(), rev.q[::-1].copy(), "euler",
                    rev.chi2_dof, rev.inertia_shape, info=info)


def euler_fit_checked(t_s: np.ndarray, b_T: np.ndarray, sigma_b_T: float, *, field_eci_T: FieldFn | None = None,
                      inertia_kgm2: np.ndarray | None = None, init: Smoothed | None = None,
                      chi2_accept: float = 1.5, hard_iron_sigma_T=None) -> Smoothed:
    """:func:`euler_fit`; when it does not explain the data (χ²/dof > `chi2_accept`) and the tensor is
    not known, again from other starts, keeping the lowest χ²/dof: the same start with a longer first window
    (:func:`_longer_first_windows`: in a few samples the fit can wander off a good start, the shape being
    unseen there), the start's rate along B moved by `ALONG_B_START_SIGMAS` of its own 1-σ there
    (:func:`_along_b_starts`), and the Euler filter's end (:func:`euler_fit_from_filter`); the search stops at
    the first that explains the data."""
    # the fits compared by their best minima's χ²/dof: only the one kept searches for other minima (the
    # search, which widens σ only, polishes every start within 30·s² of the best: all of them on a fit that
    # does not explain the data, most of the cost of the fit)
    t = np.asarray(t_s, float)
    field_eci_T = tabulated(field_eci_T, t)
    init = init or rts_smooth(t, b_T, sigma_b_T, field_eci_T=field_eci_T)
    best = _euler_minimum(t, b_T, sigma_b_T, field_eci_T=field_eci_T, inertia_kgm2=inertia_kgm2, init=init,
                          hard_iron_sigma_T=hard_iron_sigma_T)
    if inertia_kgm2 is not None:
        return best.finish()
    first, tried = best.chi2_dof, 1

    def others():
        for fw in _longer_first_windows(len(t)):
            yield lambda fw=fw: _euler_minimum(t, b_T, sigma_b_T, field_eci_T=field_eci_T, init=init, first_window=fw,
                                               hard_iron_sigma_T=hard_iron_sigma_T)
        for start in _along_b_starts(init, b_T):
            yield lambda s=start: _euler_minimum(t, b_T, sigma_b_T, field_eci_T=field_eci_T, init=s,
                                                 hard_iron_sigma_T=hard_iron_sigma_T)
        yield lambda: _minimum_from_filter(t, b_T, sigma_b_T, field_eci_T=field_eci_T,
                                           hard_iron_sigma_T=hard_iron_sigma_T)

    for fit in others():
        if np.isfinite(best.chi2_dof) and best.chi2_dof <= chi2_accept:
            break
        try:
            other = fit()
        except (RuntimeError, ValueError, np.linalg.LinAlgError):
            continue
        tried += 1
        if other is not None and np.isfinite(other.chi2_dof) and not other.chi2_dof >= best.chi2_dof:
            best = other
    res = best.finish()
    if tried > 1:
        res.info["first_chi2_dof"] = first
        res.info["starts_tried"] = tried
    return res


#: the batch fit's other starts where the first is rejected: the start's rate along B at t₀ (what the random-walk
#: smoother sees least: 20 °/s off at 23 °/s and 1.5 µT) moved by these multiples of its own 1-σ there
ALONG_B_START_SIGMAS = (1.0, -1.0, 2.0, -2.0, 3.0, -3.0)


def _longer_first_windows(n: int, factor: int = 4) -> list[int]:
    """The growing windows' first window, longer than FIRST_WINDOW by `factor` each time up to the whole record of
    `n` samples."""
    out, fw = [], FIRST_WINDOW * factor
    while fw < n:
        out.append(fw)
        fw *= factor
    return out + [n]


def _along_b_starts(init: Smoothed, b_T: np.ndarray):
    """`init` with its rate at t₀ moved along the first sample's field by ALONG_B_START_SIGMAS of its 1-σ along it."""
    b0 = np.asarray(b_T, float)[0]
    bh = b0 / np.linalg.norm(b0)
    sig = float(np.sqrt(np.sum((bh * init.sigma_radps[0]) ** 2)))
    if not (np.isfinite(sig) and sig > 0.0):
        return
    w0 = _start_rate(init)
    for k in ALONG_B_START_SIGMAS:
        w = init.w_radps.copy()
        w[0] = w0 + k * sig * bh
        yield replace(init, w_radps=w, info={})  # the fit starts from (q[0], w[0])


def _start_rate(init: Smoothed) -> np.ndarray:
    """The rate at t₀ the fit starts from: the smoother's forward pass's where it has one (`w_pass_radps`)."""
    return np.asarray(init.info.get("w_pass_radps", init.w_radps), float)[0]


def _wahba_start(kf, t, z, field_eci_T, n) -> np.ndarray:
    """The attitude at t₀ that best explains all samples for the fitted relative motion.

    With R(t_k) = R₀ R_rel,k: min over R₀ of Σ |R₀ R_rel,k z_k − B_I(t_k)|² (Wahba 1965), solved by
    the SVD of Σ B_I,k (R_rel,k z_k)ᵀ (Markley 1988): the global optimum, whatever the angle about B.
    """
    traj_q = _trajectory(kf, t, z, 1.0, n, jacobian=False).q
    if _bias(kf) is not None:
        z = np.asarray(z, float) - _bias(kf)
    C0t = rot.quat_to_dcm(kf.q).T
    Bm = np.zeros((3, 3))
    for k in range(n):
        u = C0t @ (rot.quat_to_dcm(traj_q[k]) @ z[k])
        Bm += np.outer(np.asarray(field_eci_T(t[k]), float), u)
    U, _, Vt = np.linalg.svd(Bm)
    D = np.diag([1.0, 1.0, np.linalg.det(U) * np.linalg.det(Vt)])
    R0 = U @ D @ Vt
    return rot.quat_from_dcm(R0)


def _same_start(a, b, tol_rad: float = 0.02) -> bool:
    d = rot.quat_log(rot.quat_mul(rot.quat_conj(a.q), b.q))
    return float(np.linalg.norm(d)) < tol_rad and float(np.linalg.norm(a.w - b.w)) < 1e-3


def _lm(kf, t, z, sb, n, free, prior_w, iterations, lam: float = 1e-3):
    """Levenberg–Marquardt on the first n samples from the filter's nominal start; (start, cost)."""
    nn = _n_params(kf)
    cost = math.inf
    for _ in range(iterations):
        traj = _trajectory(kf, t, z, sb, n)
        A = traj.Jr.reshape(-1, nn)[:, free]
        r = traj.r.reshape(-1)
        cost = float(r @ r) + _prior_cost(kf, prior_w)
        if not np.isfinite(cost):
            return kf, math.inf
        # (AᵀA + W² + λ diag) δ = −(Aᵀr + W² p)
        g = A.T @ r + _prior_grad(kf, prior_w)[free]
        JtJ = A.T @ A + np.diag(prior_w[free] ** 2)
        improved = False
        for _ in range(6):
            step = np.linalg.solve(JtJ + lam * np.diag(np.diag(JtJ) + 1e-12), -g)
            trial = _apply(kf, step, free)
            try:
                with np.errstate(invalid="ignore", over="ignore"):  # a step too far: a non-finite cost, refused
                    tr = _trajectory(trial, t, z, sb, n, jacobian=False)
                tc = float(tr.r.reshape(-1) @ tr.r.reshape(-1)) + _prior_cost(trial, prior_w)
            except (ValueError, OverflowError, FloatingPointError):
                tc = math.inf
            if np.isfinite(tc) and tc < cost:
                kf, improved = trial, True
                lam = max(lam / 5.0, 1e-9)
                break
            lam *= 10.0
        if not improved:
            break
        if cost - tc < 1e-3 * max(1.0, 1e-3 * cost):
            cost = tc
            break
        cost = tc
    return kf, cost


def _prior_cost(kf, w) -> float:
    cost = float(np.sum((w[6:6 + kf.n_p] * kf.p) ** 2)) if kf.n_p else 0.0
    if _bias(kf) is not None:
        cost += float(np.sum((w[kf.n:] * _bias(kf)) ** 2))
    return cost


def _prior_grad(kf, w) -> np.ndarray:
    g = np.zeros(_n_params(kf))
    if kf.n_p:
        g[6:6 + kf.n_p] = w[6:6 + kf.n_p] ** 2 * kf.p
    if _bias(kf) is not None:
        g[kf.n:] = w[kf.n:] ** 2 * _bias(kf)
    return g


def _apply(kf: ak.AttitudeRateKalman, step: np.ndarray, free: np.ndarray) -> ak.AttitudeRateKalman:
    """A copy of the filter's nominal start state moved by the error-state step."""
    d = np.zeros(_n_params(kf))
    d[free] = step
    new = ak.AttitudeRateKalman.__new__(ak.AttitudeRateKalman)
    new.__dict__.update(kf.__dict__)
    new.q = rot.quat_mul(kf.q, rot.quat_exp(d[:3]))
    new.q /= np.linalg.norm(new.q)
    new.w = kf.w + d[3:6]
    new.p = kf.p + d[6:6 + kf.n_p]
    new.beta = kf.beta + d[kf.i_beta:kf.n] if kf.n_beta else kf.beta
    if _bias(kf) is not None:
        new.bias_uT = _bias(kf) + d[kf.n:]
    return new
