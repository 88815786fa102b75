"""The fixed-step loop around `FlightSoftware.tick`, and what a run prints: the status line each second
and the summary at the end. Shared by the target (`fsw.main`), SITL (`hil.sitl`) and the replay of a
recording (`ground.replay`).

Time: a *lockstep* run (SITL, replay) sets the loop time to k·period itself and is paced at `speed`
(0: as fast as possible); the target reads the monotonic clock. Either way the flight software only
sees the time it is given. SIGINT and SIGTERM stop the loop at the next tick; the summary follows.
"""
from __future__ import annotations

import gc
import signal
import sys
import threading
import time
from dataclasses import dataclass, field
from typing import Callable, TextIO

import numpy as np

from .flight import FlightSoftware

RADIO_BYTES_PER_S = 57600 / 10  # 8N1


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
        for lo, hi in zip(edges[:-1], edges[1:], strict=True):
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
class LoopResult:
    """How a run went: loop time reached, wall time, work per tick, ticks that started late."""

    t_s: float = 0.0
    wall_s: float = 0.0
    work: WorkHistogram = field(default_factory=WorkHistogram)
    #: paced against the wall clock (speed > 0, or on target)
    real_time: bool = False
    #: real-time runs: ticks that started more than one period behind their wall-clock time
    late_ticks: int = 0
    max_late_s: float = 0.0
    #: stopped by SIGINT / SIGTERM
    interrupted: bool = False
    #: the status lines' reader went away during the run (the loop went on without them)
    status_lost: bool = False


def run_loop(fsw: FlightSoftware, *, duration_s: float | None = None, speed: float = 1.0, lockstep: bool = True,
             t0_s: float = 0.0, before_tick: Callable[[float], None] | None = None,
             after_tick: Callable[[float], None] | None = None, status: Callable[[float], str] | None = None,
             done: Callable[[], bool] | None = None, out: TextIO = sys.stdout) -> LoopResult:
    """Run `fsw` at its scheduler's rate until `duration_s` of loop time, `done()`, SIGINT or SIGTERM.

    `before_tick(t)`: e.g. the simulator advancing to t; `after_tick(t)`: scoring, collecting estimates;
    `status(t)`: the line printed once a second (None: none)."""
    res = LoopResult(real_time=speed > 0 or not lockstep)
    stop = []

    def on_signal(signum, frame):
        stop.append(signum)

    in_main_thread = threading.current_thread() is threading.main_thread()
    if in_main_thread:
        old = signal.signal(signal.SIGINT, on_signal), signal.signal(signal.SIGTERM, on_signal)
    # Everything built so far lives as long as the run: collected once and moved out of the collector's
    # reach, so that its full collections in the loop scan only what the loop itself allocated (without
    # this a full collection of the imported libraries' objects takes about 0.1 s, a hundred 1 kHz ticks).
    gc.collect()
    gc.freeze()
    period = fsw.scheduler.period_s
    pace = speed if lockstep else 1.0
    wall0 = time.monotonic()
    k = 0
    next_status = 1.0
    t = t0_s
    try:
        while not stop:
            if duration_s is not None and k * period > duration_s + 1e-9:
                break
            if done is not None and done():
                break
            t = t0_s + k * period if lockstep else time.monotonic() - wall0
            if before_tick is not None:
                before_tick(t)
            res.work.add(fsw.tick(t))
            if after_tick is not None:
                after_tick(t)
            if status is not None and t - t0_s >= next_status - 1e-9:
                next_status += 1.0
                try:
                    print(status(t), file=out, flush=True)
                except (BrokenPipeError, ValueError):  # the reader has gone (`| head`, a closed journal)
                    status = None                       # the loop flies on; the lines stop
                    res.status_lost = True
            k += 1
            if pace > 0:
                wait = wall0 + (k * period) / pace - time.monotonic()
                if wait > 0:
                    time.sleep(wait)
                elif -wait > period:  # the next tick starts more than a period late
                    res.late_ticks += 1
                    res.max_late_s = max(res.max_late_s, -wait)
    finally:
        if in_main_thread:
            signal.signal(signal.SIGINT, old[0])
            signal.signal(signal.SIGTERM, old[1])
    res.t_s = t
    res.wall_s = time.monotonic() - wall0
    res.interrupted = bool(stop)
    return res


def status_line(t_s: float, fsw: FlightSoftware) -> str:
    """Time, |B|, the flown filter (which one) and its estimate with its 1-σ (body axes, °/s)."""
    d = fsw.estimators["kalman"]
    line = f"t={t_s:7.1f} s  |B|={np.linalg.norm(fsw.sample_b_T) * 1e6:6.2f} uT"
    if hasattr(d, "name"):  # the flown filter (fsw.estimation.flown_filter): which one publishes
        line += f"  {d.name}"
    if d.flags & d.NO_ESTIMATE:
        return line + "  (waiting for samples)"
    w, sg = np.degrees(d.omega_radps), np.degrees(d.sigma_radps)
    return line + f"  w_est=[{w[0]:7.2f} {w[1]:7.2f} {w[2]:7.2f}] +-[{sg[0]:5.2f} {sg[1]:5.2f} {sg[2]:5.2f}] dps"


def sample_line(fsw: FlightSoftware) -> str:
    """The samples' way through the loop: taken by the pipeline, the queue, the rate in force and its changes."""
    q = fsw.queue
    line = (f"samples: {fsw.samples} received, {q.popped} processed, {q.depth} waiting (queue at most {q.max_depth}"
            f" of {q.capacity}, {q.deferred} deferrals, {q.dropped} refused: queue full); sample rate "
            f"{fsw.sample_rate_hz:g} Hz")
    for t, was, to in fsw.rate_changes:
        line += f"; lowered {was:g} -> {to:g} Hz at t={t:.1f} s (the loop's work per sample did not fit)"
    return line


def summary(fsw: FlightSoftware, res: LoopResult, extra: list[str] = ()) -> str:
    """The end-of-run report; `extra` lines (SITL's errors against truth) follow the magnetometer's."""
    tlm = fsw.tlm
    st = fsw.scheduler.stats
    work = res.work
    drv = fsw.driver
    lines = [f"--- summary: {res.t_s:.1f} s of loop time in {res.wall_s:.1f} s wall "
             f"({res.t_s / max(res.wall_s, 1e-9):.1f}x real time)",
             f"magnetometer: {fsw.samples} samples, {drv.bus_errors if drv else 0} bus errors, "
             f"{drv.timeouts if drv else 0} timeouts", sample_line(fsw), *extra]
    lines.append(f"loop: {st.ticks} ticks at {fsw.scheduler.rate_hz:g} Hz; step time mean {work.mean_us():.0f} us, "
                 f"p50 {work.percentile_us(50):.0f} us, p99 {work.percentile_us(99):.0f} us, "
                 f"max {work.max_s * 1e6:.0f} us; overruns {st.overruns}, task overruns {st.task_overruns}")
    lines.append("step time histogram: " + ", ".join(f"{label} {n}" for label, n in work.buckets()))
    if res.real_time:
        lines.append(f"schedule: {res.late_ticks} ticks started more than one period late"
                     + (f" (at most {res.max_late_s * 1e3:.1f} ms)" if res.late_ticks else ""))
    rate = tlm.bytes_sent / max(res.t_s, 1e-9)
    lines.append(f"link: {tlm.frames_sent} frames, {tlm.bytes_sent} bytes ({rate:.0f} B/s = "
                 f"{100 * rate / RADIO_BYTES_PER_S:.1f} % of a 57600-baud radio), send errors {tlm.send_errors}"
                 + (f", {tlm.encode_errors} frames not encoded ({tlm.last_error})" if tlm.encode_errors else "")
                 + (f", {tlm.conn.unaddressed_writes} frames not sent (no ground station known yet)"
                    if getattr(tlm.conn, "unaddressed_writes", 0) else ""))
    sf = tlm.store
    if sf is not None and (sf.outages or sf.dropped):
        lines.append(f"store and forward: {sf.outages} outages, {sf.stored} frames kept, {sf.replayed} replayed, "
                     f"{sf.dropped} dropped (buffer full), {sf.buffered} still waiting")
    rs = fsw.resender
    if rs.requests or rs.refused:
        lines.append(f"samples asked for again: {rs.requests} requests ({rs.refused} refused), {rs.resent} sent "
                     f"again, {rs.unavailable} no longer held, {rs.queued} waiting")
    to = fsw.apps.get("timeorbit")
    to_line = to.summary_line(res.t_s) if to is not None else None
    if to_line:
        lines.append(to_line)
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
    kit = fsw.apps.get("deorbit")
    if kit is not None:
        e, seq = kit.energy(), kit.sequencer
        lines.append(f"de-orbit kit: {seq.mode.name}, openings {e.channels[0].openings} + {e.channels[1].openings}, "
                     f"turns {e.channels[0].turns} + {e.channels[1].turns}, energy {e.total_J:.0f} J, "
                     f"interlock violations {seq.interlock_violations}, safe entries {seq.safe_entries}")
    g = fsw.gate
    if g.rejected:
        lines.append("magnetometer samples refused: " + ", ".join(f"{n} {k}" for k, n in g.counts.items() if n))
    return "\n".join(lines)


def run_program(body: Callable[[], str]) -> int:
    """A run's command line around `body` (parse, build, run; returns the summary): the summary printed
    and exit status 0; a bad configuration (ValueError) one line and 2, a device or link that cannot be
    opened (OSError) one line and 1, Ctrl-C outside the loop one line and 130."""
    try:
        try:
            text = body()
        except ValueError as e:
            print(f"error: {e}", file=sys.stderr)
            return 2
        except BrokenPipeError:  # stdout's reader has gone: `fsw.startup.exit_with` ends quietly
            raise
        except OSError as e:
            print(f"error: {e}", file=sys.stderr)
            return 1
        print(text, flush=True)
    except KeyboardInterrupt:  # before the loop's own handler is in place, or after it is gone
        print("interrupted", file=sys.stderr, flush=True)
        return 130
    return 0
