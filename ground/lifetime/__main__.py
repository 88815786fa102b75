"""python -m ground.lifetime: how long until re-entry, with the de-orbit sail tumbling and stabilised.

    python -m ground.lifetime --perigee-km 600 --inclination-deg 90 --json out.json --plot out.png
    python -m ground.lifetime --tle "1 ..." "2 ..." --mass-kg 180 --sail-m2 5 --body-m2 0.58
    python -m ground.lifetime --paper-table --json docs/lifetime_table.json

Prints the lifetime in each attitude mode (`ground.lifetime.craft`) and the gain 1 − stabilised /
tumbling; `--plot` draws perigee and apogee against time for the modes with the 5- and 25-year lines,
`--json` writes the figures (and each decay's history, thinned to ≤ 400 points). The atmosphere is
NRLMSIS 2.1 (`ground.lifetime.atmosphere`) with the activity of `--activity` (a constant level, the
idealised solar cycle, or `--f107/--f107a/--ap`, or `--activity-file`; `ground.lifetime.activity`);
the decay is orbit-averaged (`ground.lifetime.decay`) down to a perigee of `--reentry-km` (120 km).
`--paper-table` recomputes lapkhanov2019 Table 2 (`ground.lifetime.paper`).

Exit status: 0 done, 2 bad usage or input (one line naming it).
"""
from __future__ import annotations

import json
import math
import sys

from fsw.startup import interrupt_quietly

interrupt_quietly()

import numpy as np  # noqa: E402

from fsw.argtypes import ArgumentParser, check_paths_or_exit, finite_float  # noqa: E402
from fsw.files import write_atomic  # noqa: E402

from . import activity as act  # noqa: E402
from .atmosphere import Activity, ActivityError  # noqa: E402
from .craft import MODES, Craft, CraftError, pointing_cos_from_deorbit_json  # noqa: E402
from .decay import REENTRY_KM, YEAR_DAYS, Orbit, decay  # noqa: E402


def _parser() -> ArgumentParser:
    ap = ArgumentParser(prog="python -m ground.lifetime", description=__doc__.splitlines()[0])
    o = ap.add_argument_group("orbit (heights above the equatorial radius)")
    o.add_argument("--perigee-km", type=finite_float(), metavar="KM", help="perigee height")
    o.add_argument("--apogee-km", type=finite_float(), metavar="KM", help="apogee height (default: the perigee's)")
    o.add_argument("--inclination-deg", type=finite_float(0, 180), default=90.0, metavar="DEG",
                   help="inclination (default 90)")
    o.add_argument("--tle", nargs=2, metavar=("LINE1", "LINE2"), help="the orbit from a TLE's mean elements")
    c = ap.add_argument_group("spacecraft")
    c.add_argument("--mass-kg", type=finite_float(0, min_exclusive=True), default=180.0, help="mass (default 180)")
    c.add_argument("--sail-m2", type=finite_float(0), default=5.0, help="sail area (default 5)")
    c.add_argument("--body-m2", type=finite_float(0), default=0.58, help="body midsection (default 0.58)")
    c.add_argument("--body-surface-m2", type=finite_float(0, min_exclusive=True),
                   help="body surface: tumbling body shows a quarter")
    c.add_argument("--cd", type=finite_float(0, min_exclusive=True), default=2.2, help="drag coefficient (default 2.2)")
    c.add_argument("--pointing-error-deg", type=finite_float(0, 90), default=0.0, metavar="DEG",
                   help="stabilised: the sail's angle off broadside (default 0)")
    c.add_argument("--deorbit-json", metavar="FILE",
                   help="stabilised: the largest yaw and pitch errors of a python -m bench.deorbit --json run")
    c.add_argument("--tumble-sail-fraction", type=finite_float(0, 1), default=0.5, metavar="X",
                   help="tumbling: the share of the sail shown on average (default 0.5, a random tumble)")
    c.add_argument("--passive-swing-deg", type=finite_float(0, 90), default=57.29578, metavar="DEG",
                   help="passive: amplitude of the sail's undamped yaw and pitch swings (default 1 rad)")
    c.add_argument("--modes", nargs="+", choices=MODES, default=["tumbling", "stabilised"],
                   help="attitude modes to compute (default tumbling stabilised)")
    a = ap.add_argument_group("activity")
    a.add_argument("--activity", choices=(*act.LEVELS, "cycle"),
                   help="constant low/moderate/high level or the idealised solar cycle (default moderate; "
                        "with --paper-table: F10.7 = F10.7a = 150 sfu, Ap 15)")
    a.add_argument("--cycle-phase", type=finite_float(), default=0.0, metavar="X",
                   help="with --activity cycle: phase at the start, 0 minimum, 0.5 maximum (default 0)")
    a.add_argument("--f107", type=finite_float(), metavar="SFU", help="constant F10.7 (with --f107a, --ap)")
    a.add_argument("--f107a", type=finite_float(), metavar="SFU", help="constant 81-day F10.7")
    a.add_argument("--ap", type=finite_float(), help="constant daily Ap")
    a.add_argument("--activity-file", metavar="CSV", help="monthly rows f107_sfu,f107a_sfu,ap from the start")
    ap.add_argument("--reentry-km", type=finite_float(80, 300), default=REENTRY_KM, metavar="KM",
                    help=f"stop when the perigee reaches this height (default {REENTRY_KM:g})")
    ap.add_argument("--max-years", type=finite_float(0, 1000, min_exclusive=True), default=200.0,
                    help="give up after this long (default 200)")
    ap.add_argument("--paper-table", action="store_true", help="recompute lapkhanov2019 Table 2")
    ap.add_argument("--json", metavar="FILE", help="write the figures as JSON")
    ap.add_argument("--plot", metavar="FILE", help="perigee/apogee against time (PNG)")
    ap.add_argument("--quiet", action="store_true", help="no progress bar")
    return ap


def _schedule(ap: ArgumentParser, args) -> act.Schedule:
    try:
        given = [args.f107, args.f107a, args.ap]
        if any(x is not None for x in given):
            if any(x is None for x in given):
                ap.error("--f107, --f107a and --ap go together")
            return act.constant(Activity(args.f107, args.f107a, args.ap),
                                f"F10.7 {args.f107:g} sfu, F10.7a {args.f107a:g} sfu, Ap {args.ap:g} (constant)")
        if args.activity_file:
            return act.from_file(args.activity_file)
        if args.activity == "cycle":
            return act.cycle(args.cycle_phase, args.max_years + 1)
        level = args.activity or "moderate"
        return act.constant(act.LEVELS[level], f"{level} activity (constant)")
    except ActivityError as e:
        ap.error(str(e))
    except OSError as e:
        ap.error(f"--activity-file {args.activity_file}: {e.strerror or e}")


def _orbit(ap: ArgumentParser, args) -> Orbit:
    if args.tle:
        if args.perigee_km is not None or args.apogee_km is not None:
            ap.error("give either --tle or --perigee-km/--apogee-km")
        from fsw.estimation.tle import TleError, parse_tle
        try:
            sat = parse_tle(*args.tle).satrec()
        except TleError as e:
            ap.error(f"--tle: {e}")
        return Orbit(sat.a * sat.radiusearthkm * 1e3, sat.ecco, math.degrees(sat.inclo))
    if args.perigee_km is None:
        ap.error("give the orbit: --perigee-km [--apogee-km] or --tle")
    apogee = args.perigee_km if args.apogee_km is None else args.apogee_km
    if apogee < args.perigee_km:
        ap.error(f"--apogee-km {apogee:g} is below --perigee-km {args.perigee_km:g}")
    return Orbit.from_heights(args.perigee_km, apogee, args.inclination_deg)


def _thin(d, n: int = 400) -> dict:
    k = np.unique(np.linspace(0, len(d.t_days) - 1, min(n, len(d.t_days))).round().astype(int))
    return {"t_years": (d.t_days[k] / YEAR_DAYS).round(5).tolist(), "perigee_km": d.perigee_km[k].round(3).tolist(),
            "apogee_km": d.apogee_km[k].round(3).tolist()}


def _years(x: float | None, max_years: float) -> str:
    return f"> {max_years:g} years (still in orbit)" if x is None else f"{x:.2f} years"


def plot(path: str, decays: dict, title: str) -> None:
    import matplotlib
    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    from ground.plot import save_figure

    fig = Figure(figsize=(9, 5))
    ax = fig.add_subplot()
    for (mode, d), color in zip(decays.items(), ("tab:red", "tab:blue", "tab:green")):
        t = d.t_days / YEAR_DAYS
        life = "" if d.lifetime_years is None else f" ({d.lifetime_years:.2f} years)"
        ax.plot(t, d.perigee_km, color=color, label=f"{mode}: perigee{life}")
        ax.plot(t, d.apogee_km, color=color, ls="--", lw=0.8, label=f"{mode}: apogee")
    for yr in (5, 25):
        ax.axvline(yr, color="k", lw=0.8, ls=":")
        ax.text(yr, ax.get_ylim()[1], f" {yr} years", va="top", fontsize=8)
    ax.set_xlabel("time (years)")
    ax.set_ylabel("height (km)")
    ax.set_title(title, fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, path, dpi=110)


def main(argv: list[str] | None = None) -> int:
    ap = _parser()
    args = ap.parse_args(argv)
    check_paths_or_exit(ap, inputs={"--activity-file": args.activity_file, "--deorbit-json": args.deorbit_json},
                        outputs={"--json": args.json, "--plot": args.plot})
    from ground.plot import check_plot_path_or_exit

    check_plot_path_or_exit(ap, args.plot)
    from tqdm import tqdm

    if args.paper_table:
        from . import paper
        if args.plot:
            ap.error("--plot is for one orbit, not --paper-table")
        chosen = (args.activity or args.activity_file or args.f107 is not None or args.f107a is not None
                  or args.ap is not None)
        sched = _schedule(ap, args) if chosen else None
        with tqdm(total=len(paper.ROWS), desc="Table 2 rows", disable=args.quiet, file=sys.stderr) as bar:
            res = paper.table(schedule=sched, reentry_km=args.reentry_km, progress=lambda k: bar.update(k - bar.n))
        for r in res["rows"]:
            print(f"{r['altitude_km']:.0f} x {r['apogee_km']:.2f} km, {r['inclination_deg']:.0f}°: tumbling "
                  f"{r['tumbling_years']:.2f} (paper {r['paper_tumbling_years']}), "
                  f"stabilised {r['stabilised_years']:.2f} "
                  f"(paper {r['paper_stabilised_years']}) years, gain {100 * r['gain']:.1f} % "
                  f"(paper {100 * r['paper_gain']:.1f} %)")
        if args.json:
            write_atomic(args.json, json.dumps(res, indent=1) + "\n")
            print(f"wrote {args.json}")
        return 0

    sched = _schedule(ap, args)
    orbit = _orbit(ap, args)
    if orbit.perigee_km <= args.reentry_km:
        ap.error(f"perigee {orbit.perigee_km:.1f} km is at or below the re-entry height {args.reentry_km:g} km")
    if orbit.apogee_km > 1400:
        ap.error(f"apogee {orbit.apogee_km:.1f} km is above the atmosphere model's table (1,400 km)")
    try:
        cos = 1.0
        if args.deorbit_json:
            cos = pointing_cos_from_deorbit_json(args.deorbit_json)
        elif args.pointing_error_deg:
            cos = math.cos(math.radians(args.pointing_error_deg))
        craft = Craft(args.mass_kg, args.sail_m2, args.body_m2, args.cd, args.body_surface_m2, cos,
                      args.tumble_sail_fraction, math.radians(args.passive_swing_deg)).check()
    except CraftError as e:
        ap.error(str(e))
    decays = {}
    for mode in dict.fromkeys(args.modes):
        with tqdm(total=100, desc=mode, unit="%", disable=args.quiet, file=sys.stderr,
                  bar_format="{l_bar}{bar}| {n:.0f}/{total} % of the height") as bar:
            def step(x, bar=bar):
                bar.update(100 * x - bar.n)
            decays[mode] = decay(orbit, craft.ballistic_m2kg(mode), sched, reentry_km=args.reentry_km,
                                 max_years=args.max_years, progress=step)
    life = {m: d.lifetime_years for m, d in decays.items()}
    print(f"orbit {orbit.perigee_km:.1f} x {orbit.apogee_km:.1f} km, {orbit.inclination_deg:.1f}°; "
          f"{craft.mass_kg:g} kg, C_D {craft.cd:g}; {sched.name}; re-entry at perigee {args.reentry_km:g} km")
    for m in decays:
        print(f"{m}: {_years(life[m], args.max_years)} (area {craft.area_m2(m):.3f} m²)")
    gain = None
    if life.get("tumbling") and life.get("stabilised"):
        gain = 1.0 - life["stabilised"] / life["tumbling"]
        print(f"gain: {100 * gain:.1f} % less time in orbit stabilised than tumbling")
    if args.plot:
        plot(args.plot, decays, f"{orbit.perigee_km:.0f} x {orbit.apogee_km:.0f} km, {orbit.inclination_deg:.0f}°, "
                                f"{craft.mass_kg:g} kg; {sched.name}")
        print(f"wrote {args.plot}")
    if args.json:
        out = {
            "orbit": {"perigee_km": orbit.perigee_km, "apogee_km": orbit.apogee_km, "a_m": orbit.a_m, "e": orbit.e,
                      "inclination_deg": orbit.inclination_deg},
            "craft": {"mass_kg": craft.mass_kg, "sail_m2": craft.sail_m2, "body_m2": craft.body_m2, "cd": craft.cd,
                      "body_surface_m2": craft.body_surface_m2, "pointing_cos": craft.pointing_cos,
                      "tumble_sail_fraction": craft.tumble_sail_fraction,
                      "passive_swing_rad": craft.passive_swing_rad},
            "activity": sched.name, "reentry_km": args.reentry_km, "max_years": args.max_years,
            "lifetime_years": life, "gain": gain,
            "modes": {m: {"area_m2": craft.area_m2(m), "ballistic_m2kg": craft.ballistic_m2kg(m),
                          "lifetime_years": d.lifetime_years, "steps": d.steps, "history": _thin(d)}
                      for m, d in decays.items()},
        }
        write_atomic(args.json, json.dumps(out, indent=1) + "\n")
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    from fsw.startup import exit_with

    exit_with(main)
