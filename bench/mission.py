"""The mission benchmark: `python -m bench.mission [--seeds N] [--json FILE] [--plot FILE.png]`.

Scenario `hil/scenarios/amds_mission.toml`: the AMDS-like spacecraft with its de-orbit kit at 600 km,
its tensor unknown to the box (the truth differs from the box's guess by +25 %, +20 %, −20 % on the
diagonal, with small products). Each seed draws a tumble of 2–5 °/s about a random axis (relative to the
orbital frame) and a random attitude, the sensor's noise and the host calibration's errors. Composed as
SITL is (`hil.sitl.build`, lockstep, the flight software at `--rate` Hz on a null link), with the mission
(`fsw.deorbit.mission`) driving everything automatically: TUMBLING → RATES_KNOWN → IDENTIFYING (the kit's
magnets as the known torque) → DETUMBLING (the kit's pulses, `fsw.deorbit.detumble`) → STABILISING (the
de-orbit controller on the onboard estimate with the identified tensor) → STABILISED.

Per run (:func:`run_one`; each seed a campaign's run, bench.campaign: --workers, --scheduler, --results,
--rerun): the time each phase was entered, the
kit's energy per phase, the identified tensor against the truth (`inertia_err_pct`: the largest
component error in % of the largest true moment; `ci95_covered`: every component within its 95 %
interval), `stabilised` (STABILISED reached and the true yaw and pitch within 0.2 rad over the last
`score_s`), the largest true |ω| after the kit first acted against the tumble at the start
(`spun_up`: above it by 10 %), and the final phase with its reason. The aggregate JSON has `runs`,
`inertia_err_pct_max`, `ci95_coverage` (the fraction of runs whose six intervals all cover),
`error_sigma_rms` (each component's error in its own σ, RMS over the runs: ≈ 1 when the intervals are right),
`fraction_stabilised`, `time_to_phase_s` (mean and max per phase over the runs that reached it) and
`energy_J_by_phase` (mean per phase); `kit_residual_uT_rms` per run (per axis, on the samples the box used
while a magnet was open: the kit's field it took out, `fsw.deorbit.kit_field`, against the truth's) and
`kit_residual_uT_rms_max` (worst axis of the worst run).

`--fault KIND:CH:T` injects a kit fault into the emulator (as `bench.deorbit`: stall, stuck, switch, gpio)
at true time T. `--restart T` stops the flight software at true time T and starts it again on the running
world (`hil.sitl.build` with `sim`): a new driver on the same chip, the kit's applications on the same
lines, the mission from TUMBLING; what the box keeps comes back from its state directory (`fsw.persist`:
the host calibration, the kit's field, the inertia estimate, the time), a temporary one per run. The run's
figures then add up over the flight software's lives (energy, attempts, transitions, with ``restarts``).

The benchmark runs on a null link: after the hand-over at the start (time, orbit, host calibration)
the box hears nothing from the ground, every phase change is automatic, and its telemetry goes nowhere.
The whole mission is thus flown as a link lost from the start to the end.
"""
from __future__ import annotations

import dataclasses
import functools
import json
import math
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from bench.campaign import options as campaign_options
from bench.campaign.runs import Run
from fsw.argtypes import ArgumentParser, check_paths_or_exit, finite_float, int_range
from fsw.config import RunConfig
from fsw.deorbit.controller import euler_zyx
from fsw.deorbit.mission import MissionConfig, Phase
from fsw.estimation.inertia import params, z_value
from fsw.files import write_atomic
from fsw.system import NullLink
from ground.plot import check_plot_path_or_exit, save_figure

from bench.deorbit import Fault, _sign, hand_over_calibration
from hil import scenario as scenarios
from hil import sitl

DEFAULT_SCENARIO = "amds_mission"
DEFAULT_PARAMS = {"scenario": DEFAULT_SCENARIO, "duration_s": None, "rate_hz": 5.0, "rate_filter": "euler",
                  "faults": (), "restarts": (), "tumble_dps": (2.0, 5.0), "score_s": 1800.0, "trace": False,
                  "mission": {}}
PHASES = tuple(p.name for p in Phase)


def seeded_scenario(scn: scenarios.Scenario, seed: int, tumble_dps=(2.0, 5.0)) -> tuple[scenarios.Scenario, float]:
    """The scenario with seed `seed`'s tumble (|ω| uniform in `tumble_dps`, a random axis) and attitude
    (yaw, pitch, roll uniform); seed 0 keeps the scenario's own. Returns it and |ω| in °/s."""
    if seed == 0:
        return scn, float(np.linalg.norm(scn.deorbit.initial_rate_dps))
    rng = np.random.default_rng(20_000 + seed)
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    rate = float(rng.uniform(*tumble_dps))
    ypr = (float(rng.uniform(-180, 180)), float(np.degrees(np.arcsin(rng.uniform(-1, 1)))),
           float(rng.uniform(-180, 180)))
    spec = dataclasses.replace(scn.deorbit, initial_rate_dps=tuple(float(x) for x in rate * axis), initial_ypr_deg=ypr)
    return dataclasses.replace(scn, deorbit=spec), rate


def run_one(seed: int, params: dict | None = None) -> dict:
    """One mission from a tumble; `params` (see DEFAULT_PARAMS) override the defaults (`mission`: fields of
    `fsw.deorbit.mission.MissionConfig`). A JSON-ready dict."""
    p = {**DEFAULT_PARAMS, **(params or {})}
    if not p["restarts"]:
        return _run(seed, p, None)
    with tempfile.TemporaryDirectory(prefix="mission-state-") as state_dir:
        return _run(seed, p, state_dir)


def _run(seed: int, p: dict, state_dir: str | None) -> dict:
    scn, tumble = seeded_scenario(scenarios.load(p["scenario"]), seed, p["tumble_dps"])
    if scn.mission is None:
        raise ValueError(f"scenario {scn.name!r} has no [mission] table")
    duration = float(p["duration_s"] or scn.mission.duration_s)
    rate_hz = float(p["rate_hz"])
    step = 1.0 / rate_hz
    cfg = sitl.SitlConfig(RunConfig(rate_hz=rate_hz, buffer_frames=0, rate_filter=p["rate_filter"],
                                    state_dir=state_dir), scenario=scn, seed=seed, max_step_s=step)

    def start(sim=None):
        return sitl.build(cfg, link=NullLink(), run_id=0, mission_options={"config": MissionConfig(**p["mission"])},
                          sim=sim)

    box = start()
    sim, fsw = box.sim, box.fsw
    hand_over_calibration(fsw.calibration, sim.host, seed=seed)
    mission, kit = fsw.apps["mission"], fsw.apps["deorbit"]
    lives = [(mission, kit)]
    faults = sorted((Fault.parse(f) if isinstance(f, str) else f for f in p["faults"]), key=lambda f: f.t_s)
    restarts = sorted(float(t) for t in p["restarts"])
    trace = {k: [] for k in ("t_s", "phase", "rate_dps", "rate_est_dps", "rate_err_dps", "rate_sigma_dps", "yaw",
                             "pitch", "est_yaw", "est_pitch", "pulse_pitch", "pulse_yaw", "energy_J")}
    yaw_pitch = []
    rate_after_kit = 0.0
    kit_sq, kit_n = np.zeros(3), 0  # the kit's field the box took out against the truth's, magnets open
    n = int(round(duration * rate_hz))
    every = max(1, int(round(rate_hz)))
    wall0 = time.perf_counter()
    try:
        for k in range(n + 1):
            t_box = box.t0_s + k * step
            box.advance(t_box)
            while faults and faults[0].t_s <= sim.t_s:
                f = faults.pop(0)
                sim.kit.inject(f.channel, f.kind, f.value)
            if restarts and restarts[0] <= sim.t_s:
                restarts.pop(0)
                box.close()
                box = start(sim)
                fsw = box.fsw
                mission, kit = fsw.apps["mission"], fsw.apps["deorbit"]
                lives.append((mission, kit))
            box.tick(t_box)
            kf = fsw.kit_field
            if (kf is not None and fsw.new_sample and not fsw.kit_skip and kf.unscreened
                    and not kf.moved_between(fsw.sample_t_s, t_box)):  # the kit as it was for the sample
                kit_sq += (fsw.kit_T - sim.extra_field_body_T(sim.t_s)) ** 2
                kit_n += 1
            if k % every:
                continue
            R_bo, _, _ = sim.attitude_orbital()
            yaw, pitch, _ = euler_zyx(R_bo)
            w_true = math.degrees(float(np.linalg.norm(sim.truth().omega_radps)))
            if any(m.phase in (Phase.DETUMBLING, Phase.STABILISING, Phase.STABILISED) for m, _ in lives):
                rate_after_kit = max(rate_after_kit, w_true)
            yaw_pitch.append((sim.t_s, yaw, pitch))
            if p["trace"]:
                rep = kit.attitude.report() if kit.attitude is not None and hasattr(kit.attitude, "report") else None
                chs = sim.kit.channels
                for key, v in (("t_s", sim.t_s), ("phase", int(mission.phase)), ("rate_dps", w_true),
                               ("rate_est_dps", math.degrees(mission.rate_radps)),
                               ("rate_err_dps", math.degrees(float(np.linalg.norm(mission.omega_radps
                                                                                  - sim.truth().omega_radps)))
                                if mission.omega_radps is not None else math.nan),
                               ("rate_sigma_dps", math.degrees(mission.rate_sigma_radps)), ("yaw", yaw),
                               ("pitch", pitch), ("est_yaw", rep.yaw_rad if rep else math.nan),
                               ("est_pitch", rep.pitch_rad if rep else math.nan),
                               ("pulse_pitch", chs[0].shutter * _sign(chs[0])),
                               ("pulse_yaw", chs[1].shutter * _sign(chs[1])),
                               ("energy_J", sum(kt.energy().total_J for _, kt in lives))):
                    trace[key].append(float(v))
    finally:
        box.close()
    wall = time.perf_counter() - wall0
    kit = (np.sqrt(kit_sq / kit_n) * 1e6).tolist() if kit_n else None
    return {**_result(seed, tumble, scn, lives, sim, yaw_pitch, rate_after_kit, duration, p, wall,
                      trace if p["trace"] else None), "kit_residual_uT_rms": kit, "kit_residual_samples": kit_n}


def _result(seed, tumble, scn, lives, sim, yaw_pitch, rate_after_kit, duration, p, wall, trace) -> dict:
    """The run's figures; `lives`: (mission, kit) of each start of the flight software, the last one's
    tensor and final phase, the others' energy, attempts and transitions added."""
    mission, kit = lives[-1]
    true6 = params(scn.inertia_kgm2)
    if mission.J_kgm2 is not None:
        id6 = params(mission.J_kgm2)
        ci = mission.ci95_kgm2   # of the tensor the mission took: its attempts combined, or kept over a restart
        err = id6 - true6
        err_pct = float(100 * np.max(np.abs(err)) / np.max(true6[:3]))
        covered = bool(np.all(np.abs(err) <= ci))
    else:
        id6, ci, err_pct, covered = np.full(6, math.nan), np.full(6, math.nan), math.nan, False
    transitions = [tr for m, _ in lives for tr in m.transitions]
    entered: dict[str, float] = {}
    for t, _, new, _ in transitions:
        entered.setdefault(Phase(new).name, float(t))
    ypt = np.asarray(yaw_pitch)
    last = ypt[:, 0] >= ypt[-1, 0] - p["score_s"]
    within = bool(np.all(np.abs(ypt[last, 1:]) <= 0.2))
    leds = [kt.energy() for _, kt in lives]
    by_phase = {ph: sum(m.energy_by_phase()[ph] for m, _ in lives) for ph in PHASES}
    return {
        "seed": seed, "scenario": scn.name, "duration_s": duration, "tumble_dps": tumble,
        "inertia_true": true6.tolist(), "inertia_id": id6.tolist(), "ci95": ci.tolist(),
        "inertia_err_pct": err_pct, "ci95_covered": covered, "ci95_pct": mission.ci95_pct,
        "ident_attempts": sum(m.attempts for m, _ in lives),
        "time_to_phase_s": entered, "energy_J_by_phase": by_phase,
        "energy_J": round(sum(led.total_J for led in leds), 1),
        "capsule_openings": sum(c.openings for led in leds for c in led.channels),
        "magnet_turns": sum(c.turns for led in leds for c in led.channels),
        "final_phase": mission.phase.name, "final_reason": mission.reason_text,
        "stabilised": bool(mission.phase is Phase.STABILISED and within),
        "within_0p2_rad_at_end": within,
        "yaw_pitch_end_rad": [float(ypt[-1, 1]), float(ypt[-1, 2])],
        "rate_max_after_kit_dps": rate_after_kit, "spun_up": bool(rate_after_kit > 1.1 * tumble),
        "interlock_violations": (sum(kt.sequencer.interlock_violations for _, kt in lives)
                                 + sim.kit.interlock_violations),
        "safe_entries": sum(kt.sequencer.safe_entries for _, kt in lives),
        "faults": [f if isinstance(f, str) else f.__dict__ for f in p["faults"]],
        "restarts": [float(t) for t in p["restarts"]],
        "detumble_decisions": sum(m.law.decisions for m, _ in lives),
        "detumble_held": sum(m.law.held for m, _ in lives),
        "transitions": [[t, Phase(a).name, Phase(b).name, why] for t, a, b, why in transitions],
        "wall_s": round(wall, 1), **({"trace": trace} if trace is not None else {}),
    }


def aggregate(runs: list[dict]) -> dict:
    """The figures over the runs (see the module docstring)."""
    errs = np.array([r["inertia_err_pct"] for r in runs], float)
    times = {}
    for ph in PHASES:
        ts = [r["time_to_phase_s"][ph] for r in runs if ph in r["time_to_phase_s"]]
        if ts:
            times[ph] = {"mean": float(np.mean(ts)), "max": float(np.max(ts)), "runs": len(ts)}
    energy = {ph: float(np.mean([r["energy_J_by_phase"][ph] for r in runs])) for ph in PHASES}
    return {
        "runs": runs,
        "inertia_err_pct_max": float(np.nanmax(errs)) if np.isfinite(errs).any() else math.nan,
        "inertia_err_pct_mean": float(np.nanmean(errs)) if np.isfinite(errs).any() else math.nan,
        "identified": int(np.isfinite(errs).sum()),
        "ci95_coverage": float(np.mean([r["ci95_covered"] for r in runs])),
        "error_sigma_rms": error_sigma_rms(runs),
        "fraction_stabilised": float(np.mean([r["stabilised"] for r in runs])),
        "spun_up": int(sum(r["spun_up"] for r in runs)),
        "time_to_phase_s": times, "energy_J_by_phase": energy,
        "energy_J_mean": float(np.mean([r["energy_J"] for r in runs])),
        "interlock_violations": int(sum(r["interlock_violations"] for r in runs)),
        "kit_residual_uT_rms_max": max((max(r["kit_residual_uT_rms"]) for r in runs
                                        if r.get("kit_residual_uT_rms")), default=None),
    }


def error_sigma_rms(runs: list[dict]) -> list[float] | None:
    """Each component's error in units of its own σ (the 95 % half-width over z₀.₉₅), RMS over the runs
    that identified a tensor (Ixx, Iyy, Izz, Ixy, Ixz, Iyz): 1 for intervals of the right width, a finer
    measure than the coverage of ten runs. None when no run has one."""
    z = []
    with np.errstate(divide="ignore", invalid="ignore"):
        for r in runs:
            if all(k in r for k in ("inertia_id", "inertia_true", "ci95")):
                v = (np.asarray(r["inertia_id"], float) - np.asarray(r["inertia_true"], float)) \
                    / (np.asarray(r["ci95"], float) / z_value(0.95))
                if v.shape == (6,) and np.all(np.isfinite(v)):
                    z.append(v)
    return np.sqrt(np.mean(np.square(z), axis=0)).tolist() if z else None


def line(r: dict) -> str:
    t = r["time_to_phase_s"]
    return (f"seed {r['seed']:3d}: tumble {r['tumble_dps']:.2f} dps, tensor err {r['inertia_err_pct']:.2f} % "
            f"(ci95 {r['ci95_pct']:.2f} %, covered {r['ci95_covered']}), detumbling at "
            f"{t.get('DETUMBLING', math.nan):.0f} s, stabilising at {t.get('STABILISING', math.nan):.0f} s, "
            f"stabilised at {t.get('STABILISED', math.nan):.0f} s, end {r['final_phase']} ({r['final_reason']}), "
            f"{r['energy_J']:.0f} J" + (f", wall {r['wall_s']:.0f} s" if "wall_s" in r else ""))


def plot(r: dict, path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    tr = r["trace"]
    t = np.asarray(tr["t_s"])
    fig, ax = plt.subplots(4, 1, figsize=(11, 11), sharex=True)
    ax[0].plot(t, tr["phase"], drawstyle="steps-post", color="k")
    ax[0].set_yticks(range(len(PHASES)), PHASES, fontsize=7)
    ax[0].set_title(f"mission, seed {r['seed']}: phases (tumble {r['tumble_dps']:.1f} °/s, tensor error "
                    f"{r['inertia_err_pct']:.2f} % of the largest moment, {r['energy_J']:.0f} J)")
    ax[1].semilogy(t, np.maximum(tr["rate_dps"], 1e-3), label="|ω| truth")
    ax[1].semilogy(t, np.maximum(np.nan_to_num(tr["rate_est_dps"], nan=1e-3), 1e-3), lw=0.8, label="|ω| estimated")
    ax[1].set_ylabel("rate [°/s]")
    ax[1].legend(fontsize=8)
    ax[2].fill_between(t, tr["pulse_pitch"], step="post", color="tab:purple", lw=0, alpha=0.7, label="pitch magnet")
    ax[2].fill_between(t, tr["pulse_yaw"], step="post", color="tab:orange", lw=0, alpha=0.5, label="yaw magnet")
    ax[2].set_ylabel("opening × sign")
    ax[2].legend(fontsize=8)
    for key, est, c in (("yaw", "est_yaw", "tab:blue"), ("pitch", "est_pitch", "tab:red")):
        ax[3].plot(t, tr[key], color=c, lw=0.8, label=f"{key} truth")
        ax[3].plot(t, tr[est], color=c, lw=0.8, ls="--", label=f"{key} estimated")
    ax[3].axhspan(-0.2, 0.2, color="tab:green", alpha=0.12)
    ax[3].set_ylabel("[rad]")
    ax[3].set_xlabel("time [s]")
    ax[3].legend(fontsize=8, ncol=4)
    fig.tight_layout()
    try:
        save_figure(fig, path, dpi=100)
    finally:
        plt.close(fig)


def mission_task(run: Run, *, params: dict) -> dict:
    """A campaign's task (bench.campaign): the mission of seed `run.seed[0]` (`run_one`), without its wall
    time (a run's result depends on its seed and parameters alone)."""
    r = run_one(run.seed[0], {**params, "trace": run.params["trace"]})
    r.pop("wall_s", None)
    return r


def merge(ap, paths: list[str], out_path: str | None) -> int:
    """The runs of several JSON files of this tool (e.g. two processes' seeds) aggregated into `out_path`."""
    if not out_path:
        ap.error("--merge needs --json")
    if Path(out_path).resolve() in {Path(x).resolve() for x in paths}:
        ap.error("--json must not be one of the --merge inputs")
    runs, first = [], None
    for path in paths:
        try:
            d = json.loads(Path(path).read_text(encoding="utf-8"))
            runs += d["runs"]
        except (OSError, ValueError, KeyError, TypeError) as e:
            print(f"error: {path}: not a bench.mission JSON ({e})", file=sys.stderr)
            return 1
        first = first or d
    runs.sort(key=lambda r: r["seed"])
    write_atomic(out_path, json.dumps({"scenario": first["scenario"], "params": first["params"], **aggregate(runs)},
                                      indent=2, default=float))
    print(f"wrote {out_path}: {len(runs)} runs")
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = ArgumentParser(prog="python -m bench.mission", description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default=DEFAULT_SCENARIO, metavar="NAME|FILE")
    ap.add_argument("--seeds", type=int_range(1, 1000), default=10, metavar="N", help="seeds 0..N-1 (default 10)")
    ap.add_argument("--first-seed", type=int_range(0, 2**31 - 1), default=0, metavar="K")
    ap.add_argument("--duration", type=finite_float(0, min_exclusive=True), default=None, metavar="S",
                    help="default: the scenario's [mission] duration_s")
    ap.add_argument("--rate", type=finite_float(1, 100), default=DEFAULT_PARAMS["rate_hz"], metavar="HZ",
                    help="loop rate (default 5 Hz)")
    ap.add_argument("--fault", action="append", default=[], metavar="KIND:CH:T[:VALUE]",
                    help="a kit fault, as bench.deorbit's: stall:pitch:1500, stuck:yaw:900:0.5")
    ap.add_argument("--restart", action="append", default=[], type=finite_float(0), metavar="T",
                    help="stop the flight software at true time T s and start it again on the running world")
    ap.add_argument("--json", metavar="FILE", help="write the runs and the aggregate figures (after every run)")
    ap.add_argument("--merge", nargs="+", metavar="JSON", default=None,
                    help="no run: the runs of these JSON files (from this tool) aggregated into --json")
    ap.add_argument("--plot", metavar="FILE.png", help="the first seed's phases, rates, pulses, attitude")
    campaign_options.add_arguments(ap)
    args = ap.parse_args(argv)
    campaign_options.check(ap, args)
    scenario_file = args.scenario if Path(args.scenario).is_file() else None
    check_paths_or_exit(ap, inputs={"--scenario": scenario_file},
                        outputs={"--json": args.json, "--plot": args.plot, **campaign_options.outputs(args)})
    check_plot_path_or_exit(ap, args.plot)
    if args.merge:
        return merge(ap, args.merge, args.json)
    params = {"scenario": args.scenario, "duration_s": args.duration, "rate_hz": args.rate,
              "faults": tuple(args.fault), "restarts": tuple(args.restart)}
    try:
        for f in args.fault:
            Fault.parse(f)
        if scenarios.load(args.scenario).mission is None:
            raise ValueError(f"scenario {args.scenario!r} has no [mission] table")
    except (ValueError, scenarios.ScenarioError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    seeds = range(args.first_seed, args.first_seed + args.seeds)
    # the first seed's run keeps its trace for --plot (in its result, so that a re-run gives the same)
    specs = [Run(f"seed{seed}", (seed,), {"trace": bool(args.plot) and seed == args.first_seed}) for seed in seeds]
    config = {"benchmark": "bench.mission", **params}
    runs: list[dict] = []
    elapsed: dict = {}

    def done(spec: Run, r: dict) -> None:
        runs.append({k: v for k, v in r.items() if k != "trace"})
        print(line(r), flush=True)
        if args.json:
            write_atomic(args.json, json.dumps({"scenario": args.scenario, "params": params, **aggregate(runs)},
                                               indent=2, default=float))

    got = campaign_options.execute(ap, args, functools.partial(mission_task, params=params), specs, config,
                                   name="mission", on_result=done, elapsed_s=elapsed)
    if isinstance(got, int):  # --rerun, or a run that failed
        return got
    runs = []
    for spec, r in zip(specs, got):
        if "trace" in r:
            plot(r, args.plot)
            print(f"wrote {args.plot}")
        runs.append({**{k: v for k, v in r.items() if k != "trace"}, "wall_s": round(elapsed[spec.id], 1)})
    if args.json:
        write_atomic(args.json, json.dumps({"scenario": args.scenario, "params": params, **aggregate(runs)},
                                           indent=2, default=float))
    out = {"scenario": args.scenario, "params": params, **aggregate(runs)}
    print(f"{len(runs)} runs: tensor error max {out['inertia_err_pct_max']:.2f} % of the largest moment, ci95 "
          f"coverage {100 * out['ci95_coverage']:.0f} %, stabilised {100 * out['fraction_stabilised']:.0f} %, "
          f"spun up {out['spun_up']}")
    if args.json:
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    from fsw.startup import exit_with

    exit_with(main)
