"""Run the flight software: `python -m fsw.main --sitl` (against the simulator) or on target.

SITL runs in lockstep in one process: before each loop tick the simulator is advanced to the loop time,
and the MMC5983MA driver talks to the register-level emulator through the same bus interface it uses on
hardware. `--speed 1` paces the loop to real time; `--speed 0` runs as fast as possible.

On target (`--mag-serial PORT`) the driver talks to the chip through a serial register bridge (the
emulator can stand behind a pty: `python -m hil.pty_link`), on the monotonic clock.

Start-up: every option is checked by argparse (finite numbers in range, link ports, output paths:
`fsw.argtypes`, `fsw.files`) and a loop slower than the magnetometer's samples is refused before
anything is built. Ctrl-C at any moment before the loop runs ends the program with one line,
"interrupted" (exit status 130); during the loop it stops the loop and prints the summary.
"""
from __future__ import annotations

import os
import signal
import sys

if __name__ == "__main__":  # Ctrl-C while the modules below load (a second or more): one line, no traceback
    def _interrupted(signum, frame):
        # nothing is open that needs closing before the loop starts; an exception raised here could land
        # inside a compiled module's initialisation, which turns it into an ImportError with a traceback
        print("interrupted", file=sys.stderr, flush=True)
        os._exit(130)

    signal.signal(signal.SIGINT, _interrupted)

import gc  # noqa: E402
import math  # noqa: E402
import threading  # noqa: E402
import time  # noqa: E402
from dataclasses import dataclass, field  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from .argtypes import ArgumentParser, check_paths_or_exit, finite_float, int_range, link_url  # noqa: E402
from .drivers.mmc5983ma import Mmc5983ma  # noqa: E402
from .drivers.mmc5983ma_regs import Bandwidth, ContinuousFrequency  # noqa: E402
from .flight import FlightSoftware  # noqa: E402
from .telemetry.dialect import FSW_COMPID, FSW_SYSID  # noqa: E402
from .telemetry.sample_store import SampleStore  # noqa: E402
from .telemetry.signing import SigningClock, key_fingerprint, load_key  # noqa: E402
from .telemetry.store_forward import DEFAULT_CAPACITY, StoreForward  # noqa: E402
from .telemetry.telemetry import Telemetry  # noqa: E402
from .telemetry.udp_link import open_box_link  # noqa: E402

DEFAULT_LINK = "udpout:127.0.0.1:14550"
RADIO_BYTES_PER_S = 57600 / 10  # 8N1
BANDWIDTH = {100: Bandwidth.BW_100HZ, 200: Bandwidth.BW_200HZ, 400: Bandwidth.BW_400HZ,
             800: Bandwidth.BW_800HZ}
#: largest store-and-forward ring (--buffer-frames): about 0.8 kB of memory a frame, 0.8 GB at most
MAX_BUFFER_FRAMES = 1_000_000
#: the loop's ceiling (--rate) and the MMC5983MA's (--sample-rate)
MAX_RATE_HZ = 1000.0


def _deg(v) -> np.ndarray:
    return np.degrees(np.asarray(v, dtype=float))


def _perp(w: np.ndarray, b: np.ndarray) -> np.ndarray:
    bh = b / np.linalg.norm(b)
    return w - np.dot(w, bh) * bh


class WorkHistogram:
    """Work time per tick over a whole run in fixed 1 µs bins (the last bin holds everything above
    100 ms): constant memory however long the run, p50/p99 to the microsecond."""

    def __init__(self, max_us: int = 100_000) -> None:
        self.counts = np.zeros(max_us + 1, dtype=np.int64)
        self.n = 0
        self.total_s = 0.0
        self.max_s = 0.0

    def add(self, work_s: float) -> None:
        self.counts[min(int(work_s * 1e6), len(self.counts) - 1)] += 1
        self.n += 1
        self.total_s += work_s
        if work_s > self.max_s:
            self.max_s = work_s

    #: edges (µs) of the summary's coarse histogram
    BUCKETS_US = (50, 100, 200, 500, 1000, 5000)

    def buckets(self) -> list[tuple[str, int]]:
        """(label, ticks) per coarse bin of work time: <50 µs, 50–100 µs, … ≥5 ms."""
        edges = (0,) + self.BUCKETS_US + (len(self.counts),)
        out = []
        for lo, hi in zip(edges[:-1], edges[1:]):
            label = (f"<{hi} us" if lo == 0 else f">={lo} us" if hi == len(self.counts) else f"{lo}-{hi} us")
            out.append((label, int(self.counts[lo:hi].sum())))
        return out

    def percentile_us(self, p: float) -> float:
        if not self.n:
            return 0.0
        return float(np.searchsorted(np.cumsum(self.counts), p / 100.0 * self.n))

    def mean_us(self) -> float:
        return self.total_s / self.n * 1e6 if self.n else 0.0


@dataclass
class Score:
    """Errors of the onboard estimates against the simulator's truth, at the sample times."""

    boer_err: list = field(default_factory=list)
    deriv_err: list = field(default_factory=list)
    kalman_err: list = field(default_factory=list)
    work: WorkHistogram = field(default_factory=WorkHistogram)
    #: real-time runs: ticks that started more than one period behind their wall-clock time
    late_ticks: int = 0
    max_late_s: float = 0.0

    def add(self, fsw: FlightSoftware, tr) -> None:
        if fsw.new_estimate["boer"]:
            w = fsw.estimators["boer"].omega_radps
            self.boer_err.append(np.linalg.norm(w - _perp(tr.omega_radps, tr.b_body_T)))
        if fsw.new_estimate["derivative"]:
            w = fsw.estimators["derivative"].omega_radps
            self.deriv_err.append(np.linalg.norm(w - tr.omega_radps))
        kf = fsw.estimators["kalman"]
        if fsw.new_estimate["kalman"] and not kf.flags & kf.NO_ESTIMATE:
            self.kalman_err.append(np.linalg.norm(kf.omega_radps - tr.omega_radps))

    @staticmethod
    def _rms_max(errs) -> tuple[float, float, int]:
        if not errs:
            return math.nan, math.nan, 0
        a = np.asarray(errs)
        return float(np.sqrt(np.mean(a**2))), float(a.max()), len(a)


def build_sitl(args):
    from hil import scenario as scenarios
    from hil.sim import Simulator

    scn = scenarios.load(args.scenario)
    if scn.deorbit is not None:  # the de-orbit kit's scenario: environment torques and the kit emulator
        from hil.deorbit_sim import DeorbitSimulator
        sim = DeorbitSimulator(scn, seed=args.seed, max_step_s=min(0.02, 1.0 / args.rate))
    else:
        sim = Simulator(scn, seed=args.seed, max_step_s=min(0.02, 1.0 / args.rate))
    rate_hz, bw, cm = sitl_sensor(scn.sample_rate_hz, BANDWIDTH[scn.bandwidth_hz], getattr(args, "sample_rate", None))
    driver = Mmc5983ma(sim.sensor, bandwidth=bw, sample_period_s=1.0 / rate_hz, continuous=cm)
    sigma_b = math.hypot(scn.noise_T, bw.noise_rms_T)
    return scn, sim, driver, sigma_b


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


def parse_args(argv=None):
    ap = ArgumentParser(prog="python -m fsw.main", description=__doc__.splitlines()[0])
    mode = ap.add_mutually_exclusive_group(required=True)
    mode.add_argument("--sitl", action="store_true", help="run against the in-process simulator (lockstep)")
    mode.add_argument("--mag-serial", metavar="PORT",
                      help="on target: MMC5983MA behind a serial register bridge (e.g. the pty of python -m hil.pty_link)")
    mode.add_argument("--replay", metavar="INPUT.csv",
                      help="a recording (format v1) as the magnetometer, on a virtual clock, as fast as possible")
    ap.add_argument("--rates-out", metavar="OUT.csv",
                    help="with --replay: write the onboard Kalman filter's estimates, one row per sample")
    ap.add_argument("--scenario", default="isoi", metavar="NAME|FILE",
                    help="SITL scenario: a shipped name (isoi, aist2d, amds, amds_deorbit, ...) or a TOML file "
                         "(default: isoi)")
    ap.add_argument("--duration", type=finite_float(0, min_exclusive=True), default=None, metavar="S",
                    help="stop after S seconds of loop time (default: run until Ctrl-C)")
    ap.add_argument("--speed", type=finite_float(0), default=1.0, metavar="X",
                    help="SITL pacing: 1 = real time (default), 10 = ten times faster, 0 = as fast as possible")
    ap.add_argument("--rate", type=finite_float(0, MAX_RATE_HZ, min_exclusive=True), default=50.0, metavar="HZ",
                    help="loop rate, up to 1000 Hz and at least the magnetometer's sample rate (default 50 Hz)")
    ap.add_argument("--link", type=link_url, default=DEFAULT_LINK, metavar="URL",
                    help=f"telemetry link, any pymavlink connection string (default {DEFAULT_LINK})")
    ap.add_argument("--baud", type=int_range(1), default=57600, help="baud rate when --link is a serial port")
    ap.add_argument("--key", metavar="FILE",
                    help="mission key file (python -m ground.keys new FILE): commands must be signed with it, "
                         "telemetry is signed with it; without a key every state-changing command is refused")
    ap.add_argument("--uplink", type=link_url, metavar="URL", default=None,
                    help="where commands arrive, a pymavlink connection string (default: the --link itself; "
                         "e.g. udpin:0.0.0.0:14551 to command over UDP while ground.decode listens on --link)")
    ap.add_argument("--buffer-frames", type=int_range(0, MAX_BUFFER_FRAMES), default=DEFAULT_CAPACITY, metavar="N",
                    help=f"store-and-forward ring: telemetry frames kept while the link is down "
                         f"(default {DEFAULT_CAPACITY}; 0 = none; at most {MAX_BUFFER_FRAMES:,}, ~0.8 kB each)")
    ap.add_argument("--sample-store", metavar="FILE", default=None,
                    help="keep the numbered samples the ground may ask for again in this file, so that they and "
                         "their numbering survive a restart (default: in memory)")
    ap.add_argument("--seed", type=int_range(0), default=0, help="random seed of the simulator (default 0)")
    ap.add_argument("--sample-rate", type=finite_float(0, MAX_RATE_HZ, min_exclusive=True), default=None,
                    metavar="HZ",
                    help="magnetometer sample rate, up to 1000 Hz (default: on target 1 Hz, in SITL the scenario's; "
                         "SITL then picks the chip's bandwidth and continuous mode to suit)")
    ap.add_argument("--sigma-uT", type=finite_float(0, min_exclusive=True), default=1.5,
                    help="on target: 1-sigma field error per axis used by the estimators (default 1.5 uT)")
    ap.add_argument("--max-sample-tlm-hz", type=finite_float(0.01, MAX_RATE_HZ), default=20.0,
                    help="at most this many magnetometer samples per second go out on the link "
                         "(0.01 to 1000, default 20)")
    ap.add_argument("--quiet", action="store_true", help="no status line each second, only the summary")
    ap.add_argument("--ident-inertia-guess", type=finite_float(0, min_exclusive=True), default=100.0,
                    metavar="KGM2",
                    help="SITL identification experiment: starting tensor = this × identity (default 100 kg.m^2)")
    args = ap.parse_args(argv)
    if args.rates_out and not args.replay:
        ap.error("--rates-out needs --replay")
    scenario_file = args.scenario if args.sitl and Path(args.scenario).is_file() else None
    check_paths_or_exit(ap, inputs={"--replay": args.replay, "--key": args.key, "--scenario": scenario_file},
                        outputs={"--rates-out": args.rates_out, "--sample-store": args.sample_store})
    return args


def check_loop_rate(rate_hz: float, sample_rate_hz: float) -> str | None:
    """Refuse (ValueError) a loop slower than the magnetometer's samples: it takes one sample a tick at
    most, so it would drop samples all the time. At an equal rate: a warning line (a tick that starts
    late, the driver's start-up and each SET/RESET calibration then cost samples); None otherwise."""
    if rate_hz < sample_rate_hz * (1 - 1e-9):
        raise ValueError(f"--rate {rate_hz:g} Hz is below the magnetometer's sample rate {sample_rate_hz:g} Hz: "
                         "the loop must run at least as fast as samples arrive, or it drops them "
                         f"(give --rate {min(MAX_RATE_HZ, 2 * sample_rate_hz):g} or more)")
    if rate_hz < sample_rate_hz * (1 + 1e-9):
        return (f"warning: --rate {rate_hz:g} Hz equals the sample rate: samples are lost at start-up, at each "
                "SET/RESET calibration (every 1000 samples) and whenever a tick starts late; a faster loop "
                "loses fewer")
    return None


@dataclass
class Run:
    """What a run leaves behind: the flight software, its telemetry, the score, the times."""

    fsw: FlightSoftware
    tlm: Telemetry
    score: Score
    t_s: float
    wall_s: float
    #: paced against the wall clock (speed > 0, or on target)
    real_time: bool = False


def run(args, out=sys.stdout) -> Run:
    """Build the flight software for SITL or target from parsed `args` and run the loop."""
    truth = None
    if args.sitl:
        scn, sim, source, sigma_b = build_sitl(args)
        truth = sim.truth
        sample_rate = 1.0 / source.sample_period_s
        header = (f"SITL scenario {scn.name}: {scn.description}\n"
                  f"loop {args.rate:g} Hz, sensor {sample_rate:g} Hz, speed "
                  f"{'max' if args.speed == 0 else f'{args.speed:g}x'}, seed {args.seed}, link {args.link}")
        warning = check_loop_rate(args.rate, sample_rate)
    elif getattr(args, "replay", None):
        from .replay import RecordingReplay
        sim = None
        source = RecordingReplay.from_csv(args.replay)
        sample_rate = source.sample_rate_hz
        # one sample per tick at most: the loop runs at twice the recording's rate (virtual clock)
        args.rate = min(1000.0, max(args.rate, 2.0 * sample_rate))
        args.speed = 0.0
        sigma_b = args.sigma_uT * 1e-6
        header = (f"replay {args.replay}: {len(source.t)} samples at {sample_rate:.3g} Hz, loop {args.rate:g} Hz "
                  f"(virtual clock), link {args.link}")
        warning = None  # one sample a tick at most: a loop slower than the recording falls behind, skips none
    else:
        from .drivers.serial_bus import SerialBus
        sim = None
        sample_rate = args.sample_rate or 1.0
        warning = check_loop_rate(args.rate, sample_rate)
        source = Mmc5983ma(SerialBus(args.mag_serial), sample_period_s=1.0 / sample_rate)
        sigma_b = args.sigma_uT * 1e-6
        header = f"target: MMC5983MA on {args.mag_serial}, loop {args.rate:g} Hz, link {args.link}"

    key = load_key(args.key) if getattr(args, "key", None) else None  # KeyFileError is a ValueError
    # the signing clock is the wall clock (this is the program's edge): a SITL run faster than real
    # time still signs with real time, which the ground's replay checks compare with its own clock
    clock = SigningClock(clock_set=True, unix_time=time.time)
    link = open_box_link(args.link, source_system=FSW_SYSID, source_component=FSW_COMPID, baud=args.baud)
    uplink = link
    if getattr(args, "uplink", None):
        try:
            uplink = open_box_link(args.uplink, source_system=FSW_SYSID, source_component=FSW_COMPID,
                                   baud=args.baud, input=True)
        except BaseException:
            link.close()
            raise
    frames = getattr(args, "buffer_frames", DEFAULT_CAPACITY)
    tlm = Telemetry(link, store=StoreForward(frames) if frames > 0 else None, key=key, clock=clock)
    ident = None
    if sim is not None:  # the identification experiment needs a field model along the orbit: SITL has one
        from hil.ident_sitl import build_ident
        ident = build_ident(scn, sim, sigma_b, getattr(args, "ident_inertia_guess", 100.0))
    deorbit = None
    if sim is not None and scn.deorbit is not None:  # the kit's lines are the emulator's, attitude from truth
        from hil.deorbit_sim import build_kit
        deorbit = build_kit(sim)
        header += f"\nde-orbit kit: emulated; controller attitude from {deorbit.attitude.description}"
    # a new run id at every start (this is the program's edge): the ground tells runs apart by it
    store = SampleStore(run_id=int.from_bytes(os.urandom(4), "little"), path=getattr(args, "sample_store", None))
    if store.reset_reason:
        header += f"\nsample store: {store.reset_reason}"
    fsw = FlightSoftware(source, tlm, rate_hz=args.rate, sigma_b_T=sigma_b, truth=truth,
                         max_sample_tlm_hz=args.max_sample_tlm_hz, sample_rate_hz=sample_rate,
                         uplink=uplink, key=key, ident=ident, deorbit=deorbit, sample_store=store)
    header += (f"\nmission key {key_fingerprint(key)}: commands must be signed, telemetry is signed" if key else
               "\nno mission key: commands that change state are refused")
    if uplink is not link:
        header += f"; commands on {args.uplink}"
    if warning:
        header += "\n" + warning
    print(header, file=out, flush=True)

    stop = False

    def on_signal(signum, frame):
        nonlocal stop
        stop = True

    in_main_thread = threading.current_thread() is threading.main_thread()
    if in_main_thread:
        old = signal.signal(signal.SIGINT, on_signal), signal.signal(signal.SIGTERM, on_signal)
    score = Score()
    # Everything built so far lives as long as the run: collected once and moved out of the collector's
    # reach, so that its full collections in the loop scan only what the loop itself allocated (without
    # this a full collection of the imported libraries' objects takes about 0.1 s, a hundred 1 kHz ticks).
    gc.collect()
    gc.freeze()
    sample_truth = None  # the simulator's truth at the latest sample's time
    period = 1.0 / args.rate
    wall0 = time.monotonic()
    k = 0
    next_status = 1.0
    t = 0.0
    replay = source if getattr(args, "replay", None) else None
    t0 = replay.start_s if replay is not None else 0.0
    rates = {}  # replay: sample time -> (ω, σ) of the Kalman filter
    try:
        while not stop:
            if args.duration is not None and k * period > args.duration + 1e-9:
                break
            t = k * period
            if sim is not None:
                sim.advance_to(t)
            elif replay is not None:
                if replay.done and not fsw.new_sample:
                    break
                t = t0 + k * period
            else:
                t = time.monotonic() - wall0
            score.work.add(fsw.tick(t))
            if replay is not None and fsw.new_estimate.get("kalman"):
                kf = fsw.estimators["kalman"]
                if not kf.flags & kf.NO_ESTIMATE:
                    rates[fsw.sample_t_s] = (kf.omega_radps.copy(), kf.sigma_radps.copy())
            if fsw.new_sample and truth is not None:
                sample_truth = truth(fsw.sample_t_s)
                score.add(fsw, sample_truth)
            if t >= next_status - 1e-9:
                next_status += 1.0
                if not args.quiet:
                    print(status_line(t, fsw, sample_truth), file=out, flush=True)
            k += 1
            if args.speed > 0 or (sim is None and replay is None):
                wait = wall0 + (k * period) / (args.speed or 1.0) - time.monotonic()
                if wait > 0:
                    time.sleep(wait)
                elif -wait > period:  # the next tick starts more than a period late
                    score.late_ticks += 1
                    score.max_late_s = max(score.max_late_s, -wait)
    finally:
        if in_main_thread:
            signal.signal(signal.SIGINT, old[0])
            signal.signal(signal.SIGTERM, old[1])
        link.close()
        if uplink is not link:
            uplink.close()
        store.close()
    if replay is not None and getattr(args, "rates_out", None):
        write_replay_rates(args.rates_out, replay, rates, args.replay)
        print(f"wrote {len(rates)} Kalman estimates for {len(replay.t)} samples: {args.rates_out}", file=out)
    return Run(fsw, tlm, score, t, time.monotonic() - wall0,
               real_time=args.speed > 0 or (sim is None and replay is None))


def write_replay_rates(path, replay, rates: dict, source: str) -> None:
    """The replay's Kalman estimates in the rate-estimate format: one row per recording sample (NaN
    where the sample gate refused the sample or the filter had no estimate yet; σ = inf where it had no
    information: the link's finite "unobserved" σ, or no field)."""
    from ground.recording import RateEstimates, write_rate_estimates

    from .estimation.rate_formulas import unobserved_sigma

    n = len(replay.t)
    w = np.full((n, 3), np.nan)
    s = np.full((n, 3), np.nan)
    for i, tk in enumerate(replay.t):
        est = rates.get(float(tk))
        if est is not None:
            w[i], s[i] = est
    write_rate_estimates(path, RateEstimates(replay.t, w, unobserved_sigma(s, replay.b, 0.0), metadata={
        "source": f"python -m fsw.main --replay {source}",
        "method": "kalman (onboard RateKalman, DEBRIS_RATE_METHOD_KALMAN)"}))


def main(argv=None) -> int:
    try:
        args = parse_args(argv)
        try:
            r = run(args)
        except ValueError as e:  # a bad scenario file, an impossible sensor setting, a loop too slow
            print(f"error: {e}", file=sys.stderr)
            return 2
        except OSError as e:  # a serial port or link that cannot be opened
            print(f"error: {e}", file=sys.stderr)
            return 1
        print(summary(r), flush=True)
    except KeyboardInterrupt:  # Ctrl-C before the loop's own handler is in place (or after it is gone)
        print("interrupted", file=sys.stderr, flush=True)
        return 130
    return 0


def status_line(t_s: float, fsw: FlightSoftware, tr) -> str:
    """One line: time, |B|, the Kalman filter's estimate and 1-σ; with `tr` (truth at the sample time)
    the true rate, the filter's error and the Boer formula's."""
    b = fsw.sample_b_T
    d = fsw.estimators["kalman"]
    bo = fsw.estimators["boer"]
    line = f"t={t_s:7.1f} s  |B|={np.linalg.norm(b) * 1e6:6.2f} uT"
    if d.flags & d.NO_ESTIMATE:
        return line + "  (waiting for samples)"
    w = _deg(d.omega_radps)
    sg = _deg(d.sigma_radps)
    line += f"  w_est=[{w[0]:7.2f} {w[1]:7.2f} {w[2]:7.2f}] +-[{sg[0]:5.2f} {sg[1]:5.2f} {sg[2]:5.2f}] dps"
    if tr is not None:
        wt = _deg(tr.omega_radps)
        line += (f"  w_true=[{wt[0]:7.2f} {wt[1]:7.2f} {wt[2]:7.2f}] dps"
                 f"  err={np.linalg.norm(w - wt):6.2f} dps"
                 f"  boer_perp_err={np.degrees(np.linalg.norm(bo.omega_radps - _perp(tr.omega_radps, tr.b_body_T))):5.2f} dps")
    return line


def summary(r: Run) -> str:
    fsw, tlm, score, t_s, wall_s = r.fsw, r.tlm, r.score, r.t_s, r.wall_s
    src = fsw.source
    st = fsw.scheduler.stats
    work = score.work
    lines = [f"--- summary: {t_s:.1f} s of loop time in {wall_s:.1f} s wall "
             f"({t_s / max(wall_s, 1e-9):.1f}x real time)",
             f"magnetometer: {fsw.samples} samples, {getattr(src, 'bus_errors', 0)} bus errors, "
             f"{getattr(src, 'timeouts', 0)} timeouts"]
    if score.boer_err or score.deriv_err:
        lines.append("rate error vs truth (deg/s)         RMS      max     n")
        for name, errs in (("Boer (perpendicular part)", score.boer_err),
                           ("derivative (full vector)", score.deriv_err),
                           ("Kalman filter (full vector)", score.kalman_err)):
            rms, mx, n = Score._rms_max(errs)
            lines.append(f"  {name:<30s} {np.degrees(rms):7.3f}  {np.degrees(mx):7.3f}  {n:4d}")
    lines.append(f"loop: {st.ticks} ticks at {fsw.scheduler.rate_hz:g} Hz; step time mean {work.mean_us():.0f} us, "
                 f"p50 {work.percentile_us(50):.0f} us, p99 {work.percentile_us(99):.0f} us, "
                 f"max {work.max_s * 1e6:.0f} us; overruns {st.overruns}, task overruns {st.task_overruns}")
    lines.append("step time histogram: " + ", ".join(f"{label} {n}" for label, n in work.buckets()))
    if r.real_time:
        lines.append(f"schedule: {score.late_ticks} ticks started more than one period late"
                     + (f" (at most {score.max_late_s * 1e3:.1f} ms)" if score.late_ticks else ""))
    rate = tlm.bytes_sent / max(t_s, 1e-9)
    lines.append(f"link: {tlm.frames_sent} frames, {tlm.bytes_sent} bytes ({rate:.0f} B/s = "
                 f"{100 * rate / RADIO_BYTES_PER_S:.1f} % of a 57600-baud radio), send errors {tlm.send_errors}"
                 + (f", {tlm.conn.unaddressed_writes} frames not sent (no ground station known yet)"
                    if getattr(tlm.conn, "unaddressed_writes", 0) else ""))
    sf = tlm.store
    if sf is not None and (sf.outages or sf.dropped):
        lines.append(f"store and forward: {sf.outages} outages, {sf.stored} frames kept, {sf.replayed} replayed, "
                     f"{sf.dropped} dropped (buffer full), {sf.buffered} still waiting")
    if fsw.uplink is not None:
        u = fsw.uplink.link_counters()
        line = (f"uplink: {u['cmd_accepted']} commands accepted; rejected: {u['rejected_unsigned']} unsigned, "
                f"{u['rejected_bad_signature']} bad signature, {u['rejected_replay']} replayed, "
                f"{u['rejected_invalid']} invalid")
        if u["uplink_bytes"]:
            line += (f"; {u['uplink_bytes']} bytes in, {u['uplink_bytes_dropped']} dropped over budget, "
                     f"{u['uplink_garbage_bytes']} garbage, {u['uplink_bad_crc']} bad CRC, "
                     f"{u['uplink_foreign_datagrams']} datagrams from unknown sources, "
                     f"{u['uplink_os_dropped']} dropped by the OS")
        lines.append(line)
    kit = getattr(fsw, "deorbit", None)
    if kit is not None:
        e, seq = kit.energy(), kit.sequencer
        lines.append(f"de-orbit kit: {seq.mode.name}, openings {e.channels[0].openings} + {e.channels[1].openings}, "
                     f"turns {e.channels[0].turns} + {e.channels[1].turns}, energy {e.total_J:.0f} J, "
                     f"interlock violations {seq.interlock_violations}, safe entries {seq.safe_entries}")
    g = fsw.gate
    if g.rejected:
        lines.append("magnetometer samples refused: " + ", ".join(f"{n} {k}" for k, n in g.counts.items() if n))
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())
