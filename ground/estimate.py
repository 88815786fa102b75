"""Body rate from a magnetometer recording, by any of the methods: `python -m ground.estimate`.

    python -m ground.estimate run.csv --rates rates.csv --method smoother --plot rates.png
    python -m ground.estimate run.csv --rates rates.csv --method euler --scenario isoi   # field along the orbit
    python -m ground.estimate lab.csv --rates r.csv --method kalman --decimate-hz 10

Reads recording format v1 (`ground/recording.py`), writes the rate-estimate CSV (one row per input
sample, NaN where a method has no estimate) and, with `--plot`, each axis with its 1-σ band and the
reference rate when the recording has one (sedelnikov2024 Figures 9/12). With a reference it prints the
RMS and maximum error, of the full vector and of the part perpendicular to B.

Methods: boer (perpendicular part; `boer-printed` is the paper's sign, for comparison), derivative,
kotelnikov (`kotelnikov-paper`: sedelnikov2023's discrete pairing), kalman (the onboard filter),
kalman-orbit / kalman-euler / kalman-mm (attitude filter; -mm: a bank of rate models, random walk
and Gauss–Markov, for a slow libration; need an orbit for the field's motion unless the field
is fixed), smoother (RTS), euler (batch torque-free fit), auto (euler when it explains the data, else
smoother; never a fit that another candidate's σ excludes: `ground.smoother`'s docstring).

σ: without a field model every σ is widened by the field's own turning (`--field-turn-dps`), and a
record whose |B| varies beyond the noise (an uncalibrated host) widens the noise-only methods' σ
(`estimate`); with reference columns the share of components within 1-σ is printed.

The field along the orbit (`ground.field.recording_field`, said on the first line): `--scenario NAME|FILE` (a
SITL scenario's orbit and field epoch; the recording's t = 0 is the scenario's) or `--tle LINE1 LINE2
--utc0 ISO` (or `--utc0` alone: the recording's TLE at another t = 0), else the recording's metadata
(the TLE and utc0 `ground.decode` writes, or a circular orbit). Without any, the field's direction is
assumed fixed in inertial space — the papers' assumption; on a low orbit it turns at about twice the
orbital rate — and every method then measures the body's rate relative to the field's turning frame:
its σ is widened ⊥B by that turn, `--field-turn-dps` (default 0.133 °/s, a low orbit; 0.0042 for a
laboratory, the Earth's rotation; 0: none).

The host's hard and soft iron: `--magcal FILE.json` applies a calibration to the samples first,
`--estimate-magcal` estimates it from the recording along its orbit, and without either the calibration in
the recording's metadata (the box's) is applied unless `--no-magcal` (`ground/magcal.py`). Before that the
de-orbit kit's field the box recorded (``kit_b*_uT``) is subtracted and the samples flagged KIT_MOVING are
skipped (`ground/kit_field.py`; the first line says how many; `--kit-raw` keeps them as recorded).
"""
from __future__ import annotations

import argparse
import math
import sys
from datetime import datetime

import numpy as np

from fsw.argtypes import ArgumentParser, check_paths_or_exit, finite_float, iso_time
from fsw.config import MAX_SIGMA_UT
from fsw.estimation import attitude_kalman as ak
from fsw.estimation import field_check as fc
from fsw.estimation import filter_banks as fb
from fsw.estimation import kotelnikov as ko
from fsw.estimation import rate_formulas as rf
from fsw.estimation import rate_kalman as rk
from fsw.estimation.tle import TleError, parse_tle
from ground import angle_sum, kit_field
from ground import magcal as gm
from ground import smoother as sm
from ground.field import recording_field, scenario_field, tle_field
from ground.recording import RateEstimates, Recording, RecordingError, read_recording, write_rate_estimates

#: a field error (share of |B|, :func:`field_error_rel`) below this is not added to σ (noise's own spread)
FIELD_ERROR_NOTE = 0.005
#: methods whose σ already scales with their misfit (the ground smoothers' variance of unit weight and
#: fitted noise factor): no field-error widening on top
MISFIT_SCALED = ("smoother", "euler", "auto")
METHODS = ("boer", "boer-printed", "derivative", "kotelnikov", "kotelnikov-paper", "kalman", "kalman-orbit",
           "kalman-euler", "kalman-mm", "smoother", "euler", "auto")
PERPENDICULAR = ("boer", "boer-printed")
#: methods that take the field as fixed in inertial space whether or not a field model is given (they do
#: not use it): their σ is widened by the field's turning either way
FIELD_BLIND = ("boer", "boer-printed", "derivative", "kotelnikov", "kotelnikov-paper", "kalman")
#: samples a method needs for its first estimate: two for a difference, three for a second one (and for
#: the full vector of the filters and smoothers, which ΔB of one step does not fix)
MIN_SAMPLES = {m: 2 if m in PERPENDICULAR or m.startswith("kalman") else 3 for m in METHODS}


def noise_estimate_T(b_T: np.ndarray) -> float:
    """Per-axis white-noise σ from third differences (var = 20 σ² for white noise), robust (MAD).
    A smooth signal sampled fast leaves the noise; a coarse sampling of fast motion overestimates it."""
    d3 = np.diff(np.asarray(b_T, float), n=3, axis=0)
    if len(d3) < 3:
        return 1.5e-6
    mad = np.median(np.abs(d3 - np.median(d3, axis=0)), axis=0) / 0.6745
    return float(np.sqrt(np.mean(mad ** 2) / 20.0))


def decimate(rec: Recording, hz: float) -> Recording:
    """Keep one sample per 1/hz seconds (the first at or after each grid time): a slower sensor."""
    step = 1.0 / hz
    keep, next_t = [], rec.t_s[0]
    for i, t in enumerate(rec.t_s):
        if t >= next_t - 1e-9:
            keep.append(i)
            next_t = t + step
    return rec.rows(np.array(keep))


def field_error_rel(t_s: np.ndarray, b_T: np.ndarray, sigma_b_T: float) -> float:
    """The field's error that the noise does not explain, as a fraction of |B|: the spread of |B| about
    a quadratic in time (the orbit changes |B| slowly; a host's iron that turns with the body, a scale
    error, make |B| follow the attitude) beyond the noise's σ_B, over the median |B|. An uncalibrated
    host's 14 µT on 45 µT: ~0.2; a calibrated or clean record: ~0."""
    t = np.asarray(t_s, float)
    mag = np.linalg.norm(np.asarray(b_T, float), axis=1)
    ok = np.isfinite(mag) & np.isfinite(t)
    if ok.sum() < 10:
        return 0.0
    x = (t[ok] - t[ok].mean()) / max(np.ptp(t[ok]), 1e-9)
    resid = mag[ok] - np.polyval(np.polyfit(x, mag[ok], 2), x)
    excess = float(np.mean(resid ** 2)) - sigma_b_T ** 2
    return math.sqrt(excess) / float(np.median(mag[ok])) if excess > 0 else 0.0


def estimate(method: str, t: np.ndarray, b: np.ndarray, sigma_b_T: float, *, field=None,
             inertia_kgm2=None, field_turn_radps: float = rf.LEO_FIELD_TURN_RADPS,
             hard_iron_sigma_T=None) -> tuple[np.ndarray, np.ndarray, dict]:
    """ω (N, 3) and 1-σ (N, 3) in rad/s of `method`, NaN where it has none; and notes.

    `hard_iron_sigma_T`: the applied host calibration's hard-iron 1-σ: the batch fit (`euler`, `auto`) then
    also fits what is left of the hard iron as a constant offset in body axes with that prior
    (`ground.smoother.euler_fit`; the note `hard_iron_residual_uT` gives it).

    Without a field model (`field` None) every method takes the field as fixed in inertial space and
    its σ is widened by the field's own turning, `field_turn_radps` (default: low Earth orbit's, 0.13 °/s;
    0 for a laboratory's fixed field; so is the σ of the methods that never use a model,
    :data:`FIELD_BLIND`, when one is given): `fsw.estimation.rate_formulas.widen_for_field_turn`. A record
    whose |B| varies beyond the noise (:func:`field_error_rel` > 0.5 %: an uncalibrated host) has the σ
    of every method whose σ is the noise's alone (not the smoothers', which scale with their misfit)
    widened by that share of |ω| (`rate_formulas.widen_for_field_error`)."""
    w, s, notes = _estimate(method, t, b, sigma_b_T, field=field, inertia_kgm2=inertia_kgm2,
                            hard_iron_sigma_T=hard_iron_sigma_T)
    scale = notes.pop("variance_scale", None)
    eps = field_error_rel(t, b, sigma_b_T) if method not in MISFIT_SCALED or scale is not None else 0.0
    if eps > FIELD_ERROR_NOTE:
        if scale is not None:
            s = field_error_instead_of_misfit(s, w, eps, scale)
        else:
            s = rf.widen_for_field_error(s, w, eps)
        notes["sigma_widened_field_error"] = (f"|B| varies {100 * eps:.2g} % beyond the noise (host iron "
                                              "uncalibrated?): σ + that share of |ω|")
    if (field is None or method in FIELD_BLIND) and field_turn_radps > 0:
        s = rf.widen_for_field_turn(s, b, field_turn_radps)
        notes["sigma_widened"] = f"field taken as fixed: +{math.degrees(field_turn_radps):.3g} °/s field turn ⊥B"
    return w, s, notes


def field_error_instead_of_misfit(sigma_radps: np.ndarray, w_radps: np.ndarray, rel_error: float,
                                  variance_scale: float) -> np.ndarray:
    """A smoother's 1-σ when the field itself is off (:func:`field_error_rel` above `FIELD_ERROR_NOTE`: an
    uncalibrated host): its σ scaled by √`variance_scale` (the innovations' variance of unit weight) reads
    the misfit as white noise `variance_scale` times σ_B², while a field off by a share ε of |B| is a
    systematic error whose cost in rate is about ε|ω| (`rate_formulas.widen_for_field_error`). Unscaled, then
    widened by that: on `bench.realistic`'s uncalibrated host with the TLE (χ²/dof ≈ 25) the smoother's σ
    was 5.2 °/s per axis on a 1.4 °/s error (covered 99 %)."""
    s = np.asarray(sigma_radps, float) / math.sqrt(max(float(variance_scale), 1.0))
    return rf.widen_for_field_error(s, w_radps, rel_error)


def _estimate(method: str, t: np.ndarray, b: np.ndarray, sigma_b_T: float, *, field=None,
              inertia_kgm2=None, hard_iron_sigma_T=None) -> tuple[np.ndarray, np.ndarray, dict]:
    notes: dict = {}
    if method == "boer":
        return rf.boer_rate(t, b), _diag_sigma(rf.boer_covariance(t, b, sigma_b_T)), notes
    if method == "boer-printed":
        return rf.boer_rate_printed(t, b), _diag_sigma(rf.boer_covariance(t, b, sigma_b_T)), notes
    if method == "derivative":
        return rf.derivative_rate(t, b), _diag_sigma(rf.derivative_covariance(t, b, sigma_b_T)), notes
    if method in ("kotelnikov", "kotelnikov-paper"):
        tu, bu = t, b
        steps = np.diff(t)
        if np.max(np.abs(steps - np.median(steps))) > 0.02 * np.median(steps):
            tu, bu = ko.resample_uniform(t, b)
            notes["resampled"] = f"to a uniform {np.median(steps):.4g} s grid (linear), back by interpolation"
        w, s = ko.kotelnikov_rate(tu, bu, sigma_b_T, form="paper" if method.endswith("paper") else "analytic")
        if tu is not t:
            w = np.column_stack([np.interp(t, tu, w[:, i], left=np.nan, right=np.nan) for i in range(3)])
            s = np.column_stack([np.interp(t, tu, s[:, i], left=np.nan, right=np.nan) for i in range(3)])
        return w, s, notes
    if method == "kalman":
        w, s, _ = rk.kalman_rate(t, b, sigma_b_T)
        return w, s, notes
    if method in ("kalman-orbit", "kalman-euler", "kalman-mm"):
        fld = sm.tabulated(field, t)
        if method == "kalman-euler" and inertia_kgm2 is None:  # shape unknown: the parallel-hypothesis acquisition
            def make(angle):
                return fb.EulerAcquisitionKalman(sigma_b_T, field_eci_T=fld, angle_about_b_rad=angle)
        elif method == "kalman-mm":
            def make(angle):
                return fb.RateModelBank(sigma_b_T, field_eci_T=fld, angle_about_b_rad=angle)
        else:
            def make(angle):
                return ak.AttitudeRateKalman(sigma_b_T, field_eci_T=fld,
                                             inertia_kgm2=inertia_kgm2 if method == "kalman-euler" else None,
                                             angle_about_b_rad=angle)
        if fld is None:  # the attitude relative to the first sample: no angle about B to choose
            w, s, _ = rk.run_stream(make(0.0), t, b, sigma_b_T)
            return w, s, notes
        w, s, more = angle_sum.angle_sum_rate(make, t, b, sigma_b_T)
        notes.update(more)
        return w, s, notes
    if method in ("smoother", "euler", "auto"):
        model = {"smoother": "random_walk", "euler": "euler", "auto": "auto"}[method]
        res = sm.smooth(t, b, sigma_b_T, field_eci_T=field, model=model, inertia_kgm2=inertia_kgm2,
                        hard_iron_sigma_T=hard_iron_sigma_T)
        if "hard_iron_residual_uT" in res.info:
            notes["hard_iron_residual_uT"] = " ".join(f"{v:.3f}" for v in res.info["hard_iron_residual_uT"])
        notes["model"] = res.method
        if ("variance_scale" in res.info and "widened_to_cover" not in res.info
                and "widened_for_model_error" not in res.info):
            notes["variance_scale"] = float(res.info["variance_scale"])
        if "auto_choice" in res.info:  # the rule, with its k: said in the recording's metadata and summary
            notes["auto_rule"] = (f"no candidate that another's {sm.EXCLUDE_Z:g}-sigma band excludes at over "
                                  f"{100 * sm.EXCLUDE_SHARE:g} % of samples")
        if "widened_to_cover" in res.info:
            notes["sigma_covers"] = "solutions that disagree beyond their σ (ground.smoother.auto_result)"
        if "widened_for_model_error" in res.info:
            notes["sigma_model_error"] = (f"the model misses the motion: σ + the distance to the "
                                          f"{res.info['widened_for_model_error']} solution "
                                          "(ground.smoother.model_error_checked)")
        notes["chi2_per_dof"] = f"{res.chi2_dof:.3f}"
        if res.inertia_shape is not None:
            notes["inertia_shape"] = " ".join(f"{v:.4f}" for v in res.inertia_shape)
        return res.w_radps, res.sigma_radps, notes
    raise ValueError(f"unknown method {method!r}")



def _diag_sigma(cov: np.ndarray) -> np.ndarray:
    return np.sqrt(np.clip(np.einsum("kii->ki", cov), 0.0, None))


def score(rec: Recording, w: np.ndarray, perpendicular_only: bool, sigma: np.ndarray | None = None) -> dict:
    """RMS / max error (°/s) against the recording's reference: full vector and ⊥ B (measured B); with
    `sigma`, the share of components whose error is within 1-σ (`coverage_1sigma`)."""
    ref = rec.w_ref_radps
    ok = np.all(np.isfinite(w), axis=1) & np.all(np.isfinite(ref), axis=1)
    e = w[ok] - ref[ok]
    bh = rec.b_T[ok] / np.linalg.norm(rec.b_T[ok], axis=1, keepdims=True)
    e_perp = e - np.sum(e * bh, axis=1, keepdims=True) * bh
    cov = math.nan
    if sigma is not None and ok.any():  # share of components with |error| ≤ 1σ (Boer: its ⊥ part, per axis)
        ref_c = ref[ok] - (np.sum(ref[ok] * bh, axis=1, keepdims=True) * bh if perpendicular_only else 0.0)
        cov = float(np.mean(np.abs(w[ok] - ref_c) <= sigma[ok]))
    out = {"n": int(ok.sum()), "coverage_1sigma": cov,
           "perp_rms_dps": math.degrees(float(np.sqrt(np.mean(np.sum(e_perp ** 2, 1))))) if ok.any() else math.nan,
           "perp_max_dps": math.degrees(float(np.max(np.linalg.norm(e_perp, axis=1)))) if ok.any() else math.nan}
    if not perpendicular_only and ok.any():
        out["full_rms_dps"] = math.degrees(float(np.sqrt(np.mean(np.sum(e ** 2, 1)))))
        out["full_max_dps"] = math.degrees(float(np.max(np.linalg.norm(e, axis=1))))
    return out


def warn_field(rec: Recording, source: str, field=None) -> None:
    """Refuse a field that cannot be µT (FieldMagnitudeError, a ValueError naming the file); print the
    warnings of `fsw.estimation.field_check` (|B| outside the Earth's, or far from the orbit's model)."""
    for w in fc.check_recording(rec.b_T, str(source), rec.t_s, rec.metadata, field=field):
        print(f"ground.estimate: warning: {w}", file=sys.stderr)


def field_from_args(args):
    if args.scenario:
        return scenario_field(args.scenario)[0]
    if args.tle:
        utc = args.utc0 if isinstance(args.utc0, datetime) else datetime.fromisoformat(args.utc0)
        return tle_field(args.tle[0], args.tle[1], utc)
    return None


def inertia_tensor(text: str) -> np.ndarray:
    """argparse type of --known-inertia: 'Ixx,Iyy,Izz' or 9 values (row by row), kg·m², finite, a
    symmetric positive-definite tensor whose principal moments satisfy the triangle inequality."""
    try:
        vals = [float(v) for v in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"not numbers: {text!r} (give Ixx,Iyy,Izz or 9 values)") from None
    if len(vals) not in (3, 9):
        raise argparse.ArgumentTypeError(f"takes 3 or 9 values, got {len(vals)}")
    if not all(map(math.isfinite, vals)):
        raise argparse.ArgumentTypeError(f"values must be finite, got {text!r}")
    tensor = np.diag(vals) if len(vals) == 3 else np.reshape(vals, (3, 3))
    if not np.allclose(tensor, tensor.T, rtol=1e-9, atol=0.0):
        raise argparse.ArgumentTypeError("the 9 values must form a symmetric tensor")
    moments = np.linalg.eigvalsh(tensor)
    if moments[0] <= 0:
        raise argparse.ArgumentTypeError(f"must be positive definite (principal moments "
                                         f"{', '.join(f'{m:g}' for m in moments)} kg·m²)")
    if moments[0] / moments[2] + moments[1] / moments[2] < 1 - 1e-9:  # (divided: no overflow near the float limit)
        raise argparse.ArgumentTypeError(f"principal moments {', '.join(f'{m:g}' for m in moments)} kg·m² "
                                         "violate the triangle inequality (no body has them)")
    return tensor


def check_samples(rec: Recording, method: str) -> None:
    """Refuse (ValueError) a recording with fewer samples than `method` needs for an estimate."""
    need = MIN_SAMPLES[method]
    if len(rec) < need:
        where = f"{rec.path}: " if rec.path is not None else ""
        raise ValueError(f"{where}{len(rec)} samples: {method} needs at least {need}")


def inertia_main(argv) -> int:
    """`python -m ground.estimate INPUT.csv --inertia OUT.json [options of python -m ground.inertia]`."""
    from ground import inertia as gi

    ap = ArgumentParser(prog="python -m ground.estimate INPUT.csv --inertia OUT.json",
                                 description="the inertia tensor from a recording (output-error fit, ground.inertia)")
    ap.add_argument("input", help="recording, format v1 (CSV), with the known moment in m*_Nm")
    ap.add_argument("--inertia", required=True, metavar="OUT.json", help="inertia estimate to write (JSON)")
    gi.add_arguments(ap)
    args = ap.parse_args(argv)
    gi.check_cli_paths(ap, args.input, args.inertia, args, output_label="--inertia")
    return gi.run_cli(args.input, args.inertia, args)


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if "--inertia" in argv:
        return inertia_main(argv)
    ap = ArgumentParser(prog="python -m ground.estimate", description=__doc__.splitlines()[0],
                                 epilog="With --inertia OUT.json instead of --rates: the inertia tensor "
                                        "(options: python -m ground.inertia --help).")
    ap.add_argument("input", help="recording, format v1 (CSV)")
    ap.add_argument("--rates", required=True, metavar="OUT.csv", help="rate estimates to write")
    ap.add_argument("--method", choices=METHODS, default="smoother", help="estimator (default smoother)")
    ap.add_argument("--plot", metavar="FILE.png", help="estimate, 1-σ band and reference per axis")
    ap.add_argument("--sigma-uT", type=finite_float(0, MAX_SIGMA_UT, min_exclusive=True), default=None,
                    help="1-σ field noise per axis, > 0 (default: estimated from third differences)")
    ap.add_argument("--decimate-hz", type=finite_float(0, min_exclusive=True), default=None, metavar="HZ",
                    help="keep one sample per 1/HZ s first (mimic a slower sensor)")
    ap.add_argument("--scenario", metavar="NAME|FILE", help="the field along this SITL scenario's orbit")
    ap.add_argument("--tle", nargs=2, metavar=("LINE1", "LINE2"), help="the field along a TLE's orbit")
    ap.add_argument("--utc0", type=iso_time, help="UTC of the recording's t = 0, ISO 8601 (with --tle; alone: "
                                                  "the recording's TLE at this t = 0)")
    ap.add_argument("--field-turn-dps", type=finite_float(0), default=math.degrees(rf.LEO_FIELD_TURN_RADPS),
                    metavar="DPS", help="without an orbit: how fast the field may turn in inertial space, added "
                                        "to σ ⊥B (default %(default).3g, low Earth orbit; 0: a laboratory)")
    ap.add_argument("--known-inertia", metavar="I", type=inertia_tensor,
                    help="known tensor for euler/kalman-euler: 'Ixx,Iyy,Izz' or 9 values, kg·m²")
    gm.add_arguments(ap)
    kit_field.add_arguments(ap)
    args = ap.parse_args(argv)
    if args.tle and not args.utc0:
        ap.error("--tle needs --utc0")
    if args.scenario and args.tle:
        ap.error("give --scenario or --tle, not both")
    if args.tle:
        try:
            parse_tle(*args.tle)
        except TleError as e:
            ap.error(f"--tle: {e}")
    check_paths_or_exit(ap, inputs={"input": args.input, "--scenario": args.scenario, "--magcal": args.magcal},
                        outputs={"--rates": args.rates, "--plot": args.plot})
    from ground.plot import check_plot_path_or_exit

    check_plot_path_or_exit(ap, args.plot)
    try:
        rec, kit_line = kit_field.take_out(read_recording(args.input), raw=args.kit_raw)
        print(kit_line)
        field, orbit_how = recording_field(rec.metadata, scenario=args.scenario, tle=args.tle, utc0=args.utc0)
        print(f"field: {orbit_how}")
        check_samples(rec, args.method)
        if args.decimate_hz:
            rec = decimate(rec, args.decimate_hz)
            check_samples(rec, args.method)
        sigma = args.sigma_uT * 1e-6 if args.sigma_uT is not None else noise_estimate_T(rec.b_T)
        rec, calibrated, hard_sigma = gm.calibrate_with_sigma(rec, args, field, sigma)
        if calibrated:
            print(calibrated)
        warn_field(rec, args.input, field)
        inertia = args.known_inertia
        w, s, notes = estimate(args.method, rec.t_s, rec.b_T, sigma, field=field, inertia_kgm2=inertia,
                               field_turn_radps=math.radians(args.field_turn_dps), hard_iron_sigma_T=hard_sigma)
        meta = {"source": f"python -m ground.estimate {args.input}", "method": args.method,
                "sigma_uT": f"{sigma * 1e6:.4g}" + ("" if args.sigma_uT is not None else " (estimated)"),
                "field": "along the orbit" if field is not None else "fixed in inertial space", "orbit": orbit_how}
        if calibrated:
            meta["magcal"] = calibrated
        meta["kit_field"] = kit_line
        meta.update({k: str(v) for k, v in notes.items()})
        write_rate_estimates(args.rates, RateEstimates(rec.t_s, w, s, metadata=meta))
    except (RecordingError, ValueError, OSError) as e:
        print(f"ground.estimate: {e}", file=sys.stderr)
        return 1
    print(f"{args.method}: {int(np.all(np.isfinite(w), axis=1).sum())} estimates of {len(rec)} samples, "
          f"σ_B {sigma * 1e6:.3g} µT" + "".join(f", {k} {v}" for k, v in notes.items()))
    if rec.w_ref_radps is not None:
        sc = score(rec, w, args.method in PERPENDICULAR, s)
        parts = [f"⊥B RMS {sc['perp_rms_dps']:.3f} max {sc['perp_max_dps']:.2f}",
                 f"1-σ covers {100 * sc['coverage_1sigma']:.0f} %"]
        if "full_rms_dps" in sc:
            parts.insert(0, f"full RMS {sc['full_rms_dps']:.3f} max {sc['full_max_dps']:.2f}")
        print(f"error vs reference (°/s, {sc['n']} samples): " + ", ".join(parts))
    print(f"wrote {args.rates}")
    if args.plot:
        from ground.plot import plot_rates
        try:
            plot_rates(args.plot, rec.t_s, w, s, rec.w_ref_radps, title=f"{args.input}: {args.method}",
                       perpendicular_only=args.method in PERPENDICULAR)
        except (OSError, ValueError) as e:
            print(f"ground.estimate: --plot {args.plot}: {e}", file=sys.stderr)
            return 1
        print(f"wrote {args.plot}")
    return 0


if __name__ == "__main__":
    from fsw.startup import exit_with

    exit_with(main)
