"""Closed-loop benchmark of the de-orbit kit: `python -m bench.deorbit [--json FILE] [--plot FILE.png]`.

The scenario of lapkhanov2019 section 6 (`hil/scenarios/amds_deorbit.toml`): the AMDS spacecraft at
600 km from yaw 60°, pitch 45° (orbital frame) for 10,800 s. Composed as SITL is (`hil.sitl.build`), in
one process and in lockstep: the simulator (rigid body, orbit, field, aerodynamic and gravity-gradient
torques, the magnets' M = p × B; `hil.deorbit_sim`) and the kit emulator (steppers, shutters, switches;
`hil.deorbit_kit`) are advanced to the loop time, then the whole flight software ticks on the same clock
(telemetry into a null link), its de-orbit application at 10 Hz: drivers → sequencer (interlocks,
recovery) → controller. With a scenario's [clock] (`hil.box_clock`) the loop runs on the box's clock
from `hil.sitl.box_t0_s` and the simulator on the true time it means (`Sitl.advance`), as in SITL; faults
and the trace are on true time (the world's).
The controller is started with the ground command MAV_CMD_DEBRIS_CONTROLLER through the same handler the
uplink uses. The controller's attitude (`--attitude`) is the box's own estimate by default
(`fsw.deorbit.onboard_attitude`: the calibrated, kit-compensated magnetometer, the onboard field along the
orbit, gravity gradient, the sail and the kit's p × B in the dynamics; no pulse until it is trusted), or
the simulation truth (what the paper assumes) for comparison. The estimate is scored against the truth
once a second: `att_err_rms_rad` (yaw, pitch) and `rate_err_rms_dps` from `settle_s` on.

The host-magnetics calibration. A spacecraft held to the flow does not turn enough for the onboard
calibration (`fsw.host_calibration`) to solve the host's iron (its solutions are ill-conditioned), so the
box starts with the calibration an earlier phase of the mission (the tumble) would have left it
(:func:`hand_over_calibration`: the host's hard and soft iron with seeded errors, 0.3 µT and 0.3 %, its
thermal drift not included), applied as the box's own last good calibration. Likewise the kit-field
model starts with the calibration the mission's openings before this phase leave (:func:`hand_over_kit_field`,
`--kit-calibration none` for the design's prior instead).

`--sweep`: the 8 starts on the orbit (argument of latitude 0°, 45°, ..., 315°) × 5 seeds (the sensor's
noise, the handed-over calibration's errors), 40 runs of `--duration`; the JSON then has `runs` (one row
each), `fraction_within_0p2_rad` (yaw and pitch within 0.2 rad from `settle_s` on), `energy_J_mean`,
`energy_J_max` and `att_err_rms_rad_max` (the worst run's yaw/pitch estimation RMS). `--starts` and
`--seeds` make it smaller. `--controller FIELD=VALUE` (repeatable) replaces a number or name of the
controller's configuration (`fsw.deorbit.controller.ControllerConfig`) on top of the scenario's.

Printed: yaw and pitch errors after convergence (from `settle_s`), capsule openings, magnet turns and
energy per channel, next to the paper's figures (≤ 0.2 rad; 15 + 30 openings, 35 + 25 turns;
1,053 J + 702 J = 1,755 J per 10,800 s). `--json` writes the numbers, `--plot` the figure (the paper's
Figures 3-8: yaw, pitch, the control moments and the pulses of both channels).
"""
from __future__ import annotations

import dataclasses
import functools
import json
import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from bench.campaign import Run, run_campaign
from bench.campaign import options as campaign_options
from fsw.argtypes import ArgumentParser, check_paths_or_exit, finite_float, int_range
from fsw.deorbit.controller import ControllerConfig, euler_zyx
from fsw.deorbit.energy import PAPER_CAPSULES_J, PAPER_MAGNETS_J, PAPER_OPENINGS, PAPER_TOTAL_J, PAPER_TURNS
from fsw.config import RunConfig
from fsw.deorbit.kit import DeorbitKit
from fsw.files import write_atomic
from fsw.system import NullLink
from fsw.telemetry.dialect import mavlink
from ground.plot import check_plot_path_or_exit, save_figure

from hil import scenario as scenarios
from hil import sitl
from hil.deorbit_sim import DeorbitSimulator

DEFAULT_SCENARIO = "amds_deorbit"
PAPER = {
    "err_max_rad": 0.2,
    "capsule_openings": {"pitch": PAPER_OPENINGS["pitch"], "yaw": PAPER_OPENINGS["yaw"],
                         "total": sum(PAPER_OPENINGS.values())},
    "magnet_turns": {"pitch": PAPER_TURNS["pitch"], "yaw": PAPER_TURNS["yaw"], "total": sum(PAPER_TURNS.values())},
    "energy_J": {"capsules": PAPER_CAPSULES_J, "magnets": PAPER_MAGNETS_J, "total": PAPER_TOTAL_J},
}
#: the kit-field calibration handed over (:func:`hand_over_kit_field`): 1-σ per axis, a fraction of |F_a|
KIT_HAND_OVER_FRAC = 0.01
#: what the kit-field model starts with on the estimate: that calibration, or none (the design's 15 % prior)
KIT_CALIBRATIONS = ("handed-over", "none")
FAULT_KINDS = ("stall", "stuck", "switch", "gpio")
CHANNELS = {"pitch": 0, "yaw": 1, "0": 0, "1": 1}


@dataclass
class Fault:
    """A fault injected into the kit emulator at `t_s`: kind stall/stuck/switch/gpio on a channel."""

    t_s: float
    channel: int
    kind: str
    value: object = None

    @classmethod
    def parse(cls, text: str) -> "Fault":
        """KIND:CHANNEL:T_S[:VALUE], e.g. stall:pitch:1500, stuck:yaw:900:0.5, switch:yaw:600:closed=1."""
        parts = text.split(":")
        if len(parts) not in (3, 4) or parts[0] not in FAULT_KINDS or parts[1] not in CHANNELS:
            raise ValueError(f"bad fault {text!r}: KIND:CHANNEL:T_S[:VALUE], KIND in {FAULT_KINDS}, "
                             "CHANNEL pitch/yaw")
        value: object = None
        if len(parts) == 4:
            if parts[0] == "switch":
                name, _, level = parts[3].partition("=")
                value = (name, level in ("1", "on", "true"))
            else:
                value = float(parts[3])
                if not math.isfinite(value):
                    raise ValueError(f"bad fault {text!r}: the value must be a finite number")
        t_s = float(parts[2])
        if not (math.isfinite(t_s) and t_s >= 0):  # NaN: never injected, silently
            raise ValueError(f"bad fault {text!r}: the time must be a finite number of seconds >= 0")
        return cls(t_s, CHANNELS[parts[1]], parts[0], value)


@dataclass
class Trace:
    """One row per second of loop time."""

    t_s: list = field(default_factory=list)
    yaw: list = field(default_factory=list)
    pitch: list = field(default_factory=list)
    roll: list = field(default_factory=list)
    m_y: list = field(default_factory=list)  # magnets' moment about body y / z [N·m]
    m_z: list = field(default_factory=list)
    pulse_pitch: list = field(default_factory=list)  # unscreened fraction × polarity
    pulse_yaw: list = field(default_factory=list)
    # the onboard estimate against the truth at its latest sample (NaN before it starts / with the truth)
    est_yaw: list = field(default_factory=list)
    est_pitch: list = field(default_factory=list)
    err_yaw: list = field(default_factory=list)
    err_pitch: list = field(default_factory=list)
    err_rate_radps: list = field(default_factory=list)
    trusted: list = field(default_factory=list)


@dataclass
class BenchResult:
    scenario: str
    law: str
    duration_s: float
    settle_s: float
    rate_hz: float
    step_s: float
    wall_s: float
    attitude_source: str
    density: str
    trace: Trace
    kit: DeorbitKit
    sim: DeorbitSimulator
    faults: list
    attitude: str = "truth"
    seed: int = 0
    #: the kit-field calibration the box started with: "handed-over" (:func:`hand_over_kit_field`) or "none"
    kit_calibration: str = "none"

    # --- the numbers ----------------------------------------------------------------------------
    def _window(self) -> np.ndarray:
        return np.asarray(self.trace.t_s) >= self.settle_s

    @property
    def yaw_err_max_rad(self) -> float:
        w = self._window()
        return float(np.abs(np.asarray(self.trace.yaw)[w]).max()) if w.any() else math.nan

    @property
    def pitch_err_max_rad(self) -> float:
        w = self._window()
        return float(np.abs(np.asarray(self.trace.pitch)[w]).max()) if w.any() else math.nan

    @property
    def converged_at_s(self) -> float:
        """Time after which |yaw| and |pitch| stay within 0.2 rad (NaN if they never do by the end)."""
        y, p = np.abs(self.trace.yaw), np.abs(self.trace.pitch)
        bad = np.nonzero((y > 0.2) | (p > 0.2))[0]
        if bad.size == 0:
            return 0.0
        if bad[-1] == len(y) - 1:
            return math.nan
        return float(self.trace.t_s[bad[-1] + 1])

    def _est_rms(self, values) -> float:
        w = self._window()
        v = np.asarray(values, float)[w] if w.any() else np.zeros(0)
        v = v[np.isfinite(v)]
        return float(np.sqrt(np.mean(v ** 2))) if v.size else math.nan

    @property
    def att_err_rms_rad(self) -> tuple[float, float]:
        """(yaw, pitch) RMS of the onboard estimate's error from `settle_s` on (NaN on the truth)."""
        return self._est_rms(self.trace.err_yaw), self._est_rms(self.trace.err_pitch)

    @property
    def rate_err_rms_dps(self) -> float:
        return math.degrees(self._est_rms(self.trace.err_rate_radps))

    @property
    def trusted_from_s(self) -> float:
        """The first second the controller acted on the estimate (NaN: never; 0 with the truth)."""
        if self.attitude == "truth":
            return 0.0
        ok = np.nonzero(np.asarray(self.trace.trusted, bool))[0]
        return float(self.trace.t_s[ok[0]]) if ok.size else math.nan

    def as_dict(self) -> dict:
        kit, seq = self.kit, self.kit.sequencer
        led = kit.energy()
        names = ("pitch", "yaw")
        openings = {n: c.openings for n, c in zip(names, led.channels)}
        turns = {n: c.turns for n, c in zip(names, led.channels)}
        openings["total"] = sum(openings.values())
        turns["total"] = sum(turns.values())
        emu = self.sim.kit
        return {
            "scenario": self.scenario, "law": self.law, "duration_s": self.duration_s,
            "settle_s": self.settle_s, "loop_rate_hz": self.rate_hz, "dynamics_step_s": self.step_s,
            "arg_lat0_deg": self.sim.orbit.arg_lat0_deg,
            "attitude": self.attitude, "attitude_source": self.attitude_source, "density_model": self.density,
            "seed": self.seed, "kit_calibration": self.kit_calibration,
            "att_err_rms_rad": {"yaw": self.att_err_rms_rad[0], "pitch": self.att_err_rms_rad[1]},
            "att_err_rms_rad_max": max(self.att_err_rms_rad) if self.attitude == "estimate" else math.nan,
            "rate_err_rms_dps": self.rate_err_rms_dps,
            "trusted_from_s": self.trusted_from_s,
            "decisions_held": kit.decisions_without_attitude,
            "within_0p2_rad": bool(self.yaw_err_max_rad <= 0.2 and self.pitch_err_max_rad <= 0.2),
            "yaw_err_max_rad": self.yaw_err_max_rad, "pitch_err_max_rad": self.pitch_err_max_rad,
            "converged_at_s": self.converged_at_s,
            "roll_rate_max_radps": (float(np.abs(np.diff(np.unwrap(self.trace.roll))).max())
                                    if len(self.trace.roll) > 1 else 0.0),
            "capsule_openings": openings, "magnet_turns": turns,
            "energy_J": {k: round(v, 1) for k, v in led.as_dict().items()},
            "energy_truth_J": round(emu.energy_J, 1),
            "interlock_violations": seq.interlock_violations + emu.interlock_violations,
            "interlock_violations_flight": seq.interlock_violations,
            "interlock_violations_truth": emu.interlock_violations,
            "interlock_refusals": seq.interlock_refusals,
            "safe_entries": seq.safe_entries, "recoveries": seq.recoveries,
            "controller_state": seq.mode.name, "faults_injected": [f.__dict__ for f in self.faults],
            "fault_bits": [int(c.fault) for c in seq.channels],
            "decisions": kit.controller.decisions, "events": seq.events_total,
            "wall_s": round(self.wall_s, 2),
            "paper": PAPER,
        }


def deorbit_scenario(scenario_name: str):
    """The scenario `scenario_name`; ValueError when it has no de-orbit kit (no [deorbit] table)."""
    scn = scenarios.load(scenario_name)
    if scn.deorbit is None:
        raise ValueError(f"scenario {scn.name!r} has no [deorbit] table")
    return scn


def run_bench(scenario_name: str = DEFAULT_SCENARIO, *, duration_s: float | None = None, rate_hz: float = 10.0,
              law: str = "mpc", faults: list[Fault] | tuple = (), seed: int = 0,
              settle_s: float | None = None, controller: ControllerConfig | None = None,
              arg_lat0_deg: float | None = None, attitude: str = "estimate",
              kit_calibration: str = "handed-over", controller_overrides: dict | None = None) -> BenchResult:
    if kit_calibration not in KIT_CALIBRATIONS:
        raise ValueError(f"kit_calibration must be one of {KIT_CALIBRATIONS}, got {kit_calibration!r}")
    scn = deorbit_scenario(scenario_name)
    if arg_lat0_deg is not None:  # start elsewhere on the same orbit
        scn = dataclasses.replace(scn, arg_lat0_deg=float(arg_lat0_deg))
    spec = scn.deorbit
    duration = float(duration_s if duration_s is not None else spec.duration_s)
    settle = float(settle_s if settle_s is not None else min(spec.settle_s, duration))
    step = 1.0 / rate_hz
    box = sitl.build(sitl.SitlConfig(RunConfig(rate_hz=rate_hz, buffer_frames=0), scenario=scn, seed=seed,
                                      max_step_s=step),
                     link=NullLink(), run_id=0, ident=False,
                     kit_options={"controller": controller, "law": law, "keep_pulses": True,
                                  "attitude": attitude, "controller_overrides": controller_overrides})
    sim, fsw = box.sim, box.fsw
    hand_over_calibration(fsw.calibration, sim.host, seed=seed)
    kit_cal = kit_calibration if attitude == "estimate" else "none"  # the truth needs no kit-field model
    if kit_cal == "handed-over":
        hand_over_kit_field(fsw.kit_field, sim, seed=seed)
    kit = fsw.apps["deorbit"]
    cfg, source = kit.controller.config, kit.attitude
    # start the controller through its ground command handler
    start = SimpleNamespace(command=mavlink.MAV_CMD_DEBRIS_CONTROLLER, param1=1, param2=0, param3=0,
                            param4=0, param5=0, param6=0, param7=0)
    pending = sorted(faults, key=lambda f: f.t_s)
    tr = Trace()
    n = int(round(duration * rate_hz))
    every = max(1, int(round(rate_hz)))
    wall0 = time.perf_counter()
    for k in range(n + 1):
        t_box = box.t0_s + k * step
        box.advance(t_box)
        t = sim.t_s  # true time: the world's
        while pending and pending[0].t_s <= t:
            f = pending.pop(0)
            sim.kit.inject(f.channel, f.kind, f.value)
        if k == 0:
            result = kit.handle_command(start, t_box)
            if result != mavlink.MAV_RESULT_ACCEPTED:
                raise RuntimeError(f"controller start refused: MAV_RESULT {result}")
        fsw.tick(t_box)
        if k % every == 0:
            R_bo, _, b_body = sim.attitude_orbital()
            yaw, pitch, roll = euler_zyx(R_bo)
            m = np.cross(sim.kit.dipole_body_Am2(), b_body)
            tr.t_s.append(t)
            tr.yaw.append(yaw)
            tr.pitch.append(pitch)
            tr.roll.append(roll)
            tr.m_y.append(float(m[1]))
            tr.m_z.append(float(m[2]))
            chs = sim.kit.channels
            tr.pulse_pitch.append(chs[0].shutter * _sign(chs[0]))
            tr.pulse_yaw.append(chs[1].shutter * _sign(chs[1]))
            _score_estimate(tr, source if attitude == "estimate" else None, sim)
    wall = time.perf_counter() - wall0
    density = (f"exponential, {spec.density_kgm3:.4g} kg/m3 at {spec.density_ref_alt_km:g} km, scale height "
               f"{spec.density_scale_height_km:g} km (Vallado Table 8-4)")
    return BenchResult(scn.name, cfg.law, duration, settle, rate_hz, sim.max_step_s, wall, source.description,
                       density, tr, kit, sim, list(faults), attitude, seed, kit_cal)


def hand_over_calibration(calibration, host, *, seed: int = 0, hard_sigma_T: float = 0.3e-6,
                          soft_sigma: float = 0.003) -> str:
    """Give the box's host-magnetics calibration (`fsw.host_calibration.HostCalibration`) the host's iron
    as an earlier phase of the mission would have left it: hard iron (its mean: the thermal drift is not
    in it) and the inverse of the soft iron, with seeded errors of `hard_sigma_T` per axis and
    `soft_sigma` per element and that covariance; taken as the box's own last good calibration (kept
    applied while the new samples cannot solve a better one, and their fits fused with it). Returns how
    it was taken."""
    from fsw.estimation.magcal import D_TERMS

    rng = np.random.default_rng(10_000 + seed)
    S = np.asarray(host.soft_iron, float)
    D = np.linalg.inv(0.5 * (S + S.T)) - np.eye(3)
    E = rng.normal(0.0, soft_sigma, (3, 3))
    D = D + 0.5 * (E + E.T)
    b = np.asarray(host.hard_iron_T, float) + rng.normal(0.0, hard_sigma_T, 3)
    # its covariance as seeded: σ² per diagonal term, half that per off-diagonal one (symmetrised)
    var = [hard_sigma_T ** 2] * 3 + [soft_sigma ** 2 * (1.0 if i == j else 0.5) for i, j in D_TERMS]
    snap = {"theta_uT": [*(b * 1e6), *(D[i, j] for i, j in D_TERMS)], "b_T": list(b), "D": D.tolist(),
            "cov": np.diag(var).tolist(), "published_at_s": 0.0, "drift_period_s": None, "state": 1}
    return calibration.restore(snap, None, 0.0, restart=False)  # the box's own: not dropped at the first misfit


def hand_over_kit_field(kit_field, sim, *, seed: int = 0, sigma_frac: float = KIT_HAND_OVER_FRAC) -> None:
    """Give the box's kit-field model (`fsw.deorbit.kit_field.KitFieldModel`) the calibration the earlier
    phases of the mission (the identification's openings, the detumbling's pulses: dozens of steps per
    channel) would have left it: each channel's F_a as the truth's magnet makes it at the sensor, with a
    seeded error of `sigma_frac` of |F_a| per axis and that covariance; restored as after a restart (the
    steps of this run still judge and refine it)."""
    from hil.deorbit_kit import HOME_AXIS
    from hil.kit_field import dipole_field_T

    rng = np.random.default_rng(20_000 + seed)
    truth = sim.kit_field
    fa, var = [], []
    for ch, pos in zip(sim.kit.channels, truth.positions_m):
        f = dipole_field_T(ch.dipole_Am2 * HOME_AXIS[ch.index], -pos)
        s = sigma_frac * float(np.linalg.norm(f))
        fa.append(f + rng.normal(0.0, s, 3))
        var += [s * s] * 3
    design = [float(x) for m in kit_field.models for x in m.fa_design_T]
    kit_field.restore({"fa_T": [float(x) for f in fa for x in f], "P": np.diag(var).tolist(), "fa_design_T": design,
                       "steps": [0] * len(fa)})


def _score_estimate(tr: Trace, src, sim) -> None:
    """The onboard estimate `src` at its latest sample against the truth then (NaN without one)."""
    bank = getattr(src, "bank", None)
    if bank is None or not bank.started:
        for lst in (tr.est_yaw, tr.est_pitch, tr.err_yaw, tr.err_pitch, tr.err_rate_radps):
            lst.append(math.nan)
        tr.trusted.append(bool(src is not None and src.trusted))
        return
    R_bo, w_rel, _, _, _ = bank.orbital(bank.t_s)
    R_true, w_true, _ = sim.attitude_orbital(sim.clock.true_s(bank.t_s))
    ye, pe, _ = euler_zyx(R_bo)
    yt, pt, _ = euler_zyx(R_true)
    tr.est_yaw.append(ye)
    tr.est_pitch.append(pe)
    tr.err_yaw.append(_wrap(ye - yt))
    tr.err_pitch.append(_wrap(pe - pt))
    tr.err_rate_radps.append(float(np.linalg.norm(w_rel - w_true)))
    tr.trusted.append(bool(src.trusted))


def _wrap(a: float) -> float:
    return (a + math.pi) % (2.0 * math.pi) - math.pi


def _sign(ch) -> int:
    """Polarity of an emulated magnet from its rotor angle (+1 near home, −1 near half a turn)."""
    r = ch.rotor_steps % 200
    return 1 if min(r, 200 - r) < 50 else -1


def row(name: str, this_run: str, paper: str) -> str:
    """One line of the report's comparison table."""
    return f"{name:34s}{this_run:>22s}{paper:>22s}"


def report(r: BenchResult) -> str:
    d = r.as_dict()
    o, tu, e = d["capsule_openings"], d["magnet_turns"], d["energy_J"]
    conv = d["converged_at_s"]
    lines = [
        f"de-orbit kit closed loop: scenario {r.scenario}, {r.duration_s:.0f} s, law {r.law}, "
        f"start at argument of latitude {r.sim.orbit.arg_lat0_deg:g}°",
        f"  loop {r.rate_hz:g} Hz (fsw.scheduler), dynamics step {r.step_s:g} s, wall {r.wall_s:.1f} s",
        f"  attitude for the controller: {r.attitude_source}",
        f"  atmosphere: {r.density}",
        "",
        f"{'':34s}{'this run':>22s}{'lapkhanov2019':>22s}",
        row(f"yaw error after {r.settle_s:.0f} s [rad]", f"{d['yaw_err_max_rad']:.3f}", "<= 0.2"),
        row(f"pitch error after {r.settle_s:.0f} s [rad]", f"{d['pitch_err_max_rad']:.3f}", "<= 0.2"),
        row("within 0.2 rad from [s]", "never" if math.isnan(conv) else f"{conv:.0f}", "-"),
        *([row("estimate RMS yaw / pitch [rad]", f"{d['att_err_rms_rad']['yaw']:.3f} / "
                                                 f"{d['att_err_rms_rad']['pitch']:.3f}", "(truth)"),
           row("estimate RMS rate [deg/s]", f"{d['rate_err_rms_dps']:.4f}", "(truth)"),
           row("acting on the estimate from [s]", "never" if math.isnan(d["trusted_from_s"])
               else f"{d['trusted_from_s']:.0f}", "-"),
           row("decisions held (capsules closed)", f"{d['decisions_held']:d}", "-")]
          if r.attitude == "estimate" else []),
        row("capsule openings pitch + yaw", f"{o['pitch']:d} + {o['yaw']:d}", "15 + 30"),
        row("magnet turns pitch + yaw", f"{tu['pitch']:d} + {tu['yaw']:d}", "35 + 25"),
        row("energy capsules + magnets [J]", f"{e['capsules']:.0f} + {e['magnets']:.0f}", "1053 + 702"),
        row("energy pitch + yaw channel [J]", f"{e['pitch']:.0f} + {e['yaw']:.0f}", "-"),
        f"{'energy total [J]':34s}{e['total']:>22.0f}{'1755':>22s}",
        f"{'interlock violations':34s}{d['interlock_violations']:>22d}{'-':>22s}",
        f"  (flight monitor {d['interlock_violations_flight']}, emulator truth {d['interlock_violations_truth']}; "
        f"refused by the gate {d['interlock_refusals']}; energy by the emulator's truth {d['energy_truth_J']:.0f} J)",
        f"  kit state at the end: {d['controller_state']}, safe entries {d['safe_entries']}, "
        f"recoveries {d['recoveries']}, faults {d['fault_bits']}",
    ]
    return "\n".join(lines)


def plot(r: BenchResult, path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    tr = r.trace
    t = np.asarray(tr.t_s)
    fig, ax = plt.subplots(3, 2, figsize=(12, 9), sharex=True)
    for a, y, est, name in ((ax[0, 0], tr.yaw, tr.est_yaw, "yaw ψ"), (ax[0, 1], tr.pitch, tr.est_pitch, "pitch θ")):
        a.plot(t, y, lw=1.0, label="truth")
        if r.attitude == "estimate" and np.isfinite(np.asarray(est, float)).any():
            a.plot(t, est, lw=0.8, ls="--", color="tab:orange", label="onboard estimate")
        a.axhspan(-0.2, 0.2, color="tab:green", alpha=0.12, label="±0.2 rad")
        a.axvline(r.settle_s, color="grey", ls=":", lw=0.8)
        a.set_ylabel(f"{name} [rad]")
        a.legend(loc="upper right", fontsize=8)
    ax[0, 0].set_title("Stabilisation by yaw (cf. Fig. 3)")
    ax[0, 1].set_title("Stabilisation by pitch (cf. Fig. 4)")
    ax[1, 0].plot(t, np.asarray(tr.m_z) * 1e3, lw=0.8, color="tab:red")
    ax[1, 0].set_ylabel("M_z,ctrl [mN·m]")
    ax[1, 0].set_title("Control moment, yaw (cf. Fig. 5)")
    ax[1, 1].plot(t, np.asarray(tr.m_y) * 1e3, lw=0.8, color="tab:red")
    ax[1, 1].set_ylabel("M_y,ctrl [mN·m]")
    ax[1, 1].set_title("Control moment, pitch (cf. Fig. 7)")
    ax[2, 0].fill_between(t, tr.pulse_yaw, step="post", color="tab:purple", lw=0)
    ax[2, 0].set_ylabel("yaw magnet: opening × sign")
    ax[2, 0].set_title("Pulses for M_z,ctrl (cf. Fig. 6)")
    ax[2, 1].fill_between(t, tr.pulse_pitch, step="post", color="tab:purple", lw=0)
    ax[2, 1].set_ylabel("pitch magnet: opening × sign")
    ax[2, 1].set_title("Pulses for M_y,ctrl (cf. Fig. 8)")
    for a in ax[2]:
        a.set_xlabel("time [s]")
        a.set_ylim(-1.1, 1.1)
    d = r.as_dict()
    fig.suptitle(f"De-orbit kit, {r.scenario}, law {r.law}: {d['capsule_openings']['total']} openings, "
                 f"{d['magnet_turns']['total']} turns, {d['energy_J']['total']:.0f} J "
                 f"(paper: 45, 60, 1755 J); attitude from {r.attitude}", fontsize=10)
    fig.tight_layout()
    try:
        save_figure(fig, path, dpi=110)
    finally:
        plt.close(fig)


SWEEP_STARTS_DEG = tuple(45.0 * k for k in range(8))
RUN_KEYS = ("arg_lat0_deg", "seed", "duration_s", "settle_s", "yaw_err_max_rad", "pitch_err_max_rad",
            "within_0p2_rad", "converged_at_s", "att_err_rms_rad", "att_err_rms_rad_max", "rate_err_rms_dps",
            "trusted_from_s", "decisions_held", "interlock_violations", "safe_entries", "wall_s")


def sweep_task(run: Run, *, scenario_name: str, attitude: str, **kwargs) -> dict:
    """A campaign's task: one run of the sweep (its start on the orbit and seed from the run); the JSON's row
    but the wall time (a run's result depends on its start and seed only)."""
    d = run_bench(scenario_name, arg_lat0_deg=run.params["arg_lat0_deg"], seed=run.seed[0], attitude=attitude,
                  **kwargs).as_dict()
    row_ = sweep_row(d)
    del row_["wall_s"]
    return row_


def sweep(scenario_name: str = DEFAULT_SCENARIO, *, starts: int = 8, seeds: int = 5, attitude: str = "estimate",
          out=None, campaign=None, **kwargs) -> dict | int:
    """`starts` starts on the orbit × `seeds` seeds, one line each on `out` (default stdout); the
    aggregates of the targets. The runs are a campaign (bench.campaign): `campaign` = (parser, arguments) of
    its options (default: in this process); an exit status instead for --rerun or a failed run."""
    out = out or sys.stdout
    deorbit_scenario(scenario_name)  # refused before a campaign starts, not in each of its runs
    specs = [Run(f"u{lat0:g}-s{seed}", (seed,), {"arg_lat0_deg": lat0}) for lat0 in SWEEP_STARTS_DEG[:starts]
             for seed in range(seeds)]
    config = {"benchmark": "bench.deorbit --sweep", "scenario": scenario_name, "attitude": attitude,
              **{k: ([f.__dict__ for f in v] if k == "faults" else v) for k, v in kwargs.items()}}
    fn = functools.partial(sweep_task, scenario_name=scenario_name, attitude=attitude, **kwargs)

    def line(run: Run, d: dict) -> None:
        print(f"start {d['arg_lat0_deg']:5.0f} deg seed {d['seed']}: yaw {d['yaw_err_max_rad']:.3f} pitch "
              f"{d['pitch_err_max_rad']:.3f} rad, {d['energy_J']:.0f} J, estimate RMS "
              f"{d['att_err_rms_rad_max']:.3f} rad", file=out, flush=True)
    elapsed: dict = {}
    if campaign is None:
        runs = run_campaign(fn, specs, config=config, name="deorbit", workers=1, progress=False, on_result=line,
                            elapsed_s=elapsed)
    else:
        runs = campaign_options.execute(*campaign, fn, specs, config, name="deorbit", on_result=line,
                                        elapsed_s=elapsed)
        if isinstance(runs, int):
            return runs
    for spec, r in zip(specs, runs):
        r["wall_s"] = round(elapsed[spec.id], 2)
    res = aggregate(runs, scenario_name, attitude, out)
    if attitude == "estimate":
        res["kit_calibration"] = kwargs.get("kit_calibration", "handed-over")
    return res


def sweep_row(d: dict) -> dict:
    """A sweep's row of one run's JSON (`BenchResult.as_dict`): `RUN_KEYS`, the energy as its total."""
    row_ = {k: d[k] for k in RUN_KEYS}
    row_["energy_J"] = d["energy_J"]["total"] if isinstance(d["energy_J"], dict) else d["energy_J"]
    return row_


def aggregate(runs: list[dict], scenario_name: str, attitude: str, out=None) -> dict:
    """The sweep's JSON from its rows (:func:`sweep_row`), however they were run (one process, or one
    run's JSON each), with the aggregates of the targets; the summary line on `out` (default stdout)."""
    out = out or sys.stdout
    energy = np.array([r["energy_J"] for r in runs])
    est = np.array([r["att_err_rms_rad_max"] for r in runs], float)
    res = {"scenario": scenario_name, "attitude_source": attitude, "runs": runs,
           "fraction_within_0p2_rad": float(np.mean([r["within_0p2_rad"] for r in runs])),
           "energy_J_mean": float(energy.mean()), "energy_J_max": float(energy.max()),
           "att_err_rms_rad_max": float(np.nanmax(est)) if np.isfinite(est).any() else math.nan,
           "paper": PAPER}
    print(f"{len(runs)} runs, attitude {attitude}: within 0.2 rad {100 * res['fraction_within_0p2_rad']:.0f} %, "
          f"energy mean {res['energy_J_mean']:.0f} J, max {res['energy_J_max']:.0f} J, worst estimate RMS "
          f"{res['att_err_rms_rad_max']:.3f} rad", file=out)
    return res


def controller_overrides(items: list[str]) -> dict:
    """`FIELD=VALUE` strings as replacements of `ControllerConfig`'s fields, each parsed as its default's type
    (numbers and names only); ValueError with what is wrong."""
    defaults = {f.name: f.default for f in dataclasses.fields(ControllerConfig)}
    out: dict = {}
    for item in items:
        name, sep, text = item.partition("=")
        name = name.strip()
        if not sep or name not in defaults:
            raise ValueError(f"--controller {item!r}: need FIELD=VALUE with FIELD one of ControllerConfig's fields")
        kind = type(defaults[name])
        if kind not in (int, float, str):
            raise ValueError(f"--controller {name}: only numbers and names can be set here, not a {kind.__name__}")
        try:
            value = kind(text)
        except ValueError:
            raise ValueError(f"--controller {name}: {text!r} is not a {kind.__name__}") from None
        if kind is float and not math.isfinite(value):
            raise ValueError(f"--controller {name}: {text!r} is not finite")
        out[name] = value
    ControllerConfig(**out)  # its own checks (ranges, names)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = ArgumentParser(prog="python -m bench.deorbit", description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default=DEFAULT_SCENARIO, metavar="NAME|FILE")
    ap.add_argument("--duration", type=finite_float(0, min_exclusive=True), default=None, metavar="S",
                    help="default: the scenario's (10,800 s)")
    ap.add_argument("--rate", type=finite_float(1, 100), default=10.0, metavar="HZ",
                    help="loop rate, 1 to 100 Hz (default 10 Hz)")
    ap.add_argument("--arg-lat0", type=finite_float(), default=None, metavar="DEG",
                    help="argument of latitude at t = 0 (default: the scenario's, 0°): start elsewhere on the orbit")
    ap.add_argument("--law", choices=("mpc", "paper", "energy"), default="mpc",
                    help="what produces M_theor: the receding-horizon choice (default), the PD law, or the "
                         "energy law (fsw/deorbit/energy_horizon.py)")
    ap.add_argument("--fault", action="append", default=[], metavar="KIND:CH:T[:VALUE]",
                    help="inject a fault, e.g. stall:pitch:1500, stuck:yaw:900:0.5, switch:yaw:600:closed=1")
    ap.add_argument("--attitude", choices=("estimate", "truth"), default="estimate",
                    help="the controller's attitude: the box's own estimate (default) or the simulation truth")
    ap.add_argument("--seed", type=int_range(0, 2**31 - 1), default=0,
                    help="sensor noise and handed-over calibration errors (default 0)")
    ap.add_argument("--kit-calibration", choices=KIT_CALIBRATIONS, default="handed-over",
                    help="on the estimate: the kit-field calibration the box starts with, the one the mission's "
                         "earlier phases leave (default: the truth's magnets, 1 %% errors) or none (the design's, "
                         "15 %% prior)")
    ap.add_argument("--controller", action="append", default=[], metavar="FIELD=VALUE",
                    help="replace a number or name of the controller's configuration (fsw.deorbit.controller."
                         "ControllerConfig), e.g. continuation_reweight=2; repeatable")
    ap.add_argument("--sweep", action="store_true",
                    help="the starts on the orbit x seeds (default 8 x 5 = 40 runs); JSON: runs and aggregates")
    ap.add_argument("--starts", type=int_range(1, 8), default=8, metavar="N",
                    help="--sweep: the first N of the 8 starts (arguments of latitude 0, 45, ..., 315 deg)")
    ap.add_argument("--seeds", type=int_range(1, 100), default=5, metavar="N", help="--sweep: seeds 0..N-1")
    ap.add_argument("--json", metavar="FILE", help="write the numbers as JSON")
    ap.add_argument("--plot", metavar="FILE.png", help="write the figure")
    campaign_options.add_arguments(ap)
    args = ap.parse_args(argv)
    campaign_options.check(ap, args)
    if not args.sweep and (args.results or args.rerun):
        ap.error("--results and --rerun are for --sweep (one run has no campaign to keep)")
    scenario_file = args.scenario if Path(args.scenario).is_file() else None
    check_paths_or_exit(ap, inputs={"--scenario": scenario_file}, outputs={"--json": args.json, "--plot": args.plot,
                                                                           **campaign_options.outputs(args)})
    check_plot_path_or_exit(ap, args.plot)
    if args.sweep and args.plot:
        ap.error("--plot is for one run, not --sweep")
    try:
        faults = [Fault.parse(f) for f in args.fault]
        overrides = controller_overrides(args.controller)
        if args.sweep:
            more = {"controller_overrides": overrides} if overrides else {}  # the default's campaign unchanged
            out = sweep(args.scenario, duration_s=args.duration, rate_hz=args.rate, law=args.law, faults=faults,
                        attitude=args.attitude, starts=args.starts, seeds=args.seeds, campaign=(ap, args),
                        kit_calibration=args.kit_calibration, **more)
            if isinstance(out, int):
                return out
        else:
            r = run_bench(args.scenario, duration_s=args.duration, rate_hz=args.rate, law=args.law, faults=faults,
                          arg_lat0_deg=args.arg_lat0, attitude=args.attitude, seed=args.seed,
                          kit_calibration=args.kit_calibration, controller_overrides=overrides)
    except ValueError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    if args.sweep:
        if args.json:
            write_atomic(args.json, json.dumps(out, indent=2, default=float))
            print(f"wrote {args.json}")
        return 0
    print(report(r))
    if args.json:
        write_atomic(args.json, json.dumps(r.as_dict(), indent=2, default=float))
        print(f"wrote {args.json}")
    if args.plot:
        plot(r, args.plot)
        print(f"wrote {args.plot}")
    return 0


if __name__ == "__main__":
    from fsw.startup import exit_with

    exit_with(main)
