"""The highest magnetometer sample rate the flight loop holds, at this machine's speed and with the CPU
halved.

    python -m bench.speed [--json FILE] [--duration S] [--rates HZ,HZ,...] [--loop-rate HZ]
                          [--slowdown X,X,...] [--shared-core]

For each CPU speed (``--slowdown``: 1 = this machine, 2 = a CPU half as fast, the flight computer's
class) and each sample rate (``--rates``, the MMC5983MA's continuous-mode rates by default), the SITL
composition (`hil.sitl.build`, scenario isoi, the whole flight software, the emulated chip in
continuous mode) runs ``--duration`` seconds with the rate held (`--fixed-sample-rate`: what is held is
measured, not chosen) and then once with the box choosing its rate from its budget
(`fsw.sample_rate`).

The loop runs as it does on target: a tick starts on its period's grid or, when the previous one ran
late, as soon as it ended; the chip goes on measuring meanwhile and a sample it outputs before the
previous one was read is lost in the chip (the emulator's ``overwritten``). The work of a tick is the
loop's own CPU time (`time.thread_time`) × the slowdown, measured by the scheduler itself: another
process on this shared machine does not count as the loop's work, and the halved CPU is exact and
repeatable (it scales the interpreter's work; a slower CPU's memory and cache are not modelled). The
simulator's work (the world, the chip's physics) is outside the tick, as on hardware, and SITL's truth
frame (DEBRIS_SIM_STATE, a lookup of the simulator's state) is not sent.

``--shared-core`` measures the halved CPU the other way, on the wall clock: this process pinned to CPU 0
with a busy process (``while True: pass``) on the same CPU, slowdown 1. It depends on what else runs on
that CPU, so state the machine's load with its figures (the JSON has the load average).

A rate is *held* when overruns (ticks whose work exceeded the period) stay under 0.1 % of the ticks,
no sample is lost in the chip and every sample received reaches the pipeline (processed or waiting, none
refused by a full queue). Reported per run: step time p50/p99 (µs), overruns, samples produced by the
chip (received + lost in it), received, processed, refused; per CPU speed the highest rate held and the
rate the box chose for itself from the fastest one. The JSON feeds `docs/tables.py` (table speed-rates).
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from datetime import datetime, timezone

import numpy as np

from fsw.argtypes import ArgumentParser
from fsw.drivers.mmc5983ma_regs import ContinuousFrequency
from hil import sitl

#: the chip's continuous-mode rates (1000 Hz with BW = 800 Hz)
DEFAULT_RATES = tuple(float(f.rate_hz) for f in sorted(ContinuousFrequency, reverse=True)
                      if f is not ContinuousFrequency.OFF and f.rate_hz >= 20)
HELD_OVERRUN_SHARE = 0.001


def run_one(rate_hz: float, *, slowdown: float, duration_s: float, loop_rate_hz: float, adapt: bool,
            wall: bool = False, seed: int = 0) -> dict:
    """One run at `rate_hz` on a CPU `slowdown` times slower (`wall`: the wall clock, slowdown 1)."""
    argv = ["--rate", f"{loop_rate_hz:g}", "--sample-rate", f"{rate_hz:g}", "--quiet", "--seed", str(seed),
            "--link", "udpout:127.0.0.1:9"]
    if not adapt:
        argv.append("--fixed-sample-rate")
    s = sitl.build(sitl.parse_args(argv), ident=True)
    fsw = s.fsw
    fsw.truth = None  # no DEBRIS_SIM_STATE: the simulator's truth frame is no work of the box's
    sched = fsw.scheduler
    if wall:
        timer = time.perf_counter
    elif slowdown == 1.0:
        timer = time.thread_time
    else:
        def timer():
            return slowdown * time.thread_time()
    sched.work_timer = timer
    try:
        works = s.run_as_on_target(duration_s)
    finally:
        s.flight.close()
    w = np.array(works) * 1e6
    q, chip = fsw.queue, s.sim.sensor
    st = sched.stats
    row = {"rate_hz": rate_hz, "slowdown": slowdown, "wall_clock": wall, "adaptive": adapt,
           "loop_rate_hz": loop_rate_hz, "duration_s": duration_s, "ticks": st.ticks,
           "p50_us": float(np.percentile(w, 50)), "p99_us": float(np.percentile(w, 99)), "max_us": float(w.max()),
           "overruns": st.overruns, "overrun_share": st.overruns / max(1, st.ticks),
           "produced": s.driver.samples + chip.overwritten, "received": fsw.samples, "processed": q.popped,
           "waiting": q.depth, "refused": q.dropped, "lost_in_chip": chip.overwritten,
           "sample_cost_us": st.sample_cost_s * 1e6, "final_rate_hz": fsw.sample_rate_hz,
           "rate_changes": [list(c) for c in fsw.rate_changes]}
    row["held"] = bool(row["overrun_share"] < HELD_OVERRUN_SHARE and row["lost_in_chip"] == 0 and row["refused"] == 0
                       and row["processed"] + row["waiting"] == row["received"])
    return row


def machine() -> dict:
    return {"date_utc": datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M"), "cpus": os.cpu_count(),
            "load_average_1_5_15": list(os.getloadavg()), "python": sys.version.split()[0]}


def sweep(rates, slowdowns, *, duration_s: float, loop_rate_hz: float, shared_core: bool, out=None) -> dict:
    out = out or sys.stdout
    runs, highest, chosen = [], {}, {}
    conditions = [(f"x{x:g}", x, False) for x in slowdowns] + ([("shared-core", 1.0, True)] if shared_core else [])
    for name, slowdown, wall in conditions:
        hog = None
        if wall:
            os.sched_setaffinity(0, {0})
            hog = subprocess.Popen(["taskset", "-c", "0", sys.executable, "-c", "while True: pass"])
        try:
            held = []
            for rate in rates:
                row = run_one(rate, slowdown=slowdown, duration_s=duration_s, loop_rate_hz=loop_rate_hz,
                              adapt=False, wall=wall)
                row["condition"] = name
                runs.append(row)
                if row["held"]:
                    held.append(rate)
                print(f"{name:12s} {rate:6g} Hz  p50 {row['p50_us']:6.0f} us  p99 {row['p99_us']:6.0f} us  "
                      f"overruns {row['overruns']:5d} ({100 * row['overrun_share']:.3f} %)  samples "
                      f"{row['produced']} produced, {row['received']} received, {row['processed']} processed, "
                      f"{row['refused']} refused, {row['lost_in_chip']} lost in the chip  "
                      f"{'held' if row['held'] else 'NOT held'}", file=out, flush=True)
            highest[name] = max(held) if held else None
            auto = run_one(max(rates), slowdown=slowdown, duration_s=duration_s, loop_rate_hz=loop_rate_hz,
                           adapt=True, wall=wall)
            auto["condition"] = name
            runs.append(auto)
            chosen[name] = auto["final_rate_hz"]
            print(f"{name:12s} highest rate held {highest[name]} Hz; the box, configured at {max(rates):g} Hz, "
                  f"flies {auto['final_rate_hz']:g} Hz (overruns {auto['overruns']}, {auto['lost_in_chip']} lost "
                  f"in the chip, {auto['refused']} refused)", file=out, flush=True)
        finally:
            if hog is not None:
                hog.kill()
                hog.wait()
                os.sched_setaffinity(0, set(range(os.cpu_count() or 1)))
    return {"runs": runs, "highest_held_hz": highest, "chosen_hz": chosen, "machine": machine(),
            "held_overrun_share": HELD_OVERRUN_SHARE}


def rate_list(text: str) -> list[float]:
    try:
        rates = [float(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a list of numbers: {text!r}") from None
    if not rates or any(not 0 < r <= 1000 for r in rates):
        raise argparse.ArgumentTypeError(f"rates must be in (0, 1000] Hz: {text!r}")
    return rates


def main(argv=None) -> int:
    ap = ArgumentParser(prog="python -m bench.speed", description=__doc__.splitlines()[0])
    ap.add_argument("--json", metavar="FILE", help="write the results here")
    ap.add_argument("--duration", type=float, default=10.0, metavar="S", help="seconds of loop time a run (default 10)")
    ap.add_argument("--rates", type=rate_list, default=list(DEFAULT_RATES), metavar="HZ,...",
                    help="sample rates to try (default: the chip's continuous-mode rates from 1000 down to 20 Hz)")
    ap.add_argument("--loop-rate", type=float, default=1000.0, metavar="HZ", help="loop rate (default 1000 Hz)")
    ap.add_argument("--slowdown", type=rate_list, default=[1.0, 2.0], metavar="X,...",
                    help="CPU slowdowns: the loop's CPU time times X (default 1,2: this machine, half its speed)")
    ap.add_argument("--shared-core", action="store_true",
                    help="also: pinned to CPU 0 beside a busy process there, on the wall clock")
    args = ap.parse_args(argv)
    if not 0 < args.duration <= 3600 or not 0 < args.loop_rate <= 1000:
        ap.error("--duration must be in (0, 3600] s and --loop-rate in (0, 1000] Hz")
    result = sweep(sorted(args.rates, reverse=True), args.slowdown, duration_s=args.duration,
                   loop_rate_hz=args.loop_rate, shared_core=args.shared_core)
    result["command"] = "python -m bench.speed " + " ".join(sys.argv[1:] if argv is None else argv)
    if args.json:
        with open(args.json + ".tmp", "w") as f:
            json.dump(result, f, indent=1)
        os.replace(args.json + ".tmp", args.json)
    return 0


if __name__ == "__main__":
    sys.exit(main())
