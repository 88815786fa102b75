"""Both models together: the Euler RTS smoother started from the batch fit (:func:`euler_rts_smooth`), and
"auto" (:func:`smooth`, :func:`auto_result`): the solution no other solution's σ excludes (the rule in the
package's docstring, :mod:`ground.smoother`)."""
from __future__ import annotations

import math

import numpy as np

from fsw.estimation import attitude_kalman as ak
from fsw.estimation.rate_formulas import unobserved_sigma
from fsw.estimation import rate_kalman as rk
from ground import angle_sum, rts_pass

from .batch_fit import euler_fit, euler_fit_checked
from .rts import FieldFn, SHAPE_SIGMA_FLOOR, Smoothed, _chi2, rts, rts_smooth, tabulated, variance_scale


# --- both ------------------------------------------------------------------------------------------

def euler_rts_smooth(t_s: np.ndarray, b_T: np.ndarray, sigma_b_T: float, *, field_eci_T: FieldFn | None = None,
                     inertia_kgm2: np.ndarray | None = None, init: Smoothed | None = None,
                     accels_radps2: tuple[float, ...] = (1e-5, 1e-4, 1e-3, 1e-2)) -> Smoothed:
    """RTS over the Euler-aware attitude filter, for a body that is not quite torque-free.

    Euler's equations, with the tensor known or the shape found by the batch fit (`init`, default
    :func:`euler_fit`), carry the rate between samples; what they do not explain (a magnetic torque,
    an imperfect shape) is process noise on ω, its level chosen by maximum likelihood. The filter
    starts from the batch fit with a loose prior, so it is linearised on a good trajectory from the
    first sample.
    """
    t = np.asarray(t_s, float)
    b = np.asarray(b_T, float)
    field_eci_T = tabulated(field_eci_T, t)
    init = init or euler_fit(t, b, sigma_b_T, field_eci_T=field_eci_T, inertia_kgm2=inertia_kgm2)
    J = inertia_kgm2
    shape = None
    if J is None:
        if init.inertia_shape is not None:
            shape = init.inertia_shape
        else:
            J = np.eye(3)

    def run(accel, store):
        tun = ak.AttitudeKalmanTuning(rate_accel_radps2=accel, adapt_max=1.0, max_substep_rad=0.25,
                                      max_substeps=400)
        kf = ak.AttitudeRateKalman(sigma_b_T, field_eci_T=field_eci_T, inertia_kgm2=J,
                                   estimate_inertia=shape is not None, store=store, tuning=tun)
        n = kf.n
        P0 = np.zeros((n, n))
        P0[3:6, 3:6] = 0.05 ** 2 * np.eye(3)
        start = {"q": init.q[0], "omega_radps": init.w_radps[0], "P": P0}
        if shape is not None:  # the fitted shape with its uncertainty (the fit's covariance, floored)
            start["p"] = np.log(shape[1:])
            cov_p = np.asarray(init.info.get("cov_x0", np.zeros((n, n))))[6:8, 6:8]
            P0[6:8, 6:8] = cov_p + SHAPE_SIGMA_FLOOR ** 2 * np.eye(2)
        if field_eci_T is None:
            start["beta_uT"] = init.info.get("beta_uT")
            P0[kf.i_beta:, kf.i_beta:] = (3 * sigma_b_T * rk.UT_PER_T) ** 2 * np.eye(3)
        else:
            P0[:3, :3] = 0.1 ** 2 * np.eye(3)
        return rts_pass.forward(kf, t, b, start)  # compiled (the filter's own updates where it cannot be)

    fits = {}
    for a in accels_radps2:
        try:
            fits[a] = run(a, False).nll
        except (ValueError, np.linalg.LinAlgError):
            fits[a] = math.inf
    accel = min(fits, key=fits.get)
    kf = run(accel, True)
    q_s, x_s, P_s = rts(kf.log)
    c = variance_scale(kf.log)
    # the batch fit's other minima (another attitude about B, another motion as good): their spread
    # is not in this pass's covariance, which is linearised about one of them
    between = np.asarray(init.info.get("modes_var_radps2", 0.0))
    sig = np.sqrt(c * np.clip(np.einsum("kii->ki", P_s[:, 3:6, 3:6]), 0.0, None) + between)
    chi2 = _chi2(t, b, sigma_b_T, q_s, x_s, field_eci_T)
    if shape is not None:
        shape = np.concatenate([[1.0], np.exp(x_s[0, 3:5])])
    return Smoothed(t, x_s[:, :3].copy(), unobserved_sigma(sig, b, sigma_b_T), q_s, "euler_rts",
                    chi2 / max(3 * len(t) - kf.n, 1), init.inertia_shape if shape is None else shape,
                    info={"rate_accel_radps2": accel, "nll": kf.nll, "resets": kf.resets, "variance_scale": c})


def disagreement(a: Smoothed, b: Smoothed) -> float:
    """RMS over the samples and axes of (ω_a − ω_b) / √(σ_a² + σ_b²): how far two solutions of the same
    record are apart in units of their combined 1-σ. Two estimates from the same data are positively
    correlated, so the variance of their difference is at most σ_a² + σ_b²: for two consistent
    solutions the figure is below about 1; a solution in another minimum of the fit is many σ away."""
    ok = (np.all(np.isfinite(a.w_radps), axis=1) & np.all(np.isfinite(b.w_radps), axis=1)
          & np.all(np.isfinite(a.sigma_radps), axis=1) & np.all(np.isfinite(b.sigma_radps), axis=1))
    if not np.any(ok):
        return math.inf
    v = a.sigma_radps[ok] ** 2 + b.sigma_radps[ok] ** 2
    d2 = (a.w_radps[ok] - b.w_radps[ok]) ** 2 / np.maximum(v, 1e-30)
    return float(np.sqrt(np.mean(d2)))


#: one solution's σ excludes another's estimate when, at more than EXCLUDE_SHARE of the samples, the other
#: lies more than EXCLUDE_Z of the first one's σ away on some axis
EXCLUDE_Z, EXCLUDE_SHARE = 3.0, 0.25


def excludes(by: Smoothed, other: Smoothed, z: float = EXCLUDE_Z, share: float = EXCLUDE_SHARE) -> bool:
    """Whether `by`'s 1-σ excludes `other`'s estimate: |ω_other − ω_by| > z σ_by on some axis at more than
    `share` of the samples where both have one. A precise solution excludes a coarse one that strays
    from it (that is the precise one's claim); a coarse one excludes a precise one only when the precise
    one lies outside the coarse one's own band."""
    ok = (np.all(np.isfinite(by.w_radps), axis=1) & np.all(np.isfinite(other.w_radps), axis=1)
          & np.all(np.isfinite(by.sigma_radps), axis=1))
    if not np.any(ok):
        return False
    d = np.abs(other.w_radps[ok] - by.w_radps[ok]) / np.maximum(by.sigma_radps[ok], 1e-30)
    return float(np.mean(np.max(d, axis=1) > z)) > share


def _nll(res: Smoothed | None) -> float:
    v = math.inf if res is None else res.info.get("nll", math.inf)
    return float(v) if np.isfinite(v) else math.inf


def widened_for_model_error(fit: Smoothed, *refs: Smoothed) -> Smoothed:
    """`fit` with its 1-σ made that of the solution `ref` plus the distance to it: σ² + (ω_fit − ω_ref)² +
    σ_ref² per sample and axis (:func:`model_error_checked` says when), the largest over `refs` when the
    samples prefer none of them. The fit's error is e_fit = (ω_fit − ω_ref) + e_ref: its distance from the
    better-supported solution, taken as known, plus that solution's own error, of variance σ_ref²."""
    if "widened_for_model_error" in fit.info or not refs:
        return fit  # once: a second call would count the same distance twice
    var = fit.sigma_radps ** 2
    extra = np.zeros_like(var)
    for ref in refs:
        d2 = (fit.w_radps - ref.w_radps) ** 2
        extra = np.fmax(extra, np.where(np.isfinite(d2), d2, 0.0) + ref.sigma_radps ** 2)
    var = var + extra
    info = dict(fit.info, widened_for_model_error="+".join(r.method for r in refs))
    return Smoothed(fit.t_s, fit.w_radps, np.sqrt(var), fit.q, fit.method, fit.chi2_dof, fit.inertia_shape,
                    info=info)


#: the χ² test of a fit's misfit: its normal approximation's z at 0.1 % (one-sided)
CHI2_TEST_Z = 3.09


def chi2_consistent(res: Smoothed, z: float = CHI2_TEST_Z) -> bool:
    """Whether a fit's χ²/dof is within what the samples' noise alone gives: χ² over ν = 3N degrees of
    freedom has mean ν and spread √(2ν), so χ²/dof ≤ 1 + z √(2/ν) (z = 3.09: exceeded by chance in 0.1 %
    of records). A misfit beyond it is a model error, however small (1.3 on 360 samples is 5σ)."""
    nu = 3 * max(len(res.t_s), 1)
    return bool(np.isfinite(res.chi2_dof) and res.chi2_dof <= 1.0 + z * math.sqrt(2.0 / nu))


def model_error_checked(rw: Smoothed, eu: Smoothed | None, er: Smoothed | None,
                        chi2_accept: float = 1.5) -> tuple[Smoothed | None, Smoothed | None]:
    """The batch fit and the Euler RTS smoother with a σ that holds their model's error where the data
    show one: (eu, er), each widened by :func:`widened_for_model_error` or as it was.

    A covariance says what the samples fix *given* the model. Euler's equations carry information
    from every sample to every other, most of all about the rate along B, which the samples alone
    barely see; when the motion is not what the model says (a libration held by the orbital frame, a
    magnetic torque), that information is void and the error is a bias that no rescaling by χ²/dof
    reaches (the accuracy benchmark's orbital rows: the batch fit 3–27 °/s off a 1.6 °/s libration
    with a σ of a few tenths, covering 5–9 %; the Euler RTS smoother started from it 18–47 %).
    Two tests of the model, both on the samples:

    - the batch fit fails its χ² test (:func:`chi2_consistent`, or χ²/dof > `chi2_accept`: the
      torque-free motion does not explain the samples): its σ is widened to the likelier (by the
      samples' likelihood, the passes' innovation `nll`; both when they are within a few units,
      :func:`likeliest`) of the two smoothers that do explain them, the Euler RTS smoother (Euler's
      equations plus a process noise for what they miss) or the random-walk one (no dynamics);
    - the Euler RTS smoother explains the samples (its process noise absorbs the torque) yet the
      random-walk smoother, which assumes no dynamics, explains them as well or better (:func:`likeliest`)
      and its σ excludes the Euler smoother's estimate (:func:`excludes`): the dynamics pulled the estimate where
      the samples do not; its σ is widened to the random-walk smoother's.
    """
    refs = likeliest(rw, er)
    if eu is not None and not (_explains(eu, chi2_accept) and chi2_consistent(eu)):
        eu = widened_for_model_error(eu, *refs)
    if er is not None and np.isfinite(_nll(rw)) and any(r is rw for r in refs) and excludes(rw, er):
        er = widened_for_model_error(er, rw)
    return eu, er


def likeliest(rw: Smoothed, er: Smoothed | None, dnll: float = angle_sum.PASS_TEMPER) -> list[Smoothed]:
    """The smoothers the samples prefer: the one of lower `nll` and the other too when it is within `dnll`
    of it (the smoother's own temper of pass likelihoods, `ground.angle_sum.PASS_TEMPER`: the field model's
    error shifts a pass's likelihood by a few units, so closer than that the samples prefer neither)."""
    sols = [r for r in (er, rw) if r is not None]
    best = min(_nll(r) for r in sols)
    if not np.isfinite(best):
        return [rw]
    return [r for r in sols if _nll(r) <= best + dnll]


def _explains(res: Smoothed | None, chi2_accept: float) -> bool:
    return res is not None and np.isfinite(res.chi2_dof) and res.chi2_dof <= chi2_accept


def auto_order(eu: Smoothed | None, er: Smoothed | None, chi2_accept: float = 1.5,
               z_accept: float = 3.0, rw: Smoothed | None = None) -> list[str]:
    """The candidates of "auto" in its order of preference: the batch fit when it explains the data and
    agrees with the Euler RTS smoother, that smoother when it ran without a restart, the random walk; the
    random walk before the Euler RTS smoother when it explains the samples better (a lower `nll` than
    that smoother's: Euler's equations then add nothing the samples support, as on a libration held by
    the orbital frame, where they pulled the rate along B 3–24 °/s off)."""
    order = []
    if _explains(eu, chi2_accept) and (er is None or disagreement(eu, er) <= z_accept):
        order.append("euler")
    rest = ["euler_rts", "random_walk"]
    if rw is not None and er is not None and _nll(rw) < _nll(er):
        rest.reverse()
    if er is None or er.info.get("resets", 1) != 0:
        rest.remove("euler_rts")
    return order + rest


def auto_choice(eu: Smoothed | None, er: Smoothed | None, chi2_accept: float = 1.5, z_accept: float = 3.0,
                rw: Smoothed | None = None) -> str:
    """The model "auto" keeps: "euler" (the batch fit) when it explains the data (χ²/dof ≤ `chi2_accept`)
    and agrees with the Euler RTS smoother (:func:`disagreement` ≤ `z_accept`; a χ² test alone accepts
    a fit in a wrong minimum: χ²/dof 1.12 with 5.7 °/s of error where the RTS smoother had 0.64 °/s);
    else "euler_rts" when that smoother ran without a restart; else "random_walk" (that before "euler_rts"
    when it explains the samples better, :func:`auto_order`).

    And never a fit that another solution's σ excludes (:func:`excludes`), among the candidates of that
    order (:func:`auto_order`) that explain the data (χ²/dof ≤ `chi2_accept`; the random-walk smoother
    `rw` always counts: it assumes least): the first that no other candidate excludes. When every one is excluded by
    another (the solutions disagree beyond their σ and the data do not say which is right), the first
    is kept and :func:`auto_smooth` widens its σ to cover the others."""
    order = auto_order(eu, er, chi2_accept, z_accept, rw)
    sols = {"euler": eu, "euler_rts": er, "random_walk": rw}
    judges = [(name, res) for name, res in sols.items() if res is not None and name in order
              and (name == "random_walk" or _explains(res, chi2_accept))]
    for name in order:
        if sols[name] is None or not any(excludes(res, sols[name]) for other, res in judges if other != name):
            return name
    return order[0]


def covering(chosen: Smoothed, others: list[Smoothed]) -> Smoothed:
    """`chosen` with its 1-σ widened so that each of `others` whose σ excludes it lies within 1-σ:
    σ² + max over them of (ω_other − ω_chosen)², per sample and axis (the spread between solutions that
    the data do not tell apart is part of the uncertainty). A coarser solution that `chosen` excludes
    but whose own σ admits `chosen` widens nothing."""
    var = chosen.sigma_radps ** 2
    extra = np.zeros_like(var)
    for o in others:
        if excludes(o, chosen):
            d2 = (o.w_radps - chosen.w_radps) ** 2
            extra = np.fmax(extra, np.where(np.isfinite(d2), d2, 0.0))
    if not np.any(extra):
        return chosen
    info = dict(chosen.info, widened_to_cover="other solutions")
    return Smoothed(chosen.t_s, chosen.w_radps, np.sqrt(var + extra), chosen.q, chosen.method, chosen.chi2_dof,
                    chosen.inertia_shape, info=info)


def smooth(t_s: np.ndarray, b_T: np.ndarray, sigma_b_T: float, *, field_eci_T: FieldFn | None = None,
           model: str = "auto", inertia_kgm2: np.ndarray | None = None, chi2_accept: float = 1.5,
           z_accept: float = 3.0, hard_iron_sigma_T=None) -> Smoothed:
    """Smooth a recording. `model`: "random_walk" (:func:`rts_smooth`), "euler" (:func:`euler_fit`),
    "euler_rts" (:func:`euler_rts_smooth`) or "auto" (:func:`auto_choice`): the batch Euler fit when it
    explains the data (χ²/dof ≤ `chi2_accept`) and agrees with the Euler-aware RTS smoother started
    from it (within `z_accept` combined σ), else that smoother, else (if it had to restart: the motion
    is not Euler's) the random-walk RTS smoother. `hard_iron_sigma_T`: the applied host calibration's
    hard-iron 1-σ (per axis or one for all): the batch fit takes a constant offset in body axes with that
    prior (:func:`euler_fit`), and the Euler RTS smoother the samples less the offset it found."""
    if model not in ("auto", "random_walk", "euler", "euler_rts"):
        raise ValueError(f"model must be auto, random_walk, euler or euler_rts, got {model!r}")
    rw = rts_smooth(t_s, b_T, sigma_b_T, field_eci_T=field_eci_T)
    if model == "random_walk":
        return rw
    try:
        eu = euler_fit_checked(t_s, b_T, sigma_b_T, field_eci_T=field_eci_T, inertia_kgm2=inertia_kgm2, init=rw,
                               chi2_accept=chi2_accept, hard_iron_sigma_T=hard_iron_sigma_T)
    except (RuntimeError, ValueError, np.linalg.LinAlgError):
        if model == "auto":
            return rw
        raise
    if model == "euler" and _explains(eu, chi2_accept) and chi2_consistent(eu):  # else measured below
        eu.info["rts_chi2_dof"] = rw.chi2_dof
        return eu
    er = euler_rts_after_fit(t_s, b_T, sigma_b_T, eu, field_eci_T=field_eci_T, inertia_kgm2=inertia_kgm2)
    z = disagreement(eu, er)
    for res in (rw, eu, er):
        res.info.update(euler_chi2_dof=eu.chi2_dof, rts_chi2_dof=rw.chi2_dof, euler_vs_rts_z=z)
    eu, er = model_error_checked(rw, eu, er, chi2_accept)
    if model == "euler":
        return eu
    if model == "euler_rts":
        return er
    return auto_result(rw, eu, er, chi2_accept, z_accept)


def euler_rts_after_fit(t_s: np.ndarray, b_T: np.ndarray, sigma_b_T: float, fit: Smoothed, *,
                        field_eci_T: FieldFn | None = None, inertia_kgm2: np.ndarray | None = None) -> Smoothed:
    """:func:`euler_rts_smooth` started from the batch fit `fit`, on the samples less the constant offset in
    body axes the fit found (`hard_iron_residual_uT`; its own model has none)."""
    off = fit.info.get("hard_iron_residual_uT")
    b = b_T if off is None else np.asarray(b_T, float) - np.asarray(off) / rk.UT_PER_T
    return euler_rts_smooth(t_s, b, sigma_b_T, field_eci_T=field_eci_T, inertia_kgm2=inertia_kgm2, init=fit)


def auto_result(rw: Smoothed, eu: Smoothed | None, er: Smoothed | None, chi2_accept: float = 1.5,
                z_accept: float = 3.0) -> Smoothed:
    """What "auto" returns: :func:`auto_choice`'s solution; when another solution that explains the data
    excludes it (all of them exclude each other), with its σ widened to cover them (:func:`covering`). The
    fits' σ first hold their model's error where the samples show one (:func:`model_error_checked`)."""
    eu, er = model_error_checked(rw, eu, er, chi2_accept)
    sols = {"euler": eu, "euler_rts": er, "random_walk": rw}
    choice = auto_choice(eu, er, chi2_accept, z_accept, rw=rw)
    chosen = sols[choice]
    order = auto_order(eu, er, chi2_accept, z_accept, rw)
    others = [res for name, res in sols.items() if name != choice and res is not None and name in order
              and (name == "random_walk" or _explains(res, chi2_accept))]
    out = covering(chosen, others)
    out.info["auto_choice"] = choice
    return out
