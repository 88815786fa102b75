"""Accuracy benchmark of the rate estimators: seeded Monte-Carlo SITL runs, a table shaped like
sedelnikov2024 Table 3.

    python -m bench.accuracy                       # the full table, 3 runs per row (~17 min on 1 core)
    python -m bench.accuracy --runs 20 --json acc.json   # docs/rate-estimation.md's table (~46 min on 2 cores)
    python -m bench.accuracy --runs 20 --results acc.parquet   # kept run by run: resumable, --rerun ID
    python -m bench.accuracy --quick               # two rows, one run each: a smoke test
    python -m bench.accuracy --rows orbital --methods smoother   # a subset of rows; boer + the ground smoothers
    python -m bench.accuracy --world igrf --runs 20 --json acc_igrf.json   # the IGRF-truth rows

Every run is a task of a campaign (bench.campaign, docs/campaigns.md): on a local cluster of a worker per core
by default (``--workers N``), on a Dask cluster with ``--scheduler tcp://HOST:8786``; run r of a row is seeded
by the row's position and r, so the table does not depend on the number of workers.

Rows: mode × sampling step (1 s, 3 s) × noise (0.5 µT, the paper's 1.5 µT) × body.

Modes (sedelnikov2024 Table 3 ranges):
- ``undirected`` — free tumble, |ω| drawn in 5–28 °/s, no torque;
- ``bdot`` — |ω| in 5–23 °/s decaying under a −Ḃ magnetic law: the dipole m = −k (B_k − B_{k−1})/Δt
  from the last two measured samples, held until the next sample (saturated per axis at the value a
  10 °/s tumble asks for), torque M = m × B; k gives a damping time J̄/(k|B|²) = 30 min (|B| = 35 µT).
  The torquers' own field reaches the magnetometer: δB = 0.3 µT · m/m_max (the paper notes that the
  actuators disturb the measurement in this mode). Estimators are not told the torque;
- ``orbital`` — orbital orientation: the attitude follows the orbital frame (x along the velocity,
  z to nadir) with a libration θ(t) = Σ aᵢ sin(2πt/Tᵢ + φᵢ) about each axis (periods 40–120 s),
  scaled so that the RMS of |ω| is drawn in 0.5–3 °/s; kinematic (flywheels do whatever it takes), so
  the body's inertia plays no part.

Bodies: ``asymmetric`` = Aist-2D, diag(175, 200, 285) kg·m² (sedelnikov2023); ``near_symmetric`` =
diag(1.00, 1.02, 1.04) (ω nearly constant in body axes).

Worlds (``--world``): ``dipole`` — the true field is the IGRF-14 dipole along a 485 km, 97.5° circular
orbit with random node and phase, the very model the estimators are given; ``igrf`` (rows keyed
``…/igrf``) — the truth is IGRF-14 to degree 13 along the shipped ``isoi_sgp4`` TLE through SGP4 (a
random start within a day of its epoch), the host's hard and soft iron and its thermal drift in the
measurement, taken out by the box's calibration off by the calibration benchmark's residual (0.15 µT
per axis, 0.2 % soft iron; the calibration follows the drift as the box's does, a harmonic of the orbit —
``--host-drift untracked``: a constant calibration, the drift left in the samples, rows keyed
``…/igrf-constant-cal``), and the estimators given what the box would have: the field of the onboard model
(IGRF-14 at the flight degree) along the 3-day-older box TLE, at the box's clock 2 s ahead;
``igrf_exact`` (rows ``…/igrf-exact``) — the same truth, the box knowing it exactly (the truth's field at
the true time, no host): an IGRF row against its ``igrf_exact`` row is what the box's knowledge costs,
against the dipole row also what the other orbit and field cost (the same motions and noise, seen along
another path through another field).

Samples: the true field (random attitude and rate) plus white Gaussian noise σ_B per axis, the
MMC5983MA's own noise at BW = 100 Hz (0.04 µT) and its 18-bit quantisation (6.1 nT), at the sampling
step (the register-level emulator is not stepped here, for speed; tests/test_sitl_e2e.py runs the whole
loop).

Each run: the onboard filters run from t = 0 over a warm-up (`warmup_s`, as they would in flight) and
the scored record of `record_samples` samples; the formulas and the ground smoothers see only the
record. Errors are taken against the truth at the sample times, pooled over the runs of a row:
the full vector (for the methods that estimate it) and the part perpendicular to the true B.
A method that gives nothing on a run (a batch fit that cannot be evaluated) is counted there
(`failed_runs`, `missing_samples` for non-finite rows) and is not eligible as a row's best method.
Coverage: share of per-axis errors inside ±1σ, with its spread over the runs (a run's error is one
draw for all its samples: `coverage_se`, `runs_for_coverage_pm10` in the JSON). Orbital rows also
carry the information limit of the random-walk model on the record (:func:`information_limit`).

Methods: ``boer`` (perpendicular), ``derivative``, ``kotelnikov`` (series, analytic form); onboard:
``kalman`` (fsw RateKalman, fixed field, the filter flown by default), ``kalman_orbit`` (attitude
filter with the field along the orbit), ``kalman_euler`` (that plus Euler's equations with the inertia
shape estimated, acquired by parallel shape hypotheses, with the hypotheses over the angle about B as flown:
filter_banks.EulerAcquisitionKalman), ``kalman_mm``
(the attitude filter as a bank of rate models, random walk and Gauss–Markov, the likeliest
publishing: filter_banks.RateModelBank); ground:
``smoother`` (RTS with the field model), ``euler`` (batch torque-free fit with the field model),
``euler_rts`` (RTS over the Euler filter), ``auto`` (ground.smoother.auto_result: the Euler fit when
χ²/dof ≤ 1.5 and it agrees with the Euler RTS smoother within 3 combined σ, else that smoother, else
the random-walk RTS smoother — before it when likelier; never one that another's σ excludes, σ widened
where all disagree). ``euler`` and ``euler_rts`` as ground.smoother.smooth returns them: σ widened for
a model the samples reject (ground.smoother.model_error_checked; which, per run, in the JSON's meta).
"""
from __future__ import annotations

import functools
import json
import math
import sys
import time
from dataclasses import dataclass

import numpy as np

from fsw.argtypes import ArgumentParser, check_paths_or_exit, finite_float, int_range
from fsw.estimation import attitude_kalman as ak
from fsw.estimation import filter_banks as fb
from fsw.estimation import kotelnikov as ko
from fsw.estimation import rate_formulas as rf
from fsw.estimation import rate_kalman as rk
from fsw.estimation import rotations as rot
from fsw.files import write_atomic
from ground import smoother as sm
from bench.campaign import Run as Run_
from bench.campaign import options as campaign_options
from bench.campaign import run_campaign
from bench.accuracy_world import BODIES, CHIP_NOISE_T, IGRF_EXACT, MODES, WORLDS, Run, simulate


ONBOARD = ("kalman", "kalman_orbit", "kalman_euler", "kalman_mm")
GROUND = ("smoother", "euler", "euler_rts", "auto")
FULL = ("derivative", "kotelnikov") + ONBOARD + GROUND
METHODS = ("boer",) + FULL


# --- the information limit --------------------------------------------------------------------------

def information_limit(run: Run, sigma_b_T: float, accel_radps2: float | None = None,
                      sigma_angle0_rad: float = math.pi, sigma_rate0_radps: float = 0.5) -> dict:
    """Posterior Cramér–Rao bound (Tichavský et al. 1998) of ω on the record, linearised on the truth.

    The error state [δθ, δω] (body-frame attitude error, rate error) of the attitude filter's model:
    δθ_{k+1} = exp(−[ω_kΔt]ₓ) δθ_k + Δt J_r(ω_kΔt) δω_k, δω a random walk of per-step variance
    a²Δt; z_k = R_kᵀ B_I(t_k) + v, H_k = [[h_k]ₓ, 0], v ~ N(0, σ_B² I); a diffuse prior (σ_θ = π,
    σ_ω = 0.5 rad/s). For a linear-Gaussian model the RTS covariance is the Bayesian information
    limit: no estimator that knows only this model (and the field along the orbit, and σ_B) can do
    better on average. `accel_radps2` = a; by default the truth's own: a² = mean |Δω|² / (3Δt).
    With a → 0 the motion is "known up to a constant rate offset and the initial attitude", the most
    favourable smooth model. Returns per-sample 1-σ of the component along the true B and the RMS
    over the record of the along-B and full-vector σ (rad/s), smoothed and causal (the filter's bound
    from a diffuse prior at the record's first sample, i.e. without the onboard warm-up).
    """
    rec = run.record
    t, q, w = run.t_s[rec], run.q_true[rec], run.w_true_radps[rec]
    dt = np.diff(t)
    if accel_radps2 is None:
        dw = np.diff(w, axis=0)
        accel_radps2 = math.sqrt(float(np.mean(np.sum(dw ** 2, axis=1) / (3.0 * dt))))
    b_i = np.asarray(run.field.b_eci_T(t), float).reshape(len(t), 3)
    n = len(t)
    Rm = sigma_b_T ** 2 * np.eye(3)
    P = np.diag([sigma_angle0_rad ** 2] * 3 + [sigma_rate0_radps ** 2] * 3)
    Pf, Pp, Fs = np.zeros((n, 6, 6)), np.zeros((n, 6, 6)), np.zeros((n, 6, 6))
    bh = np.zeros((n, 3))
    for k in range(n):
        if k:
            phi = w[k - 1] * dt[k - 1]
            F = np.eye(6)
            F[:3, :3] = rot.so3_exp(-phi)
            F[:3, 3:] = dt[k - 1] * rot.so3_right_jacobian(phi)
            qw = accel_radps2 ** 2 * dt[k - 1]
            d = dt[k - 1]
            Q = np.zeros((6, 6))
            Q[:3, :3] = qw * d * d / 3 * np.eye(3)
            Q[:3, 3:] = Q[3:, :3] = qw * d / 2 * np.eye(3)
            Q[3:, 3:] = qw * np.eye(3)
            P = F @ P @ F.T + Q
            Fs[k] = F
        Pp[k] = P
        h = rot.quat_to_dcm(q[k]).T @ b_i[k]
        bh[k] = h / np.linalg.norm(h)
        H = np.hstack([rot.skew(h), np.zeros((3, 3))])
        S = H @ P @ H.T + Rm
        K = np.linalg.solve(S, H @ P).T
        IKH = np.eye(6) - K @ H
        P = IKH @ P @ IKH.T + K @ Rm @ K.T
        Pf[k] = P
    Ps = Pf.copy()
    for k in range(n - 2, -1, -1):
        C = np.linalg.solve(Pp[k + 1], Fs[k + 1] @ Pf[k]).T
        Ps[k] = Pf[k] + C @ (Ps[k + 1] - Pp[k + 1]) @ C.T
    Pw, Pc = Ps[:, 3:, 3:], Pf[:, 3:, 3:]
    along = np.sqrt(np.einsum("ki,kij,kj->k", bh, Pw, bh))

    def rms(a):
        return float(np.sqrt(np.mean(a)))
    return {"accel_radps2": accel_radps2, "sigma_along_b_radps": along,
            "rms_along_b_radps": rms(along ** 2), "rms_full_radps": rms(np.einsum("kii->k", Pw)),
            "rms_causal_along_b_radps": rms(np.einsum("ki,kij,kj->k", bh, Pc, bh)),
            "rms_causal_full_radps": rms(np.einsum("kii->k", Pc))}


# --- the estimators ---------------------------------------------------------------------------------

def estimate(run: Run, sigma_b_T: float, methods=METHODS) -> dict[str, tuple[np.ndarray, np.ndarray | None]]:
    """Every method's ω (and 1-σ) on the record, each from the data it is allowed to see."""
    rec = run.record
    t, b = run.t_s[rec], run.b_T[rec]
    out: dict[str, tuple[np.ndarray, np.ndarray | None]] = {}
    if "boer" in methods:
        out["boer"] = (rf.boer_rate(t, b), np.sqrt(np.einsum("kii->ki", rf.boer_covariance(t, b, sigma_b_T))))
    if "derivative" in methods:
        out["derivative"] = (rf.derivative_rate(t, b),
                             np.sqrt(np.einsum("kii->ki", rf.derivative_covariance(t, b, sigma_b_T))))
    if "kotelnikov" in methods:
        out["kotelnikov"] = ko.kotelnikov_rate(t, b, sigma_b_T)
    field = sm.tabulated(run.field, run.t_s)
    onboard = {
        "kalman": lambda: rk.kalman_rate(run.t_s, run.b_T, sigma_b_T),
        "kalman_orbit": lambda: ak.attitude_kalman_rate(run.t_s, run.b_T, sigma_b_T, field_eci_T=field),
        "kalman_euler": lambda: fb.euler_acquisition_rate(run.t_s, run.b_T, sigma_b_T, field_eci_T=field,
                                                          about_b_hypotheses=fb.ABOUT_B_HYPOTHESES),
        "kalman_mm": lambda: fb.rate_model_bank_rate(run.t_s, run.b_T, sigma_b_T, field_eci_T=field),
    }
    for name, fn in onboard.items():
        if name in methods:
            w, s, _ = fn()
            out[name] = (w[rec], s[rec])
    if any(m in methods for m in GROUND):
        fld = sm.tabulated(run.field, t)
        rw = sm.rts_smooth(t, b, sigma_b_T, field_eci_T=fld)
        out["smoother"] = (rw.w_radps, rw.sigma_radps)
        eu = er = None
        try:
            eu = sm.euler_fit_checked(t, b, sigma_b_T, field_eci_T=fld, init=rw,
                                      hard_iron_sigma_T=run.hard_iron_sigma_T)
            er = sm.euler_rts_after_fit(t, b, sigma_b_T, eu, field_eci_T=fld)
        except (RuntimeError, ValueError, np.linalg.LinAlgError):
            pass
        eu_raw, er_raw = eu, er
        eu, er = sm.model_error_checked(rw, eu, er)  # as ground.smoother.smooth returns them
        if eu is not None:
            out["euler"] = (eu.w_radps, eu.sigma_radps)
        if er is not None:
            out["euler_rts"] = (er.w_radps, er.sigma_radps)
        # "auto" as ground.smoother.smooth returns it (its choice, σ widened where the solutions disagree)
        auto = sm.auto_result(rw, eu, er)
        out["auto"] = (auto.w_radps, auto.sigma_radps)
        run.meta["euler_chi2_dof"] = None if eu is None else float(eu.chi2_dof)
        run.meta["euler_vs_rts_z"] = None if eu is None or er is None else sm.disagreement(eu_raw, er_raw)
        run.meta["model_error_widened"] = [n for n, r in (("euler", eu), ("euler_rts", er))
                                           if r is not None and "widened_for_model_error" in r.info]
        run.meta["auto_model"] = auto.info["auto_choice"]
        run.meta["auto_widened"] = "widened_to_cover" in auto.info
    return {k: v for k, v in out.items() if k in methods}


def errors(run: Run, est: dict) -> dict[str, dict[str, np.ndarray]]:
    """Per method: full-vector error norms, perpendicular error norms, and per-axis |e|/σ."""
    rec = run.record
    w = run.w_true_radps[rec]
    bh = run.b_true_T[rec] / np.linalg.norm(run.b_true_T[rec], axis=1, keepdims=True)
    out = {}
    for name, (we, se) in est.items():
        ok = np.all(np.isfinite(we), axis=1)
        e = we[ok] - w[ok]
        e_perp = e - np.sum(e * bh[ok], axis=1, keepdims=True) * bh[ok]
        d = {"perp": np.linalg.norm(e_perp, axis=1)}
        if name != "boer":
            d["full"] = np.linalg.norm(e, axis=1)
        if se is not None and name != "boer":
            s = se[ok]
            good = np.all(np.isfinite(s), axis=1)
            d["z"] = (np.abs(e[good]) / np.maximum(s[good], 1e-12)).ravel()
        out[name] = d
    return out


# --- the table --------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Row:
    mode: str
    body: str
    dt_s: float
    sigma_uT: float
    world: str = "dipole"
    drift_tracked: bool = True   # igrf: the box's calibration follows the hard iron's drift (as flown)

    @property
    def key(self) -> str:
        suffix = ("/igrf" + ("" if self.drift_tracked else "-constant-cal")) if self.world == "igrf" else (
            "/igrf-exact" if self.world == IGRF_EXACT else "")
        return f"{self.mode}/{self.body}/dt{self.dt_s:g}/{self.sigma_uT:g}uT{suffix}"


def all_rows(worlds=("dipole",), drift_tracked: bool = True) -> list[Row]:
    return [Row(m, b, dt, s, w, drift_tracked or w != "igrf") for w in worlds for m in MODES for b in BODIES
            for dt in (1.0, 3.0) for s in (0.5, 1.5)]


def row_seed(row: Row, seed: int) -> list[int]:
    """A row's seed: `seed` and the row's position (the same in both worlds: an IGRF row's runs are the dipole
    row's motions and noise in the other world); run r of the row is seeded row_seed + [r]."""
    return [seed, list(MODES).index(row.mode), list(BODIES).index(row.body), int(row.dt_s),
            int(round(10 * row.sigma_uT))]


def run_one(row: Row, seed: list[int], record_samples: int, warmup_s: float, methods=METHODS,
            **dispersed) -> dict:
    """One Monte-Carlo run of a row, seeded `seed`: the per-run errors that run_row pools (`dispersed`: simulate's
    inertia_kgm2, rate_range_dps)."""
    rng = np.random.default_rng(seed)
    run = simulate(row.mode, row.body, row.dt_s, row.sigma_uT * 1e-6, rng, record_samples=record_samples,
                   warmup_s=warmup_s, world=row.world, drift_tracked=row.drift_tracked, **dispersed)
    sigma_b = math.hypot(row.sigma_uT * 1e-6, CHIP_NOISE_T)
    est = estimate(run, sigma_b, methods)
    # a method that gave nothing on a run is counted, not left out of the pool
    out = {"failed": [name for name in methods if name not in est],
           "missing": {name: int(np.sum(~np.all(np.isfinite(est[name][0]), axis=1))) for name in methods
                       if name in est},
           "errors": errors(run, est), "rate_radps": np.linalg.norm(run.w_true_radps[run.record], axis=1)}
    if row.mode == "orbital":  # the information limit of the random-walk model (see information_limit)
        lim = information_limit(run, sigma_b)
        run.meta["information_limit"] = {k: v for k, v in lim.items() if k != "sigma_along_b_radps"}
    out["meta"] = run.meta
    return out


def run_row(row: Row, runs: int, seed: int, record_samples: int, warmup_s: float,
            methods=METHODS) -> dict:
    """Monte-Carlo runs of a row (seed from the row's position and `seed`), here; the pooled statistics."""
    return pool_row(row, [run_one(row, row_seed(row, seed) + [r], record_samples, warmup_s, methods)
                          for r in range(runs)], methods)


def pool_row(row: Row, per_run: list[dict], methods=METHODS) -> dict:
    """The row's statistics from its runs (run_one's results, in the order of the runs)."""
    pooled: dict[str, dict[str, list]] = {m: {"perp": [], "full": [], "z": [], "cov_run": [], "failed": [],
                                              "missing": []} for m in methods}
    rates, meta = [], []
    runs = len(per_run)
    for r, one in enumerate(per_run):
        for name in methods:
            if name in one["failed"]:
                pooled[name]["failed"].append(r)
            else:
                pooled[name]["missing"].append(one["missing"][name])
        for name, d in one["errors"].items():
            for k, v in d.items():
                pooled[name][k].append(v)
            if "z" in d and d["z"].size:
                pooled[name]["cov_run"].append(float(np.mean(d["z"] < 1.0)))
        rates.append(one["rate_radps"])
        meta.append(one["meta"])
    out = {"row": row.__dict__, "key": row.key, "runs": runs,
           "mean_rate_dps": math.degrees(float(np.mean(np.concatenate(rates)))), "methods": {}, "meta": meta}
    for name, d in pooled.items():
        res = {}
        for part in ("full", "perp"):
            if d[part]:
                a = np.concatenate(d[part])
                res[f"{part}_rms_dps"] = math.degrees(float(np.sqrt(np.mean(a ** 2)))) if a.size else math.nan
                res[f"{part}_max_dps"] = math.degrees(float(np.max(a))) if a.size else math.nan
        if d["full"]:  # each run's own RMS: the paired runs of the two worlds resampled (docs/tables.py)
            res["run_rms_dps"] = [math.degrees(float(np.sqrt(np.mean(a ** 2)))) if a.size else math.nan
                                  for a in d["full"]]
        res["failed_runs"] = list(d["failed"])
        res["missing_samples"] = int(sum(d["missing"]))
        if d["z"]:
            z = np.concatenate(d["z"])
            res["coverage_1sigma"] = float(np.mean(z < 1.0)) if z.size else math.nan
            res.update(coverage_spread(d["cov_run"]))
        out["methods"][name] = res
    lims = [m["information_limit"] for m in meta if "information_limit" in m]
    if lims:
        out["information_limit"] = {k.replace("radps", "dps"): math.degrees(math.sqrt(np.mean([d[k] ** 2
                                                                                               for d in lims])))
                                    for k in lims[0] if k.startswith("rms_")}
    boer = out["methods"].get("boer", {}).get("perp_rms_dps", math.nan)

    def best(names):  # among the methods that answered on every run
        cands = [(out["methods"][n]["full_rms_dps"], n) for n in names if n in out["methods"]
                 and "full_rms_dps" in out["methods"][n] and not out["methods"][n]["failed_runs"]]
        return min(cands) if cands else (math.nan, None)

    for label, names in (("onboard", ONBOARD), ("ground", GROUND)):
        v, n = best(names)
        out[f"best_{label}"] = {"method": n, "full_rms_dps": v, "ratio_to_boer_perp": v / boer}
    return out


def coverage_spread(per_run: list[float], half_width: float = 0.10) -> dict:
    """The coverage's own uncertainty. A run's error is one draw for all its samples (the record's few
    poorly known parameters set it), so the runs, not the samples, are the independent trials: the
    standard error of the pooled coverage is the spread of the per-run coverages / √runs, and
    (1.96 · spread / `half_width`)² runs give a 95 % interval ±`half_width` (±10 points resolves
    60–80 % around 70 %)."""
    c = np.asarray(per_run, float)
    if c.size < 2:
        return {"coverage_runs": c.tolist()}
    sd = float(np.std(c, ddof=1))
    return {"coverage_runs": c.tolist(), "coverage_se": sd / math.sqrt(c.size),
            "runs_for_coverage_pm10": int(math.ceil((1.96 * sd / half_width) ** 2))}


def campaign(rows: list[Row], runs: int, seed: int, record_samples: int, warmup_s: float,
             methods=METHODS) -> tuple[list[Run_], dict]:
    """The table as a campaign (bench.campaign): run r of a row is run ``KEY#r``, seeded row_seed + [r]; and the
    configuration that, with each run's seed and parameters, decides the results."""
    specs = [Run_(f"{row.key}#{r}", tuple(row_seed(row, seed) + [r]), {**row.__dict__, "run": r})
             for row in rows for r in range(runs)]
    config = {"benchmark": "bench.accuracy", "record_samples": record_samples, "warmup_s": warmup_s,
              "methods": list(methods)}
    return specs, config


def run_task(run: Run_, *, record_samples: int, warmup_s: float, methods: tuple) -> dict:
    """A campaign's task: one run of a row (the row from the run's parameters)."""
    p = {k: v for k, v in run.params.items() if k != "run"}
    return run_one(Row(**p), list(run.seed), record_samples, warmup_s, methods)


def task(config: dict):
    """run_task with the campaign's configuration (picklable: it goes to the workers)."""
    return functools.partial(run_task, record_samples=config["record_samples"], warmup_s=config["warmup_s"],
                             methods=tuple(config["methods"]))


def tabulate(rows: list[Row], runs: int, per_run: list[dict], config: dict) -> dict:
    """The benchmark's dict (rows pooled, targets) from the campaign's results, in campaign() order."""
    results = [pool_row(row, per_run[i * runs:(i + 1) * runs], tuple(config["methods"])) for i, row in enumerate(rows)]
    return {"config": {"runs": runs, "seed": None, "record_samples": config["record_samples"],
                       "warmup_s": config["warmup_s"], "modes": MODES,
                       "bodies": {k: np.diag(v).tolist() for k, v in BODIES.items()}},
            "rows": results, "targets": targets(results)}


def run_benchmark(rows: list[Row], runs: int = 3, seed: int = 2024, record_samples: int = 120,
                  warmup_s: float = 300.0, log=print, methods=METHODS, **campaign_options) -> dict:
    """The table through the campaign runner (`campaign_options`: run_campaign's workers, scheduler, results,
    progress; default one worker: here)."""
    specs, config = campaign(rows, runs, seed, record_samples, warmup_s, methods)
    progress = _row_progress(rows, runs, methods, log)
    opts = {"workers": 1, "progress": False, **campaign_options}
    per_run = run_campaign(task(config), specs, config={**config, "seed": seed}, name="accuracy",
                           on_result=progress, **opts)
    out = tabulate(rows, runs, per_run, config)
    out["config"]["seed"] = seed
    progress.rest(out)
    return out


def _row_progress(rows: list[Row], runs: int, methods, log):
    """on_result for the campaign: a row's line when its last run completes; its `rest(bench)` logs the rows
    whose runs were (some or all) in the results file already."""
    t0, got, logged = time.monotonic(), {}, set()
    by_key = {row.key: row for row in rows}

    def on_result(run: Run_, result: dict) -> None:
        key = run.id.rsplit("#", 1)[0]
        got.setdefault(key, {})[run.params["run"]] = result
        if len(got[key]) == runs:
            log(_progress(pool_row(by_key[key], [got[key][r] for r in range(runs)], methods), t0))
            logged.add(key)
            del got[key]

    def rest(bench: dict) -> None:
        for res in bench["rows"]:
            if res["key"] not in logged:
                log(_progress(res, t0))
    on_result.rest = rest
    return on_result


def _progress(res, t0) -> str:
    bo, bg = res["best_onboard"], res["best_ground"]
    cov = res["methods"].get(bg["method"] or "", {}).get("coverage_1sigma", math.nan)
    return (f"[{time.monotonic() - t0:6.0f} s] {res['key']:<38s} |ω| {res['mean_rate_dps']:5.1f} °/s  "
            f"Boer⊥ {res['methods']['boer']['perp_rms_dps']:6.3f}  onboard {bo['method']} "
            f"{bo['full_rms_dps']:6.3f} ({bo['ratio_to_boer_perp']:.2f})  ground {bg['method']} "
            f"{bg['full_rms_dps']:6.3f} ({bg['ratio_to_boer_perp']:.3f}) cov {100 * cov:.0f} %")


def targets(results: list[dict]) -> dict:
    """The targets, row by row: onboard ≤ 1/3, ground ≤ 1/10 of Boer⊥ RMS; ground coverage in
    [60 %, 80 %]."""
    out = {"onboard_one_third": [], "ground_one_tenth": [], "ground_coverage_60_80": []}
    for r in results:
        bo, bg = r["best_onboard"], r["best_ground"]
        out["onboard_one_third"].append((r["key"], bo["ratio_to_boer_perp"] <= 1 / 3, bo["ratio_to_boer_perp"]))
        out["ground_one_tenth"].append((r["key"], bg["ratio_to_boer_perp"] <= 0.1, bg["ratio_to_boer_perp"]))
        cov = r["methods"].get(bg["method"] or "", {}).get("coverage_1sigma", math.nan)
        out["ground_coverage_60_80"].append((r["key"], 0.6 <= cov <= 0.8, cov))
    return out


def markdown(bench: dict) -> str:
    """The README table: one line per row, RMS (max) in °/s."""
    head = ("| mode | body | Δt s | σ_B µT | mean \\|ω\\| °/s | Boer ⊥ RMS (max) | derivative | Kotelnikov | "
            "kalman | kalman_euler | kalman_mm | best onboard (÷Boer⊥) | smoother | euler | best ground (÷Boer⊥) | "
            "ground 1σ cov. |")
    lines = [head, "|" + "---|" * 16]
    for r in bench["rows"]:
        m = r["methods"]
        row = r["row"]

        def f(name, part="full", m=m):
            d = m.get(name, {})
            if f"{part}_rms_dps" not in d:
                return "—"
            return f"{d[f'{part}_rms_dps']:.2f} ({d[f'{part}_max_dps']:.1f})"

        bo, bg = r["best_onboard"], r["best_ground"]
        cov = m.get(bg["method"] or "", {}).get("coverage_1sigma", math.nan)
        igrf = " (IGRF)" if row.get("world") == "igrf" else ""
        lines.append(
            f"| {row['mode']}{igrf} | {row['body'].replace('_', '-')} | {row['dt_s']:g} | {row['sigma_uT']:g} | "
            f"{r['mean_rate_dps']:.1f} | {f('boer', 'perp')} | {f('derivative')} | {f('kotelnikov')} | "
            f"{f('kalman')} | {f('kalman_euler')} | {f('kalman_mm')} | {bo['full_rms_dps']:.2f} {bo['method']} "
            f"({bo['ratio_to_boer_perp']:.2f}) | {f('smoother')} | {f('euler')} | "
            f"{bg['full_rms_dps']:.3f} {bg['method']} ({bg['ratio_to_boer_perp']:.3f}) | {100 * cov:.0f} % |")
    return "\n".join(lines)


def coverage_markdown(bench: dict) -> str:
    """Per row, each method's 1-σ coverage (share of per-axis errors within ±1σ; target 60–80 %)."""
    names = [m for m in FULL if any(m in r["methods"] for r in bench["rows"])]
    lines = ["| row | " + " | ".join(names) + " |", "|" + "---|" * (len(names) + 1)]
    for r in bench["rows"]:
        cells = []
        for n in names:
            c = r["methods"].get(n, {}).get("coverage_1sigma", math.nan)
            cells.append("—" if not np.isfinite(c) else f"{100 * c:.0f} %")
        lines.append(f"| {r['key']} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


# --- the real recordings -------------------------------------------------------------------------------

REAL_METHODS = ("boer", "kalman", "smoother")


def real_recordings(paths, rates_hz=(None, 10.0), max_s: float | None = None, log=print) -> list[dict]:
    """Boer, the onboard Kalman filter and the RTS smoother on real recordings (fixed laboratory field),
    at the native rate and decimated: RMS error of the part perpendicular to B against the gyro (the
    full vector too, for the methods that give it). σ_B from the data (ground.estimate.noise_estimate_T)."""
    from ground.estimate import decimate, noise_estimate_T, score
    from ground.recording import Recording, read_recording

    out = []
    for path in paths:
        rec = read_recording(path)
        if rec.w_ref_radps is None:
            raise ValueError(f"{path}: no reference rate (wx_dps, wy_dps, wz_dps) to score against")
        if max_s is not None and len(rec):
            m = rec.t_s < rec.t_s[0] + max_s
            rec = Recording(rec.t_s[m], rec.b_T[m], rec.m_Nm[m], rec.w_ref_radps[m])
        if len(rec) < 10:
            raise ValueError(f"{path}: {len(rec)} samples" + (f" in the first {max_s:g} s" if max_s else "")
                             + ", too few to score (10 at least)")
        for hz in rates_hz:
            r = decimate(rec, hz) if hz else rec
            sigma = noise_estimate_T(r.b_T)
            row = {"file": str(path).split("/")[-1], "rate_hz": hz or 1.0 / float(np.median(np.diff(r.t_s))),
                   "decimated": hz is not None, "samples": len(r), "sigma_uT": sigma * 1e6,
                   "mean_rate_dps": math.degrees(float(np.nanmean(np.linalg.norm(r.w_ref_radps, axis=1)))),
                   "methods": {}}
            t0 = time.monotonic()
            row["methods"]["boer"] = score(r, rf.boer_rate(r.t_s, r.b_T), True)
            row["methods"]["kalman"] = score(r, rk.kalman_rate(r.t_s, r.b_T, sigma)[0], False)
            sm_res = sm.rts_smooth(r.t_s, r.b_T, sigma)
            row["methods"]["smoother"] = score(r, sm_res.w_radps, False)
            row["smoother_noise"] = {k: sm_res.info[k] for k in ("kappa", "rate_accel_radps2", "sigma_factor",
                                                                 "rate_tau_s")}
            best = min(REAL_METHODS, key=lambda n: row["methods"][n]["perp_rms_dps"])
            row["best"] = best
            row["best_beats_boer"] = row["methods"][best]["perp_rms_dps"] < row["methods"]["boer"]["perp_rms_dps"]
            out.append(row)
            log(f"[{time.monotonic() - t0:5.0f} s] {row['file']} {row['rate_hz']:.0f} Hz: Boer⊥ "
                f"{row['methods']['boer']['perp_rms_dps']:.2f}, "
                f"kalman⊥ {row['methods']['kalman']['perp_rms_dps']:.2f}, "
                f"smoother⊥ {row['methods']['smoother']['perp_rms_dps']:.2f} °/s")
    return out


def real_markdown(rows: list[dict]) -> str:
    lines = ["| recording | rate Hz | samples | mean \\|ω\\| °/s | Boer ⊥ RMS | kalman ⊥ RMS (full) | "
             "smoother ⊥ RMS (full) | best beats Boer |", "|" + "---|" * 8]
    for r in rows:
        m = r["methods"]
        lines.append(f"| {r['file']} | {r['rate_hz']:.0f}{' (decimated)' if r['decimated'] else ''} | "
                     f"{r['samples']} | {r['mean_rate_dps']:.0f} | {m['boer']['perp_rms_dps']:.1f} | "
                     f"{m['kalman']['perp_rms_dps']:.1f} ({m['kalman']['full_rms_dps']:.0f}) | "
                     f"{m['smoother']['perp_rms_dps']:.1f} ({m['smoother']['full_rms_dps']:.0f}) | "
                     f"{'yes' if r['best_beats_boer'] else 'no'} ({r['best']}) |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = ArgumentParser(prog="python -m bench.accuracy", description=__doc__.splitlines()[0])
    ap.add_argument("--json", metavar="FILE", help="write every number (per row and method) as JSON")
    ap.add_argument("--runs", type=int_range(1, 1000), default=3, help="Monte-Carlo runs per row (default 3)")
    ap.add_argument("--seed", type=int_range(0), default=2024, help="base seed (default 2024)")
    ap.add_argument("--record-samples", type=int_range(3), default=120, help="scored samples per run (default 120)")
    ap.add_argument("--warmup-s", type=finite_float(0), default=300.0, help="onboard filters' warm-up (default 300 s)")
    ap.add_argument("--rows", default="", help="only rows whose key contains this text (e.g. 'undirected')")
    ap.add_argument("--methods", default="",
                    help="comma-separated subset of " + ",".join(METHODS) + " (boer always; default all)")
    ap.add_argument("--world", choices=WORLDS + ("both", IGRF_EXACT), default="dipole",
                    help="truth: the dipole the estimators assume (default), igrf (IGRF-14 degree 13, SGP4, the "
                         "host's iron after the box's calibration, a 3-day-old TLE, the box's clock 2 s off), both, "
                         "or igrf_exact (the IGRF rows' truth, the box knowing it exactly: what the world's geometry "
                         "costs apart from the box's knowledge)")
    ap.add_argument("--host-drift", choices=("untracked", "tracked"), default="tracked",
                    help="IGRF rows: the box's calibration following the hard iron's ~1 µT thermal drift (as "
                         "flown; default) or constant (the drift stays in the samples)")
    ap.add_argument("--quick", action="store_true", help="two rows, one short run each (smoke test)")
    ap.add_argument("--real", metavar="DIR", help="instead: the table on the real recordings (*.csv) in DIR")
    ap.add_argument("--max-s", type=finite_float(0, min_exclusive=True), default=None,
                    help="with --real: only the first S seconds of each")
    campaign_options.add_arguments(ap)
    args = ap.parse_args(argv)
    campaign_options.check(ap, args)
    real = []
    if args.real is not None:
        from pathlib import Path
        if not Path(args.real).is_dir():
            ap.error(f"--real {args.real}: not a directory")
        real = sorted(p for p in Path(args.real).glob("*.csv") if p.is_file())
        if not real:
            ap.error(f"--real {args.real}: no recordings (*.csv) in it")
    check_paths_or_exit(ap, inputs=[("--real", p) for p in real],
                        outputs={"--json": args.json, **campaign_options.outputs(args)})
    if args.real is not None:
        try:
            rows = real_recordings(real, max_s=args.max_s)
        except ValueError as e:  # a file that is not a recording with a reference rate (RecordingError too)
            print(f"hil.accuracy: {e}", file=sys.stderr)
            return 1
        print()
        print(real_markdown(rows))
        if args.json:
            write_atomic(args.json, json.dumps(rows, indent=1, default=float))
            print(f"wrote {args.json}")
        return 0
    worlds = WORLDS if args.world == "both" else (args.world,)
    rows = [r for r in all_rows(worlds, args.host_drift == "tracked") if args.rows in r.key]
    runs, rec, warm = args.runs, args.record_samples, args.warmup_s
    if args.quick:
        rows = [Row("undirected", "asymmetric", 1.0, 0.5), Row("orbital", "near_symmetric", 3.0, 1.5)]
        runs, rec, warm = 1, 60, 120.0
    if not rows:
        ap.error(f"no row matches {args.rows!r}")
    methods = METHODS
    if args.methods:
        wanted = {m.strip() for m in args.methods.split(",") if m.strip()}
        unknown = wanted - set(METHODS)
        if unknown:
            ap.error(f"unknown method(s) {sorted(unknown)}; choose from {', '.join(METHODS)}")
        if wanted & set(GROUND):
            wanted |= set(GROUND)  # computed together ("auto" chooses among them)
        methods = tuple(m for m in METHODS if m == "boer" or m in wanted)
    specs, config = campaign(rows, runs, args.seed, rec, warm, methods)
    progress = _row_progress(rows, runs, methods, print)
    per_run = campaign_options.execute(ap, args, task(config), specs, {**config, "seed": args.seed},
                                       name="accuracy", on_result=progress)
    if isinstance(per_run, int):  # --rerun, or a run that failed
        return per_run
    bench = tabulate(rows, runs, per_run, config)
    bench["config"]["seed"] = args.seed
    progress.rest(bench)
    print()
    print(markdown(bench))
    print()
    print(coverage_markdown(bench))
    for name, items in bench["targets"].items():
        held = sum(ok for _, ok, _ in items)
        print(f"{name}: {held}/{len(items)} rows")
    if args.json:
        write_atomic(args.json, json.dumps(rounded(bench), indent=1, default=float))
        print(f"wrote {args.json}")
    return 0


def rounded(obj, digits: int = 5):
    """`obj` with every float to `digits` significant digits (the JSON a quarter of the size; no figure the
    tables print changes): what docs/accuracy_bench.json keeps."""
    if isinstance(obj, float):
        return float(f"{obj:.{digits}g}") if math.isfinite(obj) else obj
    if isinstance(obj, (np.floating, np.integer)):
        return rounded(obj.item(), digits)
    if isinstance(obj, dict):
        return {k: rounded(v, digits) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [rounded(v, digits) for v in obj]
    return obj


if __name__ == "__main__":
    from fsw.startup import exit_with

    exit_with(main)
