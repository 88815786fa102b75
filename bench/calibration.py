"""Seeded benchmark of the on-board host-magnetics calibration (`fsw.estimation.magcal`).

    python -m bench.calibration [--json FILE] [--hosts N] [--seed S] [--orbits K] [--noise-uT U]
                                [--sample-rate HZ] [--drift-uT A] [--constant-host] [--kit-runs N]
                                [--kit-duration S] [--quick]

For each of ``--hosts``
seeded hosts: hard iron h uniform in ±50 µT per axis, soft iron S = I + a symmetric matrix with every
term uniform in ±10 %, optionally a thermal drift of the hard iron (``--drift-uT``: amplitude of a
sine over one orbit along a random direction), a torque-free tumble of a random asymmetric body
(rates 1–6 °/s, `hil.dynamics`), the truth field of the simulator (`hil.field`, along its circular
485 km / 97.5° orbit) and the measurement ``B_meas = S B_true + h(t) + noise`` (σ per axis: ``--noise-uT``
and the chip's 0.04 µT at 100 Hz bandwidth) at ``--sample-rate`` (default 5 Hz: what the flight's
calibration step takes, one sample every `fsw.host_calibration.SAMPLE_EVERY_S`, of a
magnetometer sampled faster, as on target; the shipped scenarios sample at 1 Hz: ``--sample-rate 1``). The
flight form (`magcal.MagCal` with the flight's field-model σ `MODEL_SIGMA_T`, the hard iron's drift followed
as a harmonic of the orbit's period unless ``--constant-host``) takes every sample with |B_model| from the
flight software's own field (`fsw.estimation.field_motion`).

Reported: per host the per-axis RMS of the calibrated field's error over the first orbit, with the
calibration at its end (its hard iron along its drift model) applied to the noise-free measurements
(``residual_uT_rms_max``: the worst axis of the worst host; target ≤ 0.3 µT); with ``--orbits`` ≥ 2, the
field as the flight loop hands it on (the calibration in effect at each sample) orbit by orbit
(``in_flight_residual_uT_rms_max_by_orbit``, ``residual_uT_rms_max_orbit2``, ``…orbit3``: the worst axis
of the worst host over each whole orbit; the same target from the second orbit on) and how many hosts
end REJECTED (``rejected_hosts``); the time the calibration first reached its σ goals
(``convergence_s``: σ of b ≤ 0.1 µT, of D ≤ 0.002) and the time the first calibration passed its checks
and was applied (``first_calibration_s``), the errors of b (against the truth's at the calibration's
time) and D against their 1-σ at the end (coverage: how often |error| ≤ σ, about 68 % for honest σ) and
``field_model_error_uT_rms``: the on-board field model (IGRF-14 at the flight degree,
fsw.estimation.igrf) against the truth (degree 13, hil.field) along the orbit, per axis RMS.

Kit runs (``--kit-runs``, :func:`run_kit`): the de-orbit kit's magnets at the sensor compensated on board
(`fsw.deorbit.kit_field`). Each run is the closed de-orbit loop of `bench.deorbit` (scenario amds_deorbit,
composed as SITL: simulator with the kit emulator, the whole flight software at 10 Hz, the controller
started at t = 0 and moving capsules and magnets as it decides) for ``--kit-duration`` seconds from a
seeded argument of latitude, with the truth's magnets off their design by seeded manufacturing errors
(moment ±10 %, position 3 mm per axis, leakage 1-2 % against the design's 1.5 %). Scored on every
sample not flagged: the kit's field the flight software took out against the truth's (the compensated
field against the truth's field without the kit, noise-free), per axis RMS — from the time every
channel's calibration has taken two steps (``kit_residual_uT_rms_max``, worst axis of the worst run;
target ≤ 1.5 µT) and over the whole run (the design model before its calibration included); the kit's
field itself (RMS, worst), the samples flagged and the estimator restarts (none expected).

The host's effect is generated here (:func:`host_measure`, the same model as the simulator's host
magnetics will have: ``B_meas = S B_true + h(t)``).
"""
from __future__ import annotations

import functools
import json
import math
from dataclasses import dataclass, field

import numpy as np

from bench.campaign import Run, run_campaign
from bench.campaign import options as campaign_options
from fsw.argtypes import ArgumentParser, check_paths_or_exit, finite_float, int_range
from fsw.estimation import field_motion as fm
from fsw.estimation import magcal as mc
from fsw.estimation.onboard_field import flight_field
from fsw.files import write_atomic
from fsw.host_calibration import SAMPLE_EVERY_S
from fsw.config import RunConfig
from fsw.system import NullLink
from fsw.telemetry.dialect import mavlink
from hil import scenario as scenarios
from hil import sitl
from hil.dynamics import RigidBody
from hil.field import FieldAlongOrbit, IgrfField
from hil.orbit import CircularOrbit

ALTITUDE_M, INCLINATION_DEG, EPOCH = 485e3, 97.5, 2025.5
CHIP_NOISE_UT = 0.04
TARGET_RESIDUAL_UT = 0.3
TARGET_KIT_RESIDUAL_UT = 1.5
#: the rate the flight's calibration step takes samples at (one every HostCalibration.sample_every_s)
FLIGHT_RATE_HZ = 1.0 / SAMPLE_EVERY_S
KIT_SCENARIO = "amds_deorbit"
#: manufacturing errors of the truth's magnets: moment fraction, position per axis [m], leakage range
KIT_MOMENT_ERROR, KIT_POSITION_ERROR_M, KIT_LEAKAGE = 0.10, 0.003, (0.01, 0.02)


@dataclass(frozen=True)
class Host:
    """Host magnetics: B_meas = S B_true + h0 + drift · sin(2π t / period) · drift_dir."""

    S: np.ndarray
    h0_T: np.ndarray
    drift_T: float = 0.0
    drift_dir: np.ndarray = field(default_factory=lambda: np.array([1.0, 0.0, 0.0]))
    period_s: float = 5670.0

    def h_T(self, t_s: np.ndarray) -> np.ndarray:
        t = np.asarray(t_s, float)
        return self.h0_T + self.drift_T * np.sin(2 * np.pi * t / self.period_s)[..., None] * self.drift_dir


def random_host(rng: np.random.Generator, hard_uT: float = 50.0, soft: float = 0.1, drift_uT: float = 0.0,
                period_s: float = 5670.0) -> Host:
    A = rng.uniform(-soft, soft, (3, 3))
    S = np.eye(3) + np.triu(A) + np.triu(A, 1).T
    d = rng.normal(size=3)
    return Host(S, rng.uniform(-hard_uT, hard_uT, 3) * 1e-6, drift_uT * 1e-6, d / np.linalg.norm(d), period_s)


def host_measure(host: Host, b_true_T: np.ndarray, t_s: np.ndarray) -> np.ndarray:
    """The noise-free measurement of the true body field (n, 3) at times (n,)."""
    return np.asarray(b_true_T) @ host.S.T + host.h_T(t_s)


def tumble_field_T(rng: np.random.Generator, t_s: np.ndarray, b_eci_T: np.ndarray, step_s: float = 0.5,
                   rate_dps: tuple[float, float] = (1.0, 6.0)) -> np.ndarray:
    """B in body axes along a torque-free tumble of a random asymmetric body sampled at `t_s`."""
    J = np.diag(np.sort(rng.uniform(150.0, 290.0, 3)))  # within the triangle inequality
    w = rng.normal(size=3)
    w *= math.radians(rng.uniform(*rate_dps)) / np.linalg.norm(w)
    q = rng.normal(size=4)
    body = RigidBody(J, q / np.linalg.norm(q), w)
    out = np.empty_like(b_eci_T)
    zero = np.zeros(3)
    for k, t in enumerate(t_s):
        while body.t_s < t - 1e-9:
            body.step(min(step_s, t - body.t_s), zero)
        out[k] = body.dcm.T @ b_eci_T[k]
    return out


def orbit_fields(duration_s: float, rate_hz: float):
    """(t, B_eci truth [T], |B| of the on-board model [T], the model's error RMS per axis [µT] or None)."""
    t = np.arange(0.0, duration_s, 1.0 / rate_hz)
    truth = FieldAlongOrbit(CircularOrbit(ALTITUDE_M, INCLINATION_DEG), IgrfField(EPOCH))  # degree 13
    model = flight_field(fm.CircularOrbitModel(ALTITUDE_M, INCLINATION_DEG), EPOCH)
    b_true, b_model = truth.b_eci_T(t), model.b_eci_T(t)
    return t, b_true, np.linalg.norm(b_model, axis=1), float(np.sqrt(np.mean((b_true - b_model) ** 2)) * 1e6)


def run_host(seed: int, t: np.ndarray, b_eci: np.ndarray, b_model_mag: np.ndarray, noise_uT: float,
             drift_uT: float, period_s: float, drift_model: bool = True) -> dict:
    rng = np.random.default_rng(seed)
    host = random_host(rng, drift_uT=drift_uT, period_s=period_s)
    b_body = tumble_field_T(rng, t, b_eci)
    clean = host_measure(host, b_body, t)
    sigma_T = math.hypot(noise_uT, CHIP_NOISE_UT) * 1e-6
    meas = clean + rng.normal(0.0, sigma_T, clean.shape)
    # as the flight loop sets it: the drift's period the orbit's (or a constant host: --constant-host)
    cal = mc.MagCal(sigma_T, sigma_model_T=mc.MODEL_SIGMA_T, drift_period_s=period_s if drift_model else None)
    first = t < period_s
    applied = np.full(clean.shape, np.nan)  # what the flight loop hands on: the calibration in effect then
    b_first_T = None  # b(t) over the first orbit, of the solution at its end
    for k in range(len(t)):
        cal.update(meas[k], b_model_mag[k], t[k])
        if cal.good:
            applied[k] = cal.apply(clean[k], t[k])
        if b_first_T is None and (k + 1 == len(t) or t[k + 1] >= period_s):
            if k + 1 == len(t):
                cal.solve(float(t[k]))
            b_first_T, D_first = cal.hard_iron_T(t[first]), cal.calibration.D
    if len(t) > np.count_nonzero(first):
        cal.solve(float(t[-1]))
    est = cal.calibration
    # after one orbit: that orbit's record with the calibration at its end (b(t) along its drift model)
    resid = (clean[first] - b_first_T) @ (np.eye(3) + D_first).T - b_body[first]
    rms = np.sqrt(np.mean(resid ** 2, axis=0)) * 1e6
    raw = np.sqrt(np.mean((clean - b_body) ** 2, axis=0)) * 1e6
    # in flight: orbit by orbit, the calibration in effect at each sample (none yet: the raw sample)
    orbit_of = np.floor(t / period_s).astype(int)
    flown = np.where(np.isnan(applied), clean, applied) - b_body
    by_orbit = [(np.sqrt(np.mean(flown[orbit_of == j] ** 2, axis=0)) * 1e6).tolist()
                for j in range(int(orbit_of[-1]) + 1) if np.sum(orbit_of == j) > 0.9 * period_s * (len(t) / t[-1])]
    D_true = np.linalg.inv(host.S) - np.eye(3)
    t_b = cal.published_at_s if cal.published_at_s is not None else float(t[-1])
    err = np.concatenate(((est.b_T - host.h_T(t_b)) * 1e6, [est.D[i, j] - D_true[i, j] for i, j in mc.D_TERMS]))
    sig = est.sigma * np.array([1e6] * 3 + [1.0] * 6)
    return {"seed": seed, "state": mc.STATE_NAMES[cal.state], "reason": cal.reason, "good": cal.good,
            "hard_iron_uT": (host.h0_T * 1e6).tolist(), "residual_uT_rms": rms.tolist(),
            "in_flight_residual_uT_rms_by_orbit": by_orbit,
            "uncalibrated_uT_rms": raw.tolist(), "convergence_s": cal.converged_at_s,
            "first_calibration_s": cal.first_good_at_s, "rejections": cal.rejections, "dropped": cal.dropped,
            "error_over_sigma": (err / sig).tolist(), "sigma_hard_uT": sig[:3].tolist(),
            "sigma_soft": sig[3:].tolist(), "chi2_dof": cal.chi2_dof, "samples": cal.samples}


@functools.lru_cache(maxsize=4)
def _fields(orbits: float, rate_hz: float):
    """The orbit's fields of a campaign (the same for every host: computed once per worker process)."""
    period = CircularOrbit(ALTITUDE_M, INCLINATION_DEG).period_s
    return period, orbit_fields(orbits * period, rate_hz)


def campaign(hosts: int, seed: int, orbits: float, noise_uT: float, rate_hz: float, drift_uT: float,
             drift_model: bool, kit_runs: int = 0, kit_duration_s: float = 1800.0) -> tuple[list[Run], dict]:
    """The benchmark as a campaign (bench.campaign): host ``hostS`` and kit run ``kitS`` seeded S = seed + k."""
    runs = [Run(f"host{seed + k}", (seed + k,), {"kind": "host"}) for k in range(hosts)]
    runs += [Run(f"kit{seed + k}", (seed + k,), {"kind": "kit"}) for k in range(kit_runs)]
    config = {"benchmark": "bench.calibration", "orbits": orbits, "noise_uT": noise_uT, "sample_rate_hz": rate_hz,
              "drift_uT": drift_uT, "drift_model": drift_model, "kit_duration_s": kit_duration_s}
    return runs, config


def run_task(run: Run, *, orbits: float, noise_uT: float, sample_rate_hz: float, drift_uT: float,
             drift_model: bool, kit_duration_s: float, **_) -> dict:
    """A campaign's task: one host (run_host) or one kit run (run_kit)."""
    if run.params["kind"] == "kit":
        return run_kit(run.seed[0], kit_duration_s)
    period, (t, b_eci, b_mag, _) = _fields(orbits, sample_rate_hz)
    return run_host(run.seed[0], t, b_eci, b_mag, noise_uT, drift_uT, period, drift_model)


def task(config: dict):
    return functools.partial(run_task, **{k: v for k, v in config.items() if k != "benchmark"})


def run_bench(hosts: int = 20, seed: int = 1, orbits: float = 1.0, noise_uT: float = 1.5,
              rate_hz: float = FLIGHT_RATE_HZ, drift_uT: float = 0.0, drift_model: bool = True,
              **campaign_options) -> dict:
    """The hosts' figures (`campaign_options`: bench.campaign.run_campaign's; default: in this process)."""
    runs, config = campaign(hosts, seed, orbits, noise_uT, rate_hz, drift_uT, drift_model)
    elapsed: dict = {}
    rows = run_campaign(task(config), runs, config=config, name="calibration",
                        **{"workers": 1, "progress": False, **campaign_options}, elapsed_s=elapsed)
    return summary(rows, seed, orbits, noise_uT, rate_hz, drift_uT, drift_model, sum(elapsed.values()))


def summary(rows: list[dict], seed: int, orbits: float, noise_uT: float, rate_hz: float, drift_uT: float,
            drift_model: bool, cpu: float) -> dict:
    """The benchmark's figures from the hosts' runs (in seed order); `cpu`: their time in the tasks."""
    hosts = len(rows)
    period, (_, _, _, model_err) = _fields(orbits, rate_hz)
    ratios = np.abs(np.array([r["error_over_sigma"] for r in rows]))
    conv = [r["convergence_s"] for r in rows if r["convergence_s"] is not None]
    resid = max(max(r["residual_uT_rms"]) for r in rows)
    first = [r["first_calibration_s"] for r in rows]
    n_orbits = min(len(r["in_flight_residual_uT_rms_by_orbit"]) for r in rows)
    flown = [max(max(r["in_flight_residual_uT_rms_by_orbit"][j]) for r in rows) for j in range(n_orbits)]
    later = flown[1:]
    return {"hosts": hosts, "seed": seed, "orbits": orbits, "orbit_period_s": period, "sample_rate_hz": rate_hz,
            "noise_uT": math.hypot(noise_uT, CHIP_NOISE_UT), "drift_uT": drift_uT, "drift_model": drift_model,
            "residual_uT_rms_max": resid, "target_residual_uT_rms": TARGET_RESIDUAL_UT,
            "residual_within_target": bool(resid <= TARGET_RESIDUAL_UT),
            # in flight, orbit by orbit (whole orbits only): the worst axis of the worst host of the field
            # as the loop hands it on (the calibration in effect at each sample); the first orbit includes
            # the minutes before the first calibration, so the target applies from the second
            "in_flight_residual_uT_rms_max_by_orbit": flown,
            **{f"residual_uT_rms_max_orbit{j + 1}": v for j, v in enumerate(flown) if j >= 1},
            "later_orbits_within_target": None if not later else bool(max(later) <= TARGET_RESIDUAL_UT),
            "rejected_hosts": sum(r["state"] == "rejected" for r in rows),
            "uncalibrated_uT_rms_max": max(max(r["uncalibrated_uT_rms"]) for r in rows),
            "converged_hosts": len(conv),
            # over the hosts that reached the σ goals within the record
            "convergence_s_max": max(conv, default=None),
            "convergence_s_median": float(np.median(conv)) if conv else None,
            # the first calibration that passed the checks (applied from then on)
            "first_calibration_s_max": None if None in first else max(first),
            "first_calibration_s_median": None if None in first else float(np.median(first)),
            "coverage_1sigma_hard": float(np.mean(ratios[:, :3] <= 1.0)),
            "coverage_1sigma_soft": float(np.mean(ratios[:, 3:] <= 1.0)),
            "field_model_error_uT_rms": model_err,
            "field_model_note": ("truth and on-board field are the same IGRF-14 dipole" if model_err is None
                                 else "on-board model against the simulator's truth"),
            "cpu_s": cpu, "runs": rows}


def run_kit(seed: int, duration_s: float = 1800.0, rate_hz: float = 10.0, calibrated_after_steps: int = 2) -> dict:
    """One kit run (see the module's docstring): the on-board kit-field model against the truth's."""
    import dataclasses
    from types import SimpleNamespace

    rng = np.random.default_rng(seed)
    scn = dataclasses.replace(scenarios.load(KIT_SCENARIO), arg_lat0_deg=float(rng.uniform(0.0, 360.0)))
    step = 1.0 / rate_hz
    box = sitl.build(sitl.SitlConfig(RunConfig(rate_hz=rate_hz, buffer_frames=0), scenario=scn, seed=seed,
                                     max_step_s=step), link=NullLink(), run_id=0, ident=False)
    sim, flight = box.sim, box.fsw
    kit = flight.apps["deorbit"]
    model = kit.sensor_field
    truth_scale = []
    for ch in sim.kit.channels:  # the truth's magnets off their design
        ch.dipole_Am2 *= 1.0 + rng.uniform(-KIT_MOMENT_ERROR, KIT_MOMENT_ERROR)
        truth_scale.append(ch.dipole_Am2 / scn.deorbit.dipole_Am2)
    sim.kit_field.positions_m = [p + rng.normal(0.0, KIT_POSITION_ERROR_M, 3) for p in sim.kit_field.positions_m]
    sim.kit_field.leakage = float(rng.uniform(*KIT_LEAKAGE))
    start = SimpleNamespace(command=mavlink.MAV_CMD_DEBRIS_CONTROLLER, param1=1, param2=0, param3=0, param4=0,
                            param5=0, param6=0, param7=0)
    resid, kit_truth, calibrated, flagged = [], [], [], 0
    calibrated_from = None
    for k in range(int(round(duration_s * rate_hz)) + 1):
        t = k * step
        sim.advance_to(t)
        b_kit_true = sim.kit_field.b_body_T()  # the state the chip measured this tick's sample in
        if k == 0 and kit.handle_command(start, t) != mavlink.MAV_RESULT_ACCEPTED:
            raise RuntimeError("controller start refused")
        flight.tick(t)
        if not flight.new_sample:
            continue
        if flight.kit_skip:
            flagged += 1
            continue
        done = min(m.steps for m in model.models) >= calibrated_after_steps
        if done and calibrated_from is None:
            calibrated_from = t
        resid.append(b_kit_true - flight.kit_T)
        kit_truth.append(b_kit_true)
        calibrated.append(done)
    resid_uT, kit_uT, cal = np.array(resid) * 1e6, np.array(kit_truth) * 1e6, np.array(calibrated, bool)

    def rms(a):
        return np.sqrt(np.mean(a ** 2, axis=0)).tolist() if len(a) else None

    return {"seed": seed, "duration_s": duration_s, "arg_lat0_deg": scn.arg_lat0_deg,
            "truth_moment_scale": truth_scale, "truth_leakage": sim.kit_field.leakage,
            "residual_uT_rms": rms(resid_uT[cal]), "residual_uT_rms_whole_run": rms(resid_uT),
            "kit_field_uT_rms": rms(kit_uT), "kit_field_uT_max": float(np.max(np.abs(kit_uT))),
            "calibrated_from_s": calibrated_from, "samples": len(resid), "samples_flagged": flagged,
            "estimator_resets": flight.estimator_resets, "gate_rejected": flight.gate.rejected,
            "capsule_openings": [int(c.capsule.openings) for c in kit.sequencer.channels],
            "scale": [m.scale for m in model.models], "scale_sigma": [m.scale_sigma for m in model.models],
            "steps": [m.steps for m in model.models], "ill_conditioned": [m.ill_conditioned for m in model.models],
            "outliers": [m.outliers for m in model.models]}


def kit_summary(rows: list[dict]) -> dict:
    """The kit figures of the JSON over the runs."""
    if not rows:
        return {"kit_residual_uT_rms_max": None}
    cal = [max(r["residual_uT_rms"]) for r in rows if r["residual_uT_rms"] is not None]
    worst = max(cal) if len(cal) == len(rows) else None
    field_rms = max(max(r["kit_field_uT_rms"]) for r in rows)
    return {"kit_residual_uT_rms_max": worst, "target_kit_residual_uT_rms": TARGET_KIT_RESIDUAL_UT,
            "kit_residual_within_target": worst is not None and worst <= TARGET_KIT_RESIDUAL_UT,
            "kit_residual_uT_rms_max_whole_run": max(max(r["residual_uT_rms_whole_run"]) for r in rows),
            "kit_field_uT_rms_max": field_rms, "kit_field_uT_max": max(r["kit_field_uT_max"] for r in rows),
            "kit_calibrated_from_s_max": None if worst is None else max(r["calibrated_from_s"] for r in rows),
            "kit_estimator_resets": sum(r["estimator_resets"] for r in rows),
            "kit_samples_flagged": sum(r["samples_flagged"] for r in rows), "kit_runs": rows}


def kit_report(r: dict) -> list[str]:
    rows = r.get("kit_runs") or []
    if not rows:
        return []
    lines = [f"kit runs: {KIT_SCENARIO}, closed loop, magnets off their design (moment +-10 %, 3 mm, leakage 1-2 %)",
             f"{'seed':>5} {'dur s':>6} {'kit uT rms':>10} {'residual uT rms (x y z)':>24} {'whole run':>9} "
             f"{'cal from s':>10} {'steps':>6} {'flagged':>7} {'resets':>6}"]
    for k in rows:
        res = "-" if k["residual_uT_rms"] is None else " ".join(f"{v:6.3f}" for v in k["residual_uT_rms"])
        cal = "-" if k["calibrated_from_s"] is None else f"{k['calibrated_from_s']:.0f}"
        lines.append(f"{k['seed']:>5} {k['duration_s']:>6.0f} {max(k['kit_field_uT_rms']):>10.1f} {res:>24} "
                     f"{max(k['residual_uT_rms_whole_run']):>9.2f} {cal:>10} "
                     f"{'+'.join(str(s) for s in k['steps']):>6} {k['samples_flagged']:>7} {k['estimator_resets']:>6}")
    worst = r["kit_residual_uT_rms_max"]
    lines.append("kit field residual once calibrated, worst axis of the worst run: "
                 + ("not calibrated in every run" if worst is None else
                    f"{worst:.3f} uT RMS (target <= {TARGET_KIT_RESIDUAL_UT} uT: "
                    f"{'met' if r['kit_residual_within_target'] else 'MISSED'})")
                 + f"; whole run {r['kit_residual_uT_rms_max_whole_run']:.2f} uT; the kit's field "
                 f"{r['kit_field_uT_rms_max']:.1f} uT RMS, {r['kit_field_uT_max']:.1f} uT max; estimator restarts "
                 f"{r['kit_estimator_resets']}")
    return lines


def report(r: dict) -> str:
    lines = [f"{r['hosts']} hosts, {r['orbits']:g} orbit(s) of {r['orbit_period_s']:.0f} s at "
             f"{r['sample_rate_hz']:g} Hz, "
             f"noise {r['noise_uT']:.2f} uT, hard-iron drift {r['drift_uT']:g} uT, "
             f"{'drift followed (a harmonic per orbit)' if r['drift_model'] else 'constant host assumed'}",
             f"{'seed':>5} {'state':>10} {'raw uT':>7} {'residual uT rms (x y z)':>24} {'conv s':>7} {'chi2':>5}"]
    for h in r["runs"]:
        res = " ".join(f"{v:6.3f}" for v in h["residual_uT_rms"])
        conv = "-" if h["convergence_s"] is None else f"{h['convergence_s']:.0f}"
        lines.append(f"{h['seed']:>5} {h['state']:>10} {max(h['uncalibrated_uT_rms']):7.1f} {res:>24} {conv:>7} "
                     f"{h['chi2_dof']:5.2f}")
    fm_err = r["field_model_error_uT_rms"]
    ok = r["later_orbits_within_target"]
    later = "-" if ok is None else "met" if ok else "MISSED"
    lines += [f"residual after {min(r['orbits'], 1.0):g} orbit(s), worst axis of the worst host: "
              f"{r['residual_uT_rms_max']:.3f} uT "
              f"RMS (target <= {r['target_residual_uT_rms']} uT: {'met' if r['residual_within_target'] else 'MISSED'})",
              "in flight, worst axis of the worst host, orbit by orbit: "
              + " / ".join(f"{v:.3f}" for v in r["in_flight_residual_uT_rms_max_by_orbit"])
              + f" uT RMS (target from the 2nd orbit: {later}); hosts ending rejected: {r['rejected_hosts']}",
              f"reached the sigma goals: {r['converged_hosts']}/{r['hosts']} hosts, after (median / worst of those) "
              f"{r['convergence_s_median']} / {r['convergence_s_max']} s; first calibration applied after "
              f"{r['first_calibration_s_median']} / {r['first_calibration_s_max']} s",
              f"1-sigma coverage: hard iron {100 * r['coverage_1sigma_hard']:.0f} %, "
              f"soft iron {100 * r['coverage_1sigma_soft']:.0f} % (honest: ~68 %)",
              f"field model error: {'null (' + r['field_model_note'] + ')' if fm_err is None else f'{fm_err:.3f} uT'}",
              f"cpu {r['cpu_s']:.1f} s"]
    return "\n".join(lines + kit_report(r))


def main(argv: list[str] | None = None) -> int:
    ap = ArgumentParser(prog="python -m bench.calibration", description=__doc__.splitlines()[0])
    ap.add_argument("--hosts", type=int_range(1, 10000), default=20, help="seeded hosts (default 20)")
    ap.add_argument("--seed", type=int_range(0, 2 ** 31), default=1, help="first host's seed (default 1)")
    ap.add_argument("--orbits", type=finite_float(0, 20, min_exclusive=True), default=1.0,
                    help="record length in orbits (default 1)")
    ap.add_argument("--noise-uT", type=finite_float(0, 100, min_exclusive=True), default=1.5,
                    help="sensor noise per axis besides the chip's (default 1.5 uT, the scenarios')")
    ap.add_argument("--sample-rate", type=finite_float(0.01, 10), default=FLIGHT_RATE_HZ, metavar="HZ",
                    help=f"sample rate (default {FLIGHT_RATE_HZ:g} Hz, what the flight's calibration takes; "
                         "the shipped scenarios sample at 1 Hz)")
    ap.add_argument("--drift-uT", type=finite_float(0, 10), default=0.0,
                    help="amplitude of the hard iron's thermal drift over an orbit (default 0)")
    ap.add_argument("--constant-host", action="store_true",
                    help="calibrate a constant host (no drift model: the calibration before the drift was followed)")
    ap.add_argument("--kit-runs", type=int_range(0, 100), default=3,
                    help="closed-loop de-orbit runs with the kit's field compensated on board (default 3; 0: none)")
    ap.add_argument("--kit-duration", type=finite_float(300, 10800), default=1800.0, metavar="S",
                    help="length of each kit run (default 1800 s)")
    ap.add_argument("--quick", action="store_true", help="4 hosts and one kit run of 900 s (a smoke run)")
    ap.add_argument("--json", metavar="FILE", help="write the figures as JSON")
    campaign_options.add_arguments(ap)
    args = ap.parse_args(argv)
    campaign_options.check(ap, args)
    check_paths_or_exit(ap, outputs={"--json": args.json, **campaign_options.outputs(args)})
    hosts = 4 if args.quick else args.hosts
    kit_runs, kit_duration = (1, 900.0) if args.quick else (args.kit_runs, args.kit_duration)
    runs, config = campaign(hosts, args.seed, args.orbits, args.noise_uT, args.sample_rate, args.drift_uT,
                            not args.constant_host, kit_runs, kit_duration)
    elapsed: dict = {}
    got = campaign_options.execute(ap, args, task(config), runs, config, name="calibration", elapsed_s=elapsed)
    if isinstance(got, int):  # --rerun, or a run that failed
        return got
    r = summary(got[:hosts], args.seed, args.orbits, args.noise_uT, args.sample_rate, args.drift_uT,
                not args.constant_host, sum(elapsed[run.id] for run in runs[:hosts]))
    r.update(kit_summary(got[hosts:]))
    print(report(r))
    if args.json:
        write_atomic(args.json, json.dumps(r, indent=2, default=float))
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    from fsw.startup import exit_with

    exit_with(main)
