"""SITL: the flight software against the simulator, in lockstep, in one process —
`python -m hil.sitl` (or `python -m fsw.main --sitl`, which hands over to it).

Before each loop tick the simulator is advanced to the loop time, and the MMC5983MA driver talks to the
register-level emulator through the same bus interface it uses on hardware. `--speed 1` paces the
loop to real time; `--speed 0` runs as fast as possible. The flight software is composed exactly as on
target (`fsw.system.build_flight`); what SITL adds is the world around it: the scenario's simulator,
the identification experiment's tug (the simulator's torque schedule) and field model (the
scenario's orbit), the de-orbit kit's emulated lines and truth attitude, and the simulator's truth for
scoring (DEBRIS_SIM_STATE on the link; the rate errors in the status line and the summary).

Time: the loop's time is the box's clock (the flight software's injected clock). The simulator runs in
true time; the scenario's [clock] (`hil.box_clock`: offset, drift) maps one to the other where they
meet: :meth:`Sitl.advance` (the loop's `before_tick`), the truth handed to the flight software and to
scoring, the tug, the de-orbit kit's truth attitude. A run starts at box time `Sitl.t0_s` (true 0, or
later for a clock behind true time).

:func:`build` is the composition used by this command, the benchmarks and the soak.
"""
from __future__ import annotations

if __name__ == "__main__":
    from fsw.startup import interrupt_quietly

    interrupt_quietly()

import argparse  # noqa: E402
import math  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from dataclasses import dataclass, field, replace  # noqa: E402
from datetime import timezone  # noqa: E402
from pathlib import Path  # noqa: E402
from types import SimpleNamespace  # noqa: E402
from typing import TextIO  # noqa: E402

import numpy as np  # noqa: E402

from fsw.argtypes import ArgumentParser, check_paths_or_exit, finite_float, int_range  # noqa: E402
from fsw.config import RunConfig, add_run_options, check_key_or_exit, check_loop_rate, run_config  # noqa: E402
from fsw.drivers.mmc5983ma import FLIGHT_SCHEDULE, Mmc5983ma  # noqa: E402
from fsw.drivers.mmc5983ma_regs import Bandwidth, ContinuousFrequency  # noqa: E402
from fsw.estimation.onboard_field import InterpolatedOrbitField  # noqa: E402
from fsw.telemetry.dialect import FSW_SYSID  # noqa: E402
from fsw.timeorbit import TimeOrbit  # noqa: E402
from fsw.flight import FlightSoftware  # noqa: E402
from fsw.ident import IdentExperiment  # noqa: E402
from fsw.persist import BoxState  # noqa: E402
from fsw.runner import LoopResult, run_loop, run_program  # noqa: E402
from fsw.runner import status_line as flight_status  # noqa: E402
from fsw.runner import summary as flight_summary  # noqa: E402
from fsw.system import Flight, build_flight  # noqa: E402

from . import scenario as scenarios  # noqa: E402
from .sim import Simulator  # noqa: E402
from .ident_sitl import build_ident, field_model  # noqa: E402

#: the boot id of the box in SITL: one boot per process (a restart of the flight software keeps the time)
SITL_BOOT_ID = "sitl"
#: the chip's bandwidth settings by their nominal bandwidth (scenario key `bandwidth_hz`)
BANDWIDTH = {100: Bandwidth.BW_100HZ, 200: Bandwidth.BW_200HZ, 400: Bandwidth.BW_400HZ, 800: Bandwidth.BW_800HZ}


@dataclass(frozen=True)
class SitlConfig:
    """A SITL run: the flight software's configuration and the simulated world's."""

    run: RunConfig = field(default_factory=lambda: RunConfig(speed=0.0))
    #: a shipped scenario's name, a TOML file, or a loaded `hil.scenario.Scenario`
    scenario: str | scenarios.Scenario = "isoi"
    seed: int = 0
    #: the identification experiment's starting tensor, × identity, kg·m²
    ident_inertia_guess_kgm2: float = 100.0
    #: the simulator's integration step (default: 20 ms, or the loop period if shorter)
    max_step_s: float | None = None
    #: what the loop's step time is measured on: "cpu" (this thread's CPU time: the flight software's own
    #: work, whatever else runs on the machine) or "wall" (as on target, where nothing else runs)
    work_clock: str = "cpu"


@dataclass
class Sitl:
    """A composed SITL system."""

    cfg: SitlConfig
    scenario: scenarios.Scenario
    sim: Simulator
    driver: Mmc5983ma
    flight: Flight
    sigma_b_T: float
    #: the loop rate against the sample rate, when they are equal
    warning: str | None = None
    #: the box's state directory (`cfg.run.state_dir`), saved after every :meth:`tick`
    state: BoxState | None = None

    @property
    def fsw(self) -> FlightSoftware:
        return self.flight.fsw

    @property
    def t0_s(self) -> float:
        """The box's clock at the first tick (:func:`box_t0_s`)."""
        return box_t0_s(self.sim)

    def advance(self, box_t_s: float) -> None:
        """The simulator advanced to the true time at which the box's clock reads `box_t_s`."""
        self.sim.advance_to(self.sim.clock.true_s(box_t_s))
        settle = getattr(self.sim.sensor, "settle", None)
        if settle is not None:  # the chip's measurements done by now: the world's work, outside the tick
            settle()

    def tick(self, box_t_s: float) -> float:
        """One tick of the flight software at the box's time `box_t_s`, then its state saved (as the
        target's loop does after every tick); the tick's work (s)."""
        work = self.fsw.tick(box_t_s)
        if self.state is not None:
            self.state.tick(box_t_s)
        return work

    def close(self) -> None:
        """The state files written (what is pending) and the link closed: the flight software stops."""
        try:
            if self.state is not None:
                self.state.close()
        finally:
            self.flight.close()

    def run_as_on_target(self, duration_s: float, after_tick=None) -> list[float]:
        """`duration_s` of the box's time in lockstep, ticks timed as on target: a tick starts on its
        period's grid or, when the previous one ran late (its work measured by the scheduler's work timer),
        as soon as it ended, so a late loop lets the chip overwrite samples. `after_tick()` after each.
        Returns each tick's work (s)."""
        period = self.fsw.scheduler.period_s
        works: list[float] = []
        t, k = self.t0_s, 0
        while t < self.t0_s + duration_s:
            self.advance(t)
            work = self.tick(t)
            works.append(work)
            k += 1
            t = max(self.t0_s + k * period, t + work)
            if after_tick is not None:
                after_tick()
        return works

    def truth(self, box_t_s: float | None = None):
        """The simulator's truth at the box's time `box_t_s` (default: now)."""
        return box_truth(self.sim)(box_t_s)

    def header(self) -> str:
        r = self.cfg.run
        scn = self.scenario
        lines = [f"SITL scenario {scn.name}: {scn.description}",
                 f"loop {r.rate_hz:g} Hz, sensor {1.0 / self.driver.sample_period_s:g} Hz, speed "
                 f"{'max' if r.speed == 0 else f'{r.speed:g}x'}, seed {self.cfg.seed}, link {r.link}"]
        kit = self.fsw.apps.get("deorbit")
        if "mission" in self.fsw.apps:
            lines.append("mission (fsw.deorbit.mission) from a tumble: TUMBLING -> RATES_KNOWN -> IDENTIFYING -> "
                         "DETUMBLING -> STABILISING -> STABILISED; de-orbit kit emulated")
        elif kit is not None:
            lines.append(f"de-orbit kit: emulated; controller attitude from {kit.attitude.description}")
        if not self.sim.clock.is_true:
            c = self.sim.clock
            lines.append(f"box clock: offset {c.offset_s:g} s, drift {c.drift_ppm:g} ppm against true time")
        lines += self.flight.notes
        if self.warning:
            lines.append(self.warning)
        return "\n".join(lines)


def sitl_sensor(scenario_rate_hz: float, scenario_bw: Bandwidth, rate_hz: float | None
                ) -> tuple[float, Bandwidth, ContinuousFrequency]:
    """(sample rate, bandwidth, continuous mode) of the SITL magnetometer: the scenario's, or for a
    `--sample-rate` the narrowest bandwidth (least noise), no narrower than the scenario's, whose
    measurement takes at most half a sample period; continuous mode when the chip has that rate
    (1000 Hz needs BW = 800 Hz, DS p13-16), else single measurements on the driver's grid."""
    if not rate_hz:
        return scenario_rate_hz, scenario_bw, ContinuousFrequency.OFF
    if not 0 < rate_hz <= 1000.0:
        raise ValueError(f"--sample-rate must be in (0, 1000] Hz (the MMC5983MA's ceiling), got {rate_hz:g}")
    fits = [bw for bw in Bandwidth if bw >= scenario_bw and bw.measurement_time_s <= 0.5 / rate_hz]
    bw = fits[0] if fits else Bandwidth.BW_800HZ
    cm = next((f for f in ContinuousFrequency if f.rate_hz == rate_hz and f.fits(bw)), ContinuousFrequency.OFF)
    return float(rate_hz), bw, cm


def box_t0_s(sim: Simulator) -> float:
    """The box's clock at the first tick: what it reads when the simulated world starts (true time 0), or 0
    for a clock behind true time (the box starts when its clock reads 0: its time stamps are unsigned)."""
    return max(0.0, sim.clock.box_s(0.0))


def box_truth(sim: Simulator):
    """The simulator's truth looked up at the box's time (default: now)."""
    if sim.clock.is_true:
        return sim.truth
    return lambda box_t_s=None: sim.truth(None if box_t_s is None else sim.clock.true_s(box_t_s))


def onboard_field(scn: scenarios.Scenario) -> InterpolatedOrbitField | None:
    """The field along a circular orbit the flight software is given in SITL (the host-magnetics
    calibration's |B_model|, the identification's B_I): the onboard model (IGRF-14 at the flight degree,
    at knots a minute apart and interpolated, as on board)
    along the scenario's orbit, the Earth at the same angle at t = 0 as in the simulated world. None for
    a scenario with a TLE: the box then computes its own from the TLE and UTC it is handed
    (:func:`hand_over_time_and_orbit`)."""
    if scn.tle is not None:
        return None
    return InterpolatedOrbitField(field_model(scn))


def hand_over_time_and_orbit(scn: scenarios.Scenario, sim, r: RunConfig, t0_s: float) -> TimeOrbit:
    """The box's time-and-orbit application, handed what the ground would upload before the run: the UTC
    at the box's first loop time (true UTC: the ground's clock is right, the box's own may not be) and,
    in a scenario with a TLE, the box's TLE (`box_tle`, possibly older than the truth's) — through the
    same checks as an upload."""
    timeorbit = TimeOrbit(tle_file=r.tle_file, max_tle_age_d=r.tle_max_age_d)
    if scn.tle is not None:
        utc0 = scn.utc0.replace(tzinfo=timezone.utc).timestamp()
        line1, line2 = scn.box_tle or scn.tle
        timeorbit.preset(t0_s, utc0 + sim.clock.true_s(t0_s), line1, line2)
    return timeorbit


def build(cfg: SitlConfig, *, link=None, uplink=None, key: bytes | None = None, clock=None,
          run_id: int | None = None, ident: bool = True, ident_options: dict | None = None,
          kit_options: dict | None = None, mission_options: dict | None = None, sim: Simulator | None = None) -> Sitl:
    """The simulator of `cfg.scenario` and the flight software on its emulated magnetometer.

    `link`, `uplink`, `key`, `clock`, `run_id`: as `fsw.system.build_flight` (the soak hands in its radio
    model and key). The applications: the identification experiment unless `ident` is False (a tug and a
    field model: SITL has both; `ident_options`: more of its `fsw.ident.IdentConfig`), and in a scenario
    with a [deorbit] table the de-orbit kit on the emulated lines (`kit_options`: for
    `hil.deorbit_sim.build_kit`, e.g. the controller's law); with a [mission] table the mission
    (`hil.mission_sitl.build_mission`, `mission_options` for it) on the experiment and the kit.

    `cfg.run.state_dir`: the box keeps its state there as on target (`fsw.persist.BoxState`, the TLE in
    ``tle.txt`` unless `cfg.run.tle_file` names another; the box's clock is its monotonic clock, one boot
    per process), restored at the start and saved after every tick (:meth:`Sitl.tick`). `sim`: the
    flight software started again on this running world (a restart of the flight software: a new driver on
    the same chip, the kit's applications on the same lines, nothing handed over — what it knows comes
    back from its state directory)."""
    r = cfg.run
    scn = cfg.scenario if isinstance(cfg.scenario, scenarios.Scenario) else scenarios.load(cfg.scenario)
    step = cfg.max_step_s or min(0.02, 1.0 / r.rate_hz)
    restart = sim is not None
    if r.state_dir and not r.tle_file:
        r = replace(r, tle_file=str(Path(r.state_dir) / "tle.txt"))
    if sim is None and scn.deorbit is not None:  # the de-orbit kit's scenario: environment torques, kit emulator
        from .deorbit_sim import DeorbitSimulator
        sim = DeorbitSimulator(scn, seed=cfg.seed, max_step_s=step)
    elif sim is None:
        sim = Simulator(scn, seed=cfg.seed, max_step_s=step)
    rate_hz, bw, cm = sitl_sensor(scn.sample_rate_hz, BANDWIDTH[scn.bandwidth_hz], r.sample_rate_hz)
    warning = check_loop_rate(r.rate_hz, rate_hz)
    driver = Mmc5983ma(sim.sensor, bandwidth=bw, sample_period_s=1.0 / rate_hz, continuous=cm, **FLIGHT_SCHEDULE)
    sigma_b = math.hypot(scn.noise_T, bw.noise_rms_T)
    field = onboard_field(scn)
    timeorbit = (TimeOrbit(tle_file=r.tle_file, max_tle_age_d=r.tle_max_age_d) if restart
                 else hand_over_time_and_orbit(scn, sim, r, box_t0_s(sim)))
    onboard = []
    if ident:
        onboard.append(build_ident(scn, sim, sigma_b, cfg.ident_inertia_guess_kgm2,
                                   b_inertial=field.b_eci_T if field is not None else timeorbit,
                                   **(ident_options or {})))
    if scn.deorbit is not None:
        from .deorbit_sim import build_kit
        mission_kit = {"attitude": "estimate"} if scn.mission is not None else {}  # on its own estimate
        onboard.append(build_kit(sim, **{"sigma_b_T": sigma_b, **mission_kit, **(kit_options or {})}))
    if scn.mission is not None:  # the whole mission: the experiment's magnets are the kit's
        from .mission_sitl import build_mission
        onboard.append(build_mission(scn, onboard, **(mission_options or {})))
    flight = build_flight(r, driver, sigma_b_T=sigma_b, sample_rate_hz=rate_hz, truth=box_truth(sim), apps=onboard,
                          link=link, uplink=uplink, key=key, clock=clock, run_id=run_id, field=field,
                          timeorbit=timeorbit)
    if cfg.work_clock == "cpu":  # a lockstep world loses nothing to the OS's preemption: the loop's own work
        flight.fsw.scheduler.work_timer = time.thread_time
    state = None
    if r.state_dir:
        fsw = flight.fsw
        state = BoxState(r.state_dir, monotonic=lambda: sim.clock.box_s(sim.t_s), boot_id=SITL_BOOT_ID)
        state.restore(fsw.uplink.verifier if fsw.uplink is not None else None, timeorbit)
        state.restore_apps(r.system_id, calibration=fsw.calibration, kit_field=fsw.kit_field,
                           ident=next((a for a in onboard if isinstance(a, IdentExperiment)), None))
        flight.notes.extend(state.notes)
    return Sitl(cfg, scn, sim, driver, flight, sigma_b, warning, state)


# --- scoring against truth ------------------------------------------------------------------------

def perpendicular(w: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The part of `w` perpendicular to `b`."""
    bh = b / np.linalg.norm(b)
    return w - np.dot(w, bh) * bh


@dataclass
class Taken:
    """What scoring needs of one sample's pass through the pipeline (copied: the next pass overwrites)."""

    sample_t_s: float
    estimators: dict
    new_estimate: dict

    @classmethod
    def of(cls, fsw: FlightSoftware) -> "Taken":
        est = {name: SimpleNamespace(omega_radps=e.omega_radps.copy(), flags=e.flags,
                                     NO_ESTIMATE=getattr(e, "NO_ESTIMATE", 0), name=getattr(e, "name", ""))
               for name, e in fsw.estimators.items()}
        return cls(fsw.sample_t_s, est, dict(fsw.new_estimate))


@dataclass
class Score:
    """Errors of the onboard estimates against the simulator's truth, at the sample times."""

    boer_err: list = field(default_factory=list)
    deriv_err: list = field(default_factory=list)
    kalman_err: list = field(default_factory=list)
    #: the truth at the latest sample's time
    truth: object = None
    #: the flown filters that published, in order (" euler", " fixed→euler")
    filter: str = ""

    def add(self, fsw: FlightSoftware, tr) -> None:
        self.truth = tr
        if fsw.new_estimate["boer"]:
            w = fsw.estimators["boer"].omega_radps
            self.boer_err.append(np.linalg.norm(w - perpendicular(tr.omega_radps, tr.b_body_T)))
        if fsw.new_estimate["derivative"]:
            w = fsw.estimators["derivative"].omega_radps
            self.deriv_err.append(np.linalg.norm(w - tr.omega_radps))
        kf = fsw.estimators["kalman"]
        if fsw.new_estimate["kalman"] and not kf.flags & kf.NO_ESTIMATE:
            self.kalman_err.append(np.linalg.norm(kf.omega_radps - tr.omega_radps))
            name = getattr(kf, "name", "")
            if name and not self.filter.endswith(name):
                self.filter += ("→" if self.filter else " ") + name

    @staticmethod
    def rms_max(errs) -> tuple[float, float, int]:
        if not errs:
            return math.nan, math.nan, 0
        a = np.asarray(errs)
        return float(np.sqrt(np.mean(a**2))), float(a.max()), len(a)

    def lines(self) -> list[str]:
        if not (self.boer_err or self.deriv_err):
            return []
        out = ["rate error vs truth (deg/s)         RMS      max     n"]
        for name, errs in (("Boer (perpendicular part)", self.boer_err),
                           ("derivative (full vector)", self.deriv_err),
                           (f"Kalman filter (full vector){self.filter}", self.kalman_err)):
            rms, mx, n = self.rms_max(errs)
            out.append(f"  {name:<30s} {np.degrees(rms):7.3f}  {np.degrees(mx):7.3f}  {n:4d}")
        return out


def attitude_error_rad(q_est: np.ndarray, q_true: np.ndarray) -> float:
    """The angle of the rotation between two attitudes (quaternions body → ECI, w first), rad."""
    return 2.0 * math.acos(min(1.0, abs(float(np.dot(q_est, q_true)))))


def status_line(t_s: float, fsw: FlightSoftware, tr) -> str:
    """The flight software's status line (the flown filter, its rate and 1-σ); with `tr` (truth at the
    sample time) the true rate, the flown filter's error, its attitude's error when it has an attitude,
    and the Boer formula's error."""
    line = flight_status(t_s, fsw)
    kf = fsw.estimators["kalman"]
    if tr is None or kf.flags & kf.NO_ESTIMATE:
        return line
    w, wt = np.degrees(kf.omega_radps), np.degrees(tr.omega_radps)
    boer_err = np.degrees(np.linalg.norm(fsw.estimators["boer"].omega_radps
                                         - perpendicular(tr.omega_radps, tr.b_body_T)))
    att = kf.attitude() if hasattr(kf, "attitude") else None
    att_err = "" if att is None else (f"  att_err={math.degrees(attitude_error_rad(att[0], tr.q_body_to_eci)):6.1f}"
                                      f" deg (1-sigma {math.degrees(float(np.linalg.norm(att[1]))):5.1f})")
    return line + (f"  w_true=[{wt[0]:7.2f} {wt[1]:7.2f} {wt[2]:7.2f}] dps"
                   f"  err={np.linalg.norm(w - wt):6.2f} dps{att_err}  boer_perp_err={boer_err:5.2f} dps")


@dataclass
class SitlRun:
    """What a SITL run leaves behind."""

    sitl: Sitl
    loop: LoopResult
    score: Score

    @property
    def fsw(self) -> FlightSoftware:
        return self.sitl.fsw

    @property
    def tlm(self):
        return self.sitl.flight.tlm

    @property
    def real_time(self) -> bool:
        return self.loop.real_time


def run(cfg: SitlConfig, out: TextIO = sys.stdout, **build_options) -> SitlRun:
    """Build (:func:`build`) and run the lockstep loop; the header first, the status line each second."""
    s = build(cfg, **build_options)
    print(s.header(), file=out, flush=True)
    fsw, truth, score = s.fsw, s.truth, Score()
    taken = []  # each sample's estimates as the pipeline left them (a tick may take more than one)

    def keep() -> None:
        if fsw.new_sample:
            taken.append(Taken.of(fsw))

    def after(t: float) -> None:  # scored after the tick, outside the loop's measured work
        for x in taken:
            score.add(x, truth(x.sample_t_s))
        taken.clear()
        if s.state is not None:
            s.state.tick(t)

    fsw.sample_listeners.append(keep)

    try:
        res = run_loop(fsw, duration_s=cfg.run.duration_s, speed=cfg.run.speed, lockstep=True, t0_s=s.t0_s,
                       before_tick=s.advance, after_tick=after,
                       status=None if cfg.run.quiet else (lambda t: status_line(t, fsw, score.truth)), out=out)
    finally:
        s.close()
    return SitlRun(s, res, score)


def summary(r: SitlRun) -> str:
    text = flight_summary(r.fsw, r.loop, r.score.lines())
    m = r.fsw.apps.get("mission")
    if m is not None:
        seen = ", ".join(f"{old}->{new} at {t:.0f} s ({why})" for t, old, new, why in
                         ((t, m.phase.__class__(a).name, m.phase.__class__(b).name, why)
                          for t, a, b, why in m.transitions[1:]))
        energy = ", ".join(f"{k} {v:.0f}" for k, v in m.energy_by_phase().items() if v)
        text += (f"\nmission: {m.phase.name} ({m.reason_text}); {seen or 'no phase change'}; kit energy by phase "
                 f"[J]: {energy or 'none'}")
    return text


def add_sitl_options(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--scenario", default="isoi", metavar="NAME|FILE",
                    help="SITL scenario: a shipped name (isoi, aist2d, amds, amds_deorbit, ...) or a TOML file "
                         "(default: isoi)")
    ap.add_argument("--speed", type=finite_float(0), default=1.0, metavar="X",
                    help="pacing: 1 = real time (default), 10 = ten times faster, 0 = as fast as possible")
    ap.add_argument("--seed", type=int_range(0), default=0, help="random seed of the simulator (default 0)")
    ap.add_argument("--work-clock", choices=("cpu", "wall"), default="cpu",
                    help="the loop's step time (overruns, the sample rate's budget) on this thread's CPU time "
                         "(default: the flight software's own work, whatever else the machine runs) or on the "
                         "wall clock (as on target)")
    ap.add_argument("--system-id", type=int_range(1, 255), default=FSW_SYSID, metavar="ID",
                    help=f"the box's MAVLink system id (default {FSW_SYSID}; a fleet in SITL: one run per id)")
    ap.add_argument("--ident-inertia-guess", type=finite_float(0, min_exclusive=True), default=100.0,
                    metavar="KGM2",
                    help="identification experiment: starting tensor = this × identity (default 100 kg.m^2)")


def parse_args(argv=None) -> SitlConfig:
    ap = ArgumentParser(prog="python -m hil.sitl", description=__doc__.splitlines()[0])
    add_run_options(ap)
    add_sitl_options(ap)
    args = ap.parse_args(argv)
    scenario_file = args.scenario if Path(args.scenario).is_file() else None
    check_paths_or_exit(ap, inputs={"--key": args.key, "--scenario": scenario_file},
                        outputs={"--sample-store": args.sample_store})
    check_key_or_exit(ap, args.key)
    try:
        scenarios.load(args.scenario)
    except ValueError as e:
        ap.error(str(e))
    return SitlConfig(run=run_config(args, system_id=args.system_id), scenario=args.scenario, seed=args.seed,
                      ident_inertia_guess_kgm2=args.ident_inertia_guess, work_clock=args.work_clock)


def main(argv=None) -> int:
    return run_program(lambda: summary(run(parse_args(argv))))


if __name__ == "__main__":
    from fsw.startup import exit_with

    exit_with(main)
