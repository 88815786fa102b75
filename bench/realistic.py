"""Realistic truth for the benchmarks and the honesty tests: the world as the box meets it.

Truth: the simulator (`hil.sim.Simulator`) on the shipped ``isoi_sgp4`` world — an SGP4 orbit from a
TLE, IGRF-14 to degree 13 with the Earth's rotation, the host's hard and soft iron with its thermal
drift, the box's clock 2 s off (and drifting 20 ppm) — with the body, the initial rate, the noise and
the host replaced as a case asks. What the estimators are given is what the box would have: the
samples time-stamped by the box's clock, its 3-day-old TLE and the scenario's UTC of t = 0 (so the
field is looked up 2 s off), the onboard field model (`fsw.estimation.onboard_field.flight_field`,
IGRF-14 at the flight degree; `ground.field.tle_field`).

The two cases of issue 15's "never confidently wrong" (:data:`CASES`):

- ``slow_heavy`` — a heavy body (Aist-2D, diag(175, 200, 285) kg·m²) tumbling slowly (~1 °/s), 1 s
  steps, 0.3 µT, 10 min, no host iron: the rate along B is barely observable without an orbit;
- ``host_iron`` — the shipped cubesat (~10 °/s) with its uncalibrated host (hard ≈ 14 µT, soft ≈ 4 %),
  1 s steps, 0.3 µT, 10 min.

    python -m bench.realistic slow_heavy rec.csv      # the record as a CSV (format v1, with the truth)
    python -m bench.realistic slow_heavy --score --seeds 2 --json s.json   # every method's error and coverage
"""
from __future__ import annotations

import dataclasses
import math
import sys
from dataclasses import dataclass

import numpy as np

from hil import scenario as scenarios
from hil.host_magnetics import HostMagnetics
from hil.sim import Simulator

#: the box's calibration off by what the calibration benchmark leaves after one orbit (0.14 µT worst axis):
#: 0.15 µT per axis of hard iron, 0.2 % per element of the soft iron
HOST_RESIDUAL_T, SOFT_RESIDUAL = 0.15e-6, 0.002
CHIP_NOISE_T = 0.04e-6
LSB_T = 1e-4 / 16384.0
HEAVY_KGM2 = np.diag([175.0, 200.0, 285.0])


@dataclass(frozen=True)
class Case:
    """A realistic record: the body, its rate, sampling, noise, duration, and whether the host's iron is in."""

    name: str
    inertia_kgm2: tuple | None = None   # None: the scenario's body
    rate_dps: float | None = None       # |ω₀|; None: the scenario's ω₀
    dt_s: float = 1.0
    sigma_uT: float = 0.3
    duration_s: float = 600.0
    host: bool = True


CASES = {
    "slow_heavy": Case("slow_heavy", tuple(map(tuple, HEAVY_KGM2)), 1.0, host=False),
    "host_iron": Case("host_iron"),
}


@dataclass
class Record:
    """Samples at the box's time stamps with their truth; what the box would have (TLE, UTC of t = 0)."""

    t_s: np.ndarray            # box clock
    b_T: np.ndarray            # measured (host's iron and noise in)
    b_true_T: np.ndarray       # the true field in body axes
    w_true_radps: np.ndarray
    q_true: np.ndarray         # body → ECI
    box_tle: tuple[str, str]
    utc0: object               # datetime: the UTC the box takes for its t = 0
    case: Case
    seed: int

    def recording(self):
        """As a `ground.recording.Recording` (the truth as its reference rate)."""
        from ground.recording import Recording
        return Recording(self.t_s, self.b_T, w_ref_radps=self.w_true_radps,
                         metadata={"source": f"bench.realistic {self.case.name} seed {self.seed}"})

    def field(self):
        """The field the box (and the ground, with --tle --utc0) would compute: the onboard model along
        the box's TLE, t = 0 at the box's UTC."""
        from ground.field import tle_field
        return tle_field(*self.box_tle, self.utc0)


class BoxField:
    """The field the box computes (its TLE, its onboard model) at its own clock: B(t + offset)."""

    def __init__(self, field, offset_s: float) -> None:
        self.field, self.offset_s = field, float(offset_s)

    def b_eci_T(self, t_s):
        return self.field.b_eci_T(np.asarray(t_s, float) + self.offset_s)

    __call__ = b_eci_T


class HostResidual:
    """The host's iron (`hil.host_magnetics`) in the measurement, taken out again by the box's calibration,
    which is off by what the calibration benchmark leaves: the samples the estimators get.

    `drift_tracked` False (a constant calibration): the hard iron's thermal drift (~1 µT over an orbit)
    stays in the samples; True (the box's calibration as flown, `fsw.estimation.magcal`'s harmonic of the
    orbit): the calibration follows it, only the residual stays. A hard-iron error δ on |B| turns into a
    rate error of about |ω| δ/|B|: 1 µT on 40 µT at 19 °/s is ~0.5 °/s, which is what the IGRF rows of the
    fast tumbles show with the drift in."""

    def __init__(self, host, rng, drift_tracked: bool = False) -> None:
        self.host = host
        self.drift_tracked = bool(drift_tracked)
        self.h_err_T = rng.normal(scale=HOST_RESIDUAL_T, size=3)
        s_est = host.soft_iron + rng.normal(scale=SOFT_RESIDUAL, size=(3, 3))
        self.s_est_inv = np.linalg.inv(s_est)

    def __call__(self, b_T: np.ndarray, t_s) -> np.ndarray:
        meas = self.host.measured_T(b_T, t_s)
        h_est = (self.host.hard_iron_at_T(t_s) if self.drift_tracked else self.host.hard_iron_T) + self.h_err_T
        return (meas - h_est) @ self.s_est_inv.T


def simulate(case: Case | str, seed: int = 0, *, random_attitude: bool = True) -> Record:
    """A seeded realistic record of `case` (a :class:`Case` or a name in :data:`CASES`): the initial
    rate direction and attitude drawn from the seed, the noise white Gaussian per axis plus the chip's
    own and its 18-bit quantisation."""
    case = CASES[case] if isinstance(case, str) else case
    rng = np.random.default_rng([seed, 15])
    scn = scenarios.load("isoi_sgp4")
    changes = {"noise_T": 0.0}
    if case.inertia_kgm2 is not None:
        changes["inertia_kgm2"] = np.array(case.inertia_kgm2, float)
    w0 = np.asarray(scn.omega0_radps, float)
    if random_attitude:
        v = rng.normal(size=3)
        w0 = v / np.linalg.norm(v) * np.linalg.norm(w0)
        changes["attitude_rpy_deg"] = np.array([rng.uniform(-180, 180), rng.uniform(-90, 90), rng.uniform(-180, 180)])
    if case.rate_dps is not None:
        w0 = w0 / np.linalg.norm(w0) * math.radians(case.rate_dps)
    changes["omega0_radps"] = w0
    if not case.host:
        changes["host"] = HostMagnetics()
    scn = dataclasses.replace(scn, **changes)
    rate = max(float(np.linalg.norm(w0)), 1e-3)
    sim = Simulator(scn, seed=seed, max_step_s=min(0.02, 0.01 / rate))
    n = int(round(case.duration_s / case.dt_s)) + 1
    t_true = np.arange(n) * case.dt_s
    b_meas, b_true, w, q = np.zeros((n, 3)), np.zeros((n, 3)), np.zeros((n, 3)), np.zeros((n, 4))
    sigma = math.hypot(case.sigma_uT * 1e-6, CHIP_NOISE_T)
    for k, tt in enumerate(t_true):
        sim.advance_to(tt)
        tr = sim.truth()
        b_true[k], w[k], q[k] = tr.b_body_T, tr.omega_radps, tr.q_body_to_eci
        b_meas[k] = sim.measured_field_T(tt) + rng.normal(scale=sigma, size=3)
    b_meas = np.round(b_meas / LSB_T) * LSB_T
    t_box = np.array([sim.clock.box_s(x) for x in t_true])
    return Record(t_box, b_meas, b_true, w, q, sim.box_tle, sim.utc0, case, seed)


#: the ground tool's methods scored by :func:`score` (`python -m bench.realistic CASE --score`)
SCORED = ("boer", "kalman", "kalman-orbit", "kalman-euler", "kalman-mm", "smoother", "auto")


def score(case: Case | str, seeds=(0,), methods=SCORED, fields=("tle", "none"), campaign=None) -> list[dict] | int:
    """Each method of `ground.estimate` on the seeded records of `case`, with the box's TLE (``tle``, as
    ``--tle … --utc0 …``) and without an orbit (``none``): full-vector RMS error (Boer: ⊥B) in °/s and
    the share of components within 1-σ (`ground.estimate.score`), one dict per (seed, field, method). A seed is
    a campaign's run (bench.campaign): `campaign` = (parser, arguments) of its options (default: in this
    process); an exit status instead for --rerun or a failed run."""
    import functools

    from bench.campaign import Run, run_campaign
    from bench.campaign import options as campaign_options
    name = case if isinstance(case, str) else case.name
    specs = [Run(f"seed{seed}", (seed,), {}) for seed in seeds]
    config = {"benchmark": "bench.realistic --score", "case": name, "methods": list(methods), "fields": list(fields)}
    fn = functools.partial(score_seed, case=case, methods=tuple(methods), fields=tuple(fields))
    if campaign is None:
        got = run_campaign(fn, specs, config=config, name="realistic", workers=1, progress=False)
    else:
        got = campaign_options.execute(*campaign, fn, specs, config, name="realistic")
        if isinstance(got, int):
            return got
    return [r for one in got for r in one["rows"]]


def score_seed(run, *, case: Case | str, methods=SCORED, fields=("tle", "none")) -> dict:
    """A campaign's task: the rows of one seed (the run's)."""
    from ground import estimate as ge
    seed = run.seed[0]
    rows = []
    rec = simulate(case, seed)
    r = rec.recording()
    sigma = ge.noise_estimate_T(r.b_T)
    for fld in fields:
        field = rec.field() if fld == "tle" else None
        for m in methods:
            w, s, _ = ge.estimate(m, r.t_s, r.b_T, sigma, field=field)
            sc = ge.score(r, w, m in ge.PERPENDICULAR, s)
            rows.append({"case": rec.case.name, "seed": seed, "field": fld, "method": m,
                         "rms_dps": sc.get("full_rms_dps", sc["perp_rms_dps"]),
                         "coverage_1sigma": sc["coverage_1sigma"]})
    return {"rows": rows}


def main(argv=None) -> int:
    import json

    from fsw.argtypes import ArgumentParser, check_paths_or_exit, int_range
    from ground.recording import write_recording

    ap = ArgumentParser(prog="python -m bench.realistic", description=__doc__.splitlines()[0])
    ap.add_argument("case", choices=sorted(CASES))
    ap.add_argument("output", nargs="?", help="recording to write (CSV, format v1, with the true rate as reference)")
    ap.add_argument("--seed", type=int_range(0), default=0)
    ap.add_argument("--score", action="store_true", help="instead: each ground.estimate method's RMS error and "
                                                         "1-σ coverage, with the TLE and without an orbit")
    ap.add_argument("--seeds", type=int_range(1), default=1, help="--score: seeds 0 … N−1 (default 1)")
    ap.add_argument("--methods", default=",".join(SCORED), help="--score: comma-separated methods")
    ap.add_argument("--json", metavar="FILE", help="--score: the rows as JSON")
    from bench.campaign import options as campaign_options
    campaign_options.add_arguments(ap)
    args = ap.parse_args(argv)
    campaign_options.check(ap, args)
    if args.score:
        from ground.estimate import METHODS
        methods = [m for m in args.methods.split(",") if m]
        bad = [m for m in methods if m not in METHODS]
        if bad or not methods:
            ap.error(f"--methods: unknown {', '.join(bad) or '(none)'}; choose from {', '.join(METHODS)}")
        check_paths_or_exit(ap, inputs={}, outputs={"--json": args.json, **campaign_options.outputs(args)})
        rows = score(args.case, range(args.seeds), methods, campaign=(ap, args))
        if isinstance(rows, int):  # --rerun, or a failed run
            return rows
        print("case        seed field method         RMS °/s  1-σ covers")
        for r in rows:
            print(f"{r['case']:11s} {r['seed']:4d} {r['field']:5s} {r['method']:13s} {r['rms_dps']:8.3f}  "
                  f"{100 * r['coverage_1sigma']:5.1f} %")
        if args.json:
            with open(args.json, "w") as f:
                json.dump(rows, f, indent=1)
            print(f"wrote {args.json}")
        return 0
    if args.output is None:
        ap.error("give OUTPUT (the recording to write) or --score")
    if args.results or args.rerun or args.scheduler or args.workers:
        ap.error("--workers, --scheduler, --results and --rerun are for --score")
    check_paths_or_exit(ap, inputs={}, outputs={"output": args.output})
    rec = simulate(args.case, args.seed)
    write_recording(args.output, rec.recording())
    print(f"wrote {args.output}: {len(rec.t_s)} samples; the box's TLE and UTC of t = 0:")
    print(f"  --tle '{rec.box_tle[0]}' '{rec.box_tle[1]}' --utc0 {rec.utc0.isoformat()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
