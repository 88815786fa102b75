"""The scenarios a campaign file can name: each a task (a Run in, a flat dict of figures out), the parameters it
takes (with their defaults) and the figures it reports by default.

- ``accuracy`` — one pass of bench.accuracy (a row: mode, body, step, noise; dispersible inertia and initial
  rate): every method's full and perpendicular RMS error and 1-σ coverage;
- ``calibration`` — one seeded host of bench.calibration (hard and soft iron from |B| along the orbit):
  residual, convergence, error over σ;
- ``probe`` — draws from the run's seed after `work_s` seconds of busy CPU: the runner's own overhead and
  scaling (docs/campaigns.md), and the tests.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from bench.campaign.runs import Run


@dataclass(frozen=True)
class Scenario:
    task: object
    params: dict      # name -> default
    figures: tuple[str, ...]


def _accuracy(run: Run) -> dict:
    from bench import accuracy as acc
    p = {**SCENARIOS["accuracy"].params, **run.params}
    row = acc.Row(p["mode"], p["body"], float(p["dt_s"]), float(p["sigma_uT"]), p["world"])
    dispersed = {}
    if any(p[k] is not None for k in ("Jx_kgm2", "Jy_kgm2", "Jz_kgm2")):
        J = np.diag(acc.BODIES[row.body]).copy()
        for i, k in enumerate(("Jx_kgm2", "Jy_kgm2", "Jz_kgm2")):
            if p[k] is not None:
                J[i] = p[k]
        if np.any(J <= 0):
            raise ValueError(f"inertia {J.tolist()} kg·m²: not positive")
        dispersed["inertia_kgm2"] = np.diag(J)
    if p["rate_dps"] is not None:
        dispersed["rate_range_dps"] = (float(p["rate_dps"]), float(p["rate_dps"]))
    methods = tuple(p["methods"]) if p["methods"] else acc.METHODS
    one = acc.run_one(row, list(run.seed), int(p["record_samples"]), float(p["warmup_s"]), methods, **dispersed)
    res = acc.pool_row(row, [one], methods)
    out = {"mean_rate_dps": res["mean_rate_dps"]}
    for name, m in res["methods"].items():
        for k in ("full_rms_dps", "perp_rms_dps", "coverage_1sigma"):
            if k in m:
                out[f"{name}_{k}"] = m[k]
        out[f"{name}_failed"] = bool(m["failed_runs"])
    return out


def _calibration(run: Run) -> dict:
    from bench import calibration as cb
    from hil.orbit import CircularOrbit
    p = {**SCENARIOS["calibration"].params, **run.params}
    period = CircularOrbit(cb.ALTITUDE_M, cb.INCLINATION_DEG).period_s
    t, b_eci, b_mag, _ = cb.orbit_fields(float(p["orbits"]) * period, float(p["sample_rate_hz"]))
    r = cb.run_host(list(run.seed), t, b_eci, b_mag, float(p["noise_uT"]), float(p["drift_uT"]), period)
    ratios = np.abs(np.asarray(r["error_over_sigma"]))
    return {"residual_uT_rms_max": max(r["residual_uT_rms"]), "convergence_s": r["convergence_s"],
            "first_calibration_s": r["first_calibration_s"], "good": r["good"], "chi2_dof": r["chi2_dof"],
            "coverage_1sigma_hard": float(np.mean(ratios[:3] <= 1.0)),
            "coverage_1sigma_soft": float(np.mean(ratios[3:] <= 1.0)), "hard_iron_uT_norm":
            float(np.linalg.norm(r["hard_iron_uT"]))}


def _probe(run: Run) -> dict:
    p = {**SCENARIOS["probe"].params, **run.params}
    end = time.thread_time() + float(p["work_s"])
    while time.thread_time() < end:   # busy: the CPU a run of this size takes
        pass
    rng = np.random.default_rng(list(run.seed))
    payload = rng.normal(size=int(p["payload_floats"]))
    return {"x": float(rng.normal(float(p["mean"]), 1.0)), "payload": payload,
            "payload_rms": math.sqrt(float(np.mean(payload ** 2))) if payload.size else 0.0}


SCENARIOS = {
    "accuracy": Scenario(_accuracy, {"mode": "undirected", "body": "asymmetric", "dt_s": 1.0, "sigma_uT": 1.5,
                                     "world": "dipole", "record_samples": 120, "warmup_s": 300.0, "methods": [],
                                     "Jx_kgm2": None, "Jy_kgm2": None, "Jz_kgm2": None, "rate_dps": None},
                         ("boer_perp_rms_dps", "kalman_full_rms_dps", "kalman_euler_full_rms_dps",
                          "auto_full_rms_dps", "auto_coverage_1sigma")),
    "calibration": Scenario(_calibration, {"noise_uT": 1.5, "drift_uT": 0.0, "orbits": 1.0, "sample_rate_hz": 1.0},
                            ("residual_uT_rms_max", "convergence_s", "coverage_1sigma_hard", "coverage_1sigma_soft")),
    "probe": Scenario(_probe, {"work_s": 0.0, "payload_floats": 0, "mean": 0.0}, ("x", "payload_rms")),
}
