"""The de-orbit controller's inputs from a telemetry log, against SITL's truth:
`python -m ground.deorbit_attitude LOG.tlog --plot FILE.png [--csv FILE.csv]`.

Reads every DEBRIS_DEORBIT_ATTITUDE of a tlog (`ground.tlog`, through `ground.decode.Decoder`, so that a
message the decoder refuses is refused here too): the yaw, pitch and roll the controller was given w.r.t.
the orbital frame, the σ of the sail normal's pointing, whether they were trusted, and — from SITL —
the simulation's true yaw, pitch and roll sent beside them (`truth_ypr`; NaN from the target). The plot
shows yaw and pitch, estimated (±1σ band) against true, and their difference; the CSV the same series.
Prints the RMS of the difference per axis over the trusted seconds.
"""
from __future__ import annotations

import csv
import math
import sys
from dataclasses import dataclass, field

import numpy as np

from fsw.argtypes import ArgumentParser, check_paths_or_exit

from .decode import Decoder
from .plot import check_plot_path_or_exit, save_figure
from .tlog import TlogError, read_tlog


@dataclass
class DeorbitAttitudeSeries:
    """One row per DEBRIS_DEORBIT_ATTITUDE (SI)."""

    t_s: list = field(default_factory=list)
    ypr_rad: list = field(default_factory=list)  # the controller's inputs
    sigma_rad: list = field(default_factory=list)  # pointing σ about body y, z
    truth_ypr_rad: list = field(default_factory=list)
    trusted: list = field(default_factory=list)

    def add(self, a: dict) -> None:
        self.t_s.append(a["t_s"])
        self.ypr_rad.append((a["yaw_rad"], a["pitch_rad"], a["roll_rad"]))
        self.sigma_rad.append(tuple(a["pointing_sigma_rad"]))
        self.truth_ypr_rad.append(tuple(a["truth_ypr_rad"]))
        self.trusted.append(a["source"] in ("trusted", "truth"))

    def error_rms_rad(self) -> tuple[float, float]:
        """RMS of (estimate − truth) in yaw and pitch over the trusted rows with a truth (NaN: none)."""
        est, tru = np.array(self.ypr_rad, float).reshape(-1, 3), np.array(self.truth_ypr_rad, float).reshape(-1, 3)
        d = (est - tru + math.pi) % (2 * math.pi) - math.pi
        ok = np.asarray(self.trusted, bool) & np.isfinite(d).all(axis=1)
        if not ok.any():
            return math.nan, math.nan
        return tuple(float(np.sqrt(np.mean(d[ok, i] ** 2))) for i in (0, 1))


def read_series(path) -> DeorbitAttitudeSeries:
    """The DEBRIS_DEORBIT_ATTITUDE series of a tlog (TlogError / OSError as `ground.tlog`)."""
    dec, out = Decoder(), DeorbitAttitudeSeries()
    for rec in read_tlog(path):
        for msg in rec.messages:
            if msg.get_type() != "DEBRIS_DEORBIT_ATTITUDE":
                continue
            before = dec.deorbit_attitude
            dec.handle(msg, rec.t_us * 1e-6)
            if dec.deorbit_attitude is not before:
                out.add(dec.deorbit_attitude)
    return out


def plot(s: DeorbitAttitudeSeries, path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = np.asarray(s.t_s, float)
    est, tru = np.array(s.ypr_rad, float).reshape(-1, 3), np.array(s.truth_ypr_rad, float).reshape(-1, 3)
    sig = np.array(s.sigma_rad, float).reshape(-1, 2)
    fig, ax = plt.subplots(2, 2, figsize=(12, 6), sharex=True)
    for col, (i, name, si) in enumerate(((0, "yaw ψ", 1), (1, "pitch θ", 0))):  # yaw ~ about z, pitch ~ about y
        a = ax[0, col]
        a.plot(t, tru[:, i], lw=1.0, label="truth (SITL)")
        a.plot(t, est[:, i], lw=0.8, ls="--", label="controller's input")
        a.fill_between(t, est[:, i] - sig[:, si], est[:, i] + sig[:, si], alpha=0.2, lw=0, label="±1σ")
        a.set_ylabel(f"{name} [rad]")
        a.legend(loc="upper right", fontsize=8)
        d = (est[:, i] - tru[:, i] + math.pi) % (2 * math.pi) - math.pi
        ax[1, col].plot(t, d, lw=0.8, color="tab:red")
        ax[1, col].set_ylabel(f"{name} error [rad]")
        ax[1, col].set_xlabel("time [s]")
    fig.suptitle("De-orbit controller's attitude against SITL's truth (DEBRIS_DEORBIT_ATTITUDE)")
    fig.tight_layout()
    save_figure(fig, path, dpi=110)
    plt.close(fig)


def write_csv(s: DeorbitAttitudeSeries, path) -> None:
    from fsw.files import atomic_file

    with atomic_file(path, "w") as f:
        w = csv.writer(f, lineterminator="\n")
        w.writerow(["t_s", "yaw_rad", "pitch_rad", "roll_rad", "sigma_y_rad", "sigma_z_rad", "true_yaw_rad",
                    "true_pitch_rad", "true_roll_rad", "trusted"])
        for row in zip(s.t_s, s.ypr_rad, s.sigma_rad, s.truth_ypr_rad, s.trusted):
            w.writerow([row[0], *row[1], *row[2], *row[3], int(row[4])])


def main(argv: list[str] | None = None) -> int:
    ap = ArgumentParser(prog="python -m ground.deorbit_attitude", description=__doc__.splitlines()[0])
    ap.add_argument("tlog", help="a telemetry log (.tlog) of a run with the de-orbit kit")
    ap.add_argument("--plot", metavar="FILE.png", help="estimated against true yaw and pitch")
    ap.add_argument("--csv", metavar="FILE.csv", help="the series")
    args = ap.parse_args(argv)
    check_paths_or_exit(ap, inputs={"tlog": args.tlog}, outputs={"--plot": args.plot, "--csv": args.csv})
    check_plot_path_or_exit(ap, args.plot)
    try:
        s = read_series(args.tlog)
    except (TlogError, OSError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    if not s.t_s:
        print(f"error: {args.tlog}: no DEBRIS_DEORBIT_ATTITUDE", file=sys.stderr)
        return 1
    ry, rp = s.error_rms_rad()
    print(f"{len(s.t_s)} DEBRIS_DEORBIT_ATTITUDE, {sum(s.trusted)} trusted; estimate - truth RMS over the trusted: "
          f"yaw {ry:.3f} rad, pitch {rp:.3f} rad" + (" (no truth in this log: not SITL)" if math.isnan(ry) else ""))
    if args.plot:
        plot(s, args.plot)
        print(f"wrote {args.plot}")
    if args.csv:
        write_csv(s, args.csv)
        print(f"wrote {args.csv}")
    return 0


if __name__ == "__main__":
    from fsw.startup import exit_with

    exit_with(main)
