"""Ground refinement of the inertia tensor from a magnetometer recording (output-error fit).

    python -m ground.inertia INPUT.csv OUT.json [--scenario NAME|FILE] [--sigma-uT S] [--diag]
                             [--guess KGM2] [--plot FILE [--running N]] [--hold centered|forward] [--quiet]
                             [--magcal FILE.json | --estimate-magcal]

(also reached as ``python -m ground.estimate INPUT.csv --inertia OUT.json``). INPUT is a recording
in format v1 (`recording.py`): the field samples and the known applied moment ``m*_Nm`` (about the
centre of mass, sensor axes; from the simulation truth in SITL, from the tug's log otherwise).
Euler's equations and the attitude kinematics are integrated with the candidate tensor and fitted to
the samples themselves (`fsw.estimation.euler_fit`: multiple shooting, then single shooting): no rate
is differentiated, so no errors-in-variables bias. The inertial field along the orbit comes from the
flight copy of the field model (`ground.field.recording_field`, said on the first line) for the orbit of
``--scenario``, of ``--tle``/``--utc0`` (``--utc0`` alone: the recording's TLE at another t = 0), or of the
recording's metadata (the ``tle_line1``/``tle_line2``/``utc0`` that `ground.decode` writes, or a circular
orbit: ``# orbit_altitude_km:``, ``# orbit_inclination_deg:``, ``# orbit_raan_deg:``,
``# orbit_arg_lat0_deg:``, ``# field_epoch_year:``; ``t_s`` = 0 at the orbit's epoch, the Earth rotation
angle 0 there).

Without an orbit (a laboratory file, an old export) the fit still runs, as in sedelnikov2023, on the
assumption that the field's direction is fixed in inertial space, its magnitude the recording's own
(|B| does not depend on the attitude: a cubic in time through the samples' |B|). On a low orbit the
direction turns at about twice the orbital rate, which that assumption ignores, so the intervals are
widened for it: the fit is repeated with the field turning at ``--field-turn-dps`` (default 0.133 °/s,
`ground.field.LEO_FIELD_TURN_DPS`; 0.0042 for a laboratory, the Earth's rotation; 0: no widening) about
each inertial axis in turn, and the three shifts of the tensor are added to its covariance
(Σ_k d_k d_kᵀ: a turn of that size about any axis). Three more fits: the run takes about four times as
long. The JSON says so in ``field_turn``; the running estimate of ``--plot`` is not widened.

``--field-error`` fits the field model's error along the record with the tensor — a smooth offset of the
inertial field (an old TLE, a clock off) and a drift of the host's hard iron, their size from |B|
against the model's |B| (`fsw.estimation.euler_fit.field_error`) — and puts its uncertainty in the
intervals (JSON ``field_error``).

The host's hard and soft iron are taken out of the samples first with ``--magcal FILE.json`` or
``--estimate-magcal`` (`ground/magcal.py`; the JSON then says which in ``magcal``). Before that the de-orbit
kit's field the box recorded (``kit_b*_uT``) is subtracted and the samples flagged KIT_MOVING are skipped
(`ground/kit_field.py`; the first line says how many; ``--kit-raw`` keeps them as recorded).

Output: the inertia JSON of recording-format.md — tensor about the centre of mass in sensor axes,
95 % half-widths, principal moments, method, samples — plus the 99 % half-widths, the physical
checks, the fitted initial rate and the offset. ``--plot`` draws the running estimate (the fit of the
first n samples, n growing) with its 95 % band next to the final value, like sedelnikov2023's
Figures 11–12 (and the truth, when a scenario gives it).
"""
from __future__ import annotations

import argparse
import json
import math
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from fsw.argtypes import ArgumentParser, check_paths_or_exit, finite_float, int_range, iso_time
from fsw.config import MAX_SIGMA_UT
from fsw.estimation import euler_fit as ef
from fsw.estimation.euler_fit import field_error
from fsw.estimation import field_check as fc
from fsw.estimation import inertia as inr
from fsw.estimation import sampled_moment as sm
from fsw.estimation.tle import TleError, parse_tle
from fsw.files import write_atomic

from . import kit_field
from . import magcal as gm
from .field import LEO_FIELD_TURN_DPS, recording_field, scenario_field
from .plot import check_plot_path_or_exit, save_figure
from .recording import Recording, RecordingError, read_recording

#: metadata keys of the orbit (recording ``# key: value`` lines)
ORBIT_KEYS = ("orbit_altitude_km", "orbit_inclination_deg", "orbit_raan_deg", "orbit_arg_lat0_deg",
              "field_epoch_year")


@dataclass
class InertiaReport:
    """What :func:`run` found: the final estimate, the fit behind it, and the running estimate."""

    estimate: inr.InertiaEstimate
    fit: ef.FitResult
    running: list[tuple[float, np.ndarray, np.ndarray]] = field(default_factory=list)  # (t_end, p, ci95)
    truth_p: np.ndarray | None = None
    source: str = ""


def field_model(scenario: str | None = None, metadata: dict | None = None, *, tle=None, utc0=None
                ) -> tuple[Callable | None, np.ndarray | None, str]:
    """B_I(t) along the orbit of a scenario (name or TOML), of `tle`/`utc0` or of the recording metadata
    (`ground.field.recording_field`), None without one; also the truth tensor (scenario only) and a
    description."""
    if scenario:
        field, scn = scenario_field(scenario)
        return field.b_eci_T, inr.params(scn.inertia_kgm2), f"scenario {scn.name}"
    field, how = recording_field(metadata or {}, tle=tle, utc0=utc0)
    return (None if field is None else field.b_eci_T), None, how


def fixed_field(rec: Recording) -> Callable:
    """A field fixed in direction (inertial z) with the recording's own magnitude, a cubic in time through
    the samples' |B| (the magnitude does not depend on the attitude): the field model of a recording
    without an orbit."""
    t = rec.t_s
    t_mid, span = 0.5 * (t[0] + t[-1]), max(0.5 * (t[-1] - t[0]), 1e-9)
    coef = np.polyfit((t - t_mid) / span, np.linalg.norm(rec.b_T, axis=1), min(3, len(t) - 1))

    def b_inertial(ts):
        ts = np.asarray(ts, float)
        out = np.zeros(ts.shape + (3,))
        out[..., 2] = np.polyval(coef, (ts - t_mid) / span)
        return out

    return b_inertial


def turning(b_inertial: Callable, w_radps: np.ndarray, t_mid_s: float) -> Callable:
    """`b_inertial` turned at the constant rate `w_radps` (inertial axes) about its value at `t_mid_s`."""
    from scipy.spatial.transform import Rotation

    def b(ts):
        ts = np.asarray(ts, float)
        flat = np.atleast_1d(ts)
        out = Rotation.from_rotvec(np.outer(flat - t_mid_s, w_radps)).apply(np.asarray(b_inertial(flat)).reshape(-1, 3))
        return out.reshape(ts.shape + (3,))

    return b


def widen_for_field_turn(rec: Recording, report: InertiaReport, b_fixed: Callable, turn_dps: float,
                         log: Callable[[str], None] | None = None, **fit) -> None:
    """Add to the estimate's covariance what the field's unseen turn may do to it: refits with the field
    turning at `turn_dps` about each inertial axis, Σ_k d_k d_kᵀ of the tensor's shifts (see the module's
    docstring); `fit`: the options of :func:`run`."""
    w = math.radians(turn_dps)
    t_mid = 0.5 * (rec.t_s[0] + rec.t_s[-1])
    shifts = []
    for k in range(3):
        if log:
            log(f"refit with the field turning at {turn_dps:g} °/s about inertial axis {'xyz'[k]}")
        axis = np.zeros(3)
        axis[k] = w
        shifts.append(run(rec, turning(b_fixed, axis, t_mid), running_points=0, **fit).estimate.p
                      - report.estimate.p)
    d = np.array(shifts)
    est = report.estimate
    before = est.ci95.copy()
    est.cov = est.cov + d.T @ d
    est.extra["field_turn"] = {
        "assumed": "no orbit: the field's direction fixed in inertial space; intervals widened for a turn of "
                   f"{turn_dps:g} deg/s about any inertial axis",
        "turn_dps": turn_dps, "shift_kgm2": d.tolist(), "ci95_before_kgm2": before.tolist()}


def known_action(rec: Recording, hold: str = "centered") -> ef.KnownAction:
    """The known moment of a recording (its m*_Nm columns held between samples)."""
    return ef.KnownAction.from_samples(rec.t_s, rec.m_Nm, hold=hold)


def known_moment_span(rec: Recording) -> tuple[Recording, int]:
    """The recording from its first to its last sample with a known moment, and how many samples that
    leaves out: before the first and after the last known moment nothing could fix an unknown one
    (`fsw.estimation.sampled_moment`); unknown moments between them are fitted."""
    i0, i1 = sm.known_span(rec.m_Nm)
    if (i0, i1) == (0, len(rec)):
        return rec, 0
    return rec.rows(slice(i0, i1)), len(rec) - (i1 - i0)


def run(rec: Recording, b_inertial: Callable, *, sigma_b_T: float = 1.5e-6, mode: str = "full",
        guess_kgm2: float | None = None, hold: str = "centered", running_points: int = 12,
        opts: ef.FitOptions | None = None, log: Callable[[str], None] | None = None) -> InertiaReport:
    """Fit the tensor to a recording; ``running_points`` prefixes for the running estimate (0: none).

    ``guess_kgm2``: starting tensor guess × identity (default: 100 kg·m²); it is also the mean of a weak
    prior (1-σ three times the guess), so it need only be right within a factor of a few.
    """
    unknown = int(sm.unknown_rows(rec.m_Nm).sum())
    rec, excluded = known_moment_span(rec)
    if len(rec) < 20:
        raise ValueError(f"{len(rec)} samples with a known moment span: too few to identify a tensor "
                         "(need 20 or more)")
    opts = opts or ef.FitOptions(mode=mode)
    opts.mode = mode
    action = known_action(rec, hold)
    plan = sm.plan(rec.t_s, rec.m_Nm, hold)
    if not np.any(action.moment_Nm):
        raise ValueError("the recording has no known moment (m*_Nm all zero): torque-free data fix the "
                         "tensor only up to scale")
    g = 100.0 if guess_kgm2 is None else float(guess_kgm2)
    check_moments(rec, g)
    p_guess = np.array([g, g, g, 0.0, 0.0, 0.0])
    t, b = rec.t_s, rec.b_T
    b_samples = np.asarray(b_inertial(t), float)
    fit = ef.identify(t, b[None], b_inertial, action, sigma_b_T, p_guess, opts, b_samples=b_samples, log=log)[0]
    est = fit.estimate(f"output-error fit of Euler + kinematics to the samples ({mode})")
    if fit.field_error is not None:
        est.extra["field_error"] = {"assumed": "the field model's error along the record fitted (a smooth offset of "
                                               "the inertial field, the host's drift) and its uncertainty in the "
                                               "intervals", **fit.field_error.as_dict()}
    est.extra.update({"omega0_dps": np.degrees(fit.omega0_radps).tolist(), "offset_uT": (fit.bias_T * 1e6).tolist(),
                      "t0_s": float(t[0]), "sigma_uT": sigma_b_T * 1e6,
                      "moment_unknown": {"samples": unknown, "held": plan.held,
                                         "shortest_hold_s": plan.shortest_hold_s,
                                         "fitted_one_switch": plan.switch, "fitted_free": plan.free,
                                         "fitted_intervals": len(plan.intervals), "left_out_at_ends": excluded}})
    running = []
    if running_points > 0:
        n = len(t)
        lengths = sorted({int(round(x)) for x in np.linspace(max(20, n / running_points), n, running_points)})
        for res, nn in zip(ef.prefix_fits(t, b, b_inertial, action, sigma_b_T, fit, lengths, p_guess, opts,
                                          b_samples=b_samples), lengths):
            running.append((float(t[nn - 1]), res.p, inr.half_width(res.cov_p, 0.95)))
    return InertiaReport(est, fit, running)


#: how far below the guess the tensor may be, for the plausibility of the known moment
GUESS_RANGE = 10.0


def check_moments(rec: Recording, guess_kgm2: float) -> None:
    """Refuse (ValueError) a known moment no sampled body near the guess could show: one that would turn
    a body of a tenth of the guessed tensor by more than half a turn in one sample step, beyond which
    the samples cannot say how it turned (a moment in the wrong units, or a corrupted file). NaN rows
    (unknown moment) are not judged here."""
    if len(rec) < 2:
        return
    dt = float(np.median(np.diff(rec.t_s)))
    limit = math.pi * (guess_kgm2 / GUESS_RANGE) / dt ** 2
    size = np.linalg.norm(rec.m_Nm, axis=1)
    bad = np.flatnonzero(size > limit)  # NaN compares False
    if bad.size:
        k = int(bad[0])
        where = f"{rec.path}: " if rec.path is not None else ""
        raise ValueError(f"{where}known moment m*_Nm of {size[k]:.3g} N·m at t = {rec.t_s[k]:g} s ({bad.size} "
                         f"samples above {limit:.3g} N·m) would turn a body of {guess_kgm2 / GUESS_RANGE:g} kg·m² "
                         f"(a tenth of --guess) by more than half a turn in one {dt:g} s sample step: "
                         "not a moment in N·m?")


def write_json(path: str | Path, est: inr.InertiaEstimate, **extra) -> None:
    """Write the inertia JSON (atomically: nothing is written on error)."""
    doc = est.to_json()
    doc.update(extra)
    write_atomic(path, json.dumps(doc, indent=2, default=float) + "\n")


def plot(path: str | Path, report: InertiaReport) -> None:
    """The running estimate of each component with its 95 % band, the final value and the truth."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    full = report.estimate.full
    comps = range(6) if full else range(3)
    fig, axes = plt.subplots(2 if full else 1, 3, figsize=(12, 6.5 if full else 3.6), squeeze=False)
    t = np.array([r[0] for r in report.running])
    p = np.array([r[1] for r in report.running]) if report.running else np.zeros((0, 6))
    ci = np.array([r[2] for r in report.running]) if report.running else np.zeros((0, 6))
    final, hw = report.estimate.p, report.estimate.ci95
    for k in comps:
        ax = axes.flat[k]
        if len(t):
            ax.fill_between(t, p[:, k] - ci[:, k], p[:, k] + ci[:, k], color="C0", alpha=0.25,
                            label="95 % band")
            ax.plot(t, p[:, k], "o-", color="C0", ms=3, label="running estimate")
        ax.axhline(final[k], color="k", lw=1, label=f"final {final[k]:.1f} ± {hw[k]:.1f}")
        if report.truth_p is not None:
            ax.axhline(report.truth_p[k], color="C3", ls="--", lw=1, label=f"truth {report.truth_p[k]:.1f}")
        half = 6 * max(hw[k], 1e-3 * abs(final[k]) + 1e-6)
        lo, hi = final[k] - half, final[k] + half
        ax.set_ylim(lo, hi)
        ax.set_title(f"{inr.COMPONENTS[k]} [kg·m²]")
        ax.set_xlabel("data up to t [s]")
        ax.legend(fontsize=7)
    fig.suptitle("Inertia tensor about the centre of mass, sensor axes: running estimate "
                 f"({report.estimate.method})", fontsize=9)
    fig.tight_layout()
    try:
        save_figure(fig, path, dpi=110)
    finally:
        plt.close(fig)


def summary(report: InertiaReport) -> str:
    e = report.estimate
    c = e.checks()
    lines = [f"inertia about the centre of mass, sensor axes ({e.method}, {e.samples_used} samples, "
             f"χ²/dof {e.extra.get('chi2_per_dof', math.nan):.3f})",
             "component      estimate    ±95 %     ±99 %" + ("       truth" if report.truth_p is not None else "")]
    for k, name in enumerate(inr.COMPONENTS):
        if not e.full and k >= 3:
            continue
        row = f"  {name:<8s} {e.p[k]:11.3f} {e.ci95[k]:8.3f} {e.ci99[k]:9.3f}"
        if report.truth_p is not None:
            row += f" {report.truth_p[k]:11.3f}"
        lines.append(row + "  kg·m²")
    u = e.extra.get("moment_unknown")
    if u and u["samples"]:
        lines.append(f"applied moment unknown (NaN) at {u['samples']} samples: {u['held']} held between equal "
                     f"known moments (gaps shorter than the shortest hold, {u['shortest_hold_s']:.3g} s), "
                     f"{u['fitted_one_switch'] + u['fitted_free']} fitted as {u['fitted_intervals']} unknown "
                     f"constant moments ({u['fitted_one_switch']} across a switch), {u['left_out_at_ends']} "
                     "left out at the ends")
    I = c["principal_kgm2"]
    lines.append(f"principal moments {I[0]:.2f} {I[1]:.2f} {I[2]:.2f} kg·m²; positive definite: "
                 f"{'yes' if c['positive_definite'] else 'NO'}; triangle inequalities: "
                 f"{'yes' if c['triangle'] else 'NO'} (margin {c['triangle_margin_kgm2']:.2f} kg·m²)")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = ArgumentParser(prog="python -m ground.inertia", description=__doc__.splitlines()[0])
    ap.add_argument("input", help="recording-format CSV with the field and the known moment m*_Nm")
    ap.add_argument("output", help="inertia JSON to write")
    add_arguments(ap)
    args = ap.parse_args(argv)
    check_cli_paths(ap, args.input, args.output, args)
    return run_cli(args.input, args.output, args)


def add_arguments(ap: argparse.ArgumentParser) -> None:
    """The options of the inertia fit (shared with ``python -m ground.estimate --inertia``)."""
    ap.add_argument("--scenario", metavar="NAME|FILE",
                    help="take the orbit (field model) and the truth from a SITL scenario")
    ap.add_argument("--tle", nargs=2, metavar=("LINE1", "LINE2"), help="the field along a TLE's orbit (with --utc0)")
    ap.add_argument("--utc0", type=iso_time, help="UTC of the recording's t = 0, ISO 8601 (with --tle; alone: "
                                                  "the recording's TLE at this t = 0)")
    ap.add_argument("--field-turn-dps", type=finite_float(0), default=LEO_FIELD_TURN_DPS, metavar="DPS",
                    help="without an orbit: the field's turn in inertial space the intervals allow for "
                         f"(default {LEO_FIELD_TURN_DPS} °/s, a low orbit; 0: none)")
    ap.add_argument("--sigma-uT", type=finite_float(0, MAX_SIGMA_UT, min_exclusive=True), default=1.5,
                    help="1-σ field noise per axis, > 0 (default 1.5 µT)")
    ap.add_argument("--diag", action="store_true",
                    help="diagonal tensor only (sedelnikov2023's special case: sensor axes = principal axes)")
    ap.add_argument("--guess", type=finite_float(0, min_exclusive=True), default=100.0, metavar="KGM2",
                    help="starting tensor = this × identity, within a factor of a few (default 100)")
    ap.add_argument("--hold", choices=("centered", "forward"), default="centered",
                    help="how the sampled moment holds between samples (default centered)")
    ap.add_argument("--plot", metavar="FILE", help="draw the running estimate with its 95 %% band (PNG)")
    ap.add_argument("--running", type=int_range(1), default=12, metavar="N",
                    help="points of the running estimate drawn by --plot (default 12)")
    ap.add_argument("--field-error", action="store_true",
                    help="fit the field model's error along the record with the tensor (an old TLE, a clock off, "
                         "the host's drift) and put its uncertainty in the intervals")
    ap.add_argument("--quiet", action="store_true", help="no progress lines")
    gm.add_arguments(ap)
    kit_field.add_arguments(ap)


def check_cli_paths(ap: argparse.ArgumentParser, input_path: str, output_path: str, args,
                    output_label: str = "output") -> None:
    """Before any work: the output JSON and plot are not an input nor each other, can be written, and
    the plot's suffix is an image format (usage error, exit 2, otherwise)."""
    check_paths_or_exit(ap, inputs={"input": input_path, "--scenario": args.scenario,
                                    "--magcal": getattr(args, "magcal", None)},
                        outputs={output_label: output_path, "--plot": args.plot})
    check_plot_path_or_exit(ap, args.plot)


def run_cli(input_path: str, output_path: str, args) -> int:
    tle = getattr(args, "tle", None)
    if tle and not getattr(args, "utc0", None):
        print("ground.inertia: --tle needs --utc0", file=sys.stderr)
        return 2
    if tle and args.scenario:
        print("ground.inertia: give --scenario or --tle, not both", file=sys.stderr)
        return 2
    if tle:
        try:
            parse_tle(*tle)
        except TleError as e:
            print(f"ground.inertia: --tle: {e}", file=sys.stderr)
            return 2
    try:
        rec, kit_line = kit_field.take_out(read_recording(input_path), raw=getattr(args, "kit_raw", False))
        print(kit_line)
        fc.check(rec.b_T, str(input_path))             # units first: they matter more than a missing orbit
        b_inertial, truth, where = field_model(args.scenario, rec.metadata, tle=tle, utc0=getattr(args, "utc0", None))
        print(f"field: {where}")
        rec, calibrated = gm.calibrate(rec, args, b_inertial, args.sigma_uT * 1e-6)
        if calibrated:
            print(calibrated)
        no_orbit = b_inertial is None
        if no_orbit:
            b_inertial = fixed_field(rec)
        else:
            for w in fc.check_recording(rec.b_T, str(input_path), rec.t_s, field=b_inertial):
                print(f"ground.inertia: warning: {w}", file=sys.stderr)
        log = None if args.quiet else (lambda m: print("  " + m, flush=True))
        fit = dict(sigma_b_T=args.sigma_uT * 1e-6, mode="diag" if args.diag else "full", guess_kgm2=args.guess,
                   hold=args.hold)
        if getattr(args, "field_error", False):
            fit["opts"] = ef.FitOptions(field_error_degree=field_error.degree_for(float(rec.t_s[-1] - rec.t_s[0])))
        report = run(rec, b_inertial, running_points=args.running if args.plot else 0, log=log, **fit)
        turn = getattr(args, "field_turn_dps", LEO_FIELD_TURN_DPS)
        if no_orbit and turn > 0:
            widen_for_field_turn(rec, report, b_inertial, turn, log=log, **fit)
            print(f"no orbit: intervals widened for the field's turn of {turn:g} °/s (--field-turn-dps): 95 % "
                  "half-widths " + ", ".join(f"{a:.2f} → {b:.2f}" for a, b in
                                             zip(report.estimate.extra["field_turn"]["ci95_before_kgm2"],
                                                 report.estimate.ci95)) + " kg·m²")
    except (OSError, RecordingError, ValueError) as e:
        print(f"ground.inertia: {e}", file=sys.stderr)
        return 1
    report.truth_p = truth
    report.source = where
    try:
        extra = {"magcal": calibrated} if calibrated else {}
        write_json(output_path, report.estimate, input=str(input_path), field_model=where, **extra)
        print(summary(report))
        print(f"wrote inertia: {output_path}")
        if args.plot:
            plot(args.plot, report)
            print(f"wrote plot: {args.plot}")
    except (OSError, ValueError) as e:
        print(f"ground.inertia: {e}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    from fsw.startup import exit_with

    exit_with(main)
