"""What the box keeps across a restart in its state directory, beside the TLE (`tle.txt`, `fsw.timeorbit`)
and the numbered samples (`samples.store`, `fsw.telemetry.sample_store`), which keep their own files:

- ``signing.json``: the last accepted timestamp of every signed command stream (sysid, compid, link) and
  the signing clock's floor. Without it a restarted box would take a command replayed within the new
  stream window (`fsw.telemetry.signing.NEW_STREAM_WINDOW`, 60 s) as new, and after a reboot with a clock
  that went back (a board without a real-time clock) it would sign telemetry older than the ground has
  seen. Saved after every accepted command (within one tick) and every minute while the clock advances.
- ``time.json``: the UTC the box was given, as (UTC, monotonic clock, boot id). Restored at the first
  tick after a restart of the service on the same boot (the monotonic clock runs on; CLOCK_MONOTONIC
  restarts at a reboot, so after one the time is not restored and must be set again).

Files are written whole or not at all and a torn one is never loaded (`fsw.state_files`). Writes happen
on a thread of their own (the newest snapshot of each file wins), so an fsync on a slow SD card never
holds up the loop; `close()` writes what is pending. The monotonic clock and the boot id are injected by
the program's edge (`fsw.main`).

The onboard results (:meth:`BoxState.restore_apps`), each saved when it changes with the box's system id
(a file of another box is ignored) and restored through the application's own ``restore``:

- ``calibration.json``: the host calibration last published (`fsw.estimation.magcal.MagCal.snapshot`: θ,
  b, D, covariance, drift period, state) and the UTC at the loop's time 0 when the box had it. Applied from
  the first sample after the restart, flagged (DEBRIS_MAGCAL's `restored` 1) and judged by the new
  samples like any calibration: the first minute of samples it does not fit drops it (`restored` 2,
  counted in `MagCal.restored_dropped`). The loop's time starts again at 0, so the drift's phase is
  carried by the UTC: when it is known before the restart and restored after it (same boot), the drift's
  terms are rotated to the new time base (a start-up of a fraction of a second is a phase error of ~1e-4
  of a cycle); otherwise they are dropped and the hard iron is the constant published one, its σ
  grown by the drift's amplitude (the error is up to twice that, ~1 µT, until the first solution from new
  samples, after about `MagCal.min_samples`).
- ``kit_field.json``: the kit's magnets as the sensor sees them (`fsw.deorbit.kit_field`: F_a per channel
  and their covariance; a file of another kit design is refused).
- ``ident.json``: the last inertia estimate with its covariance and state, sent again in
  DEBRIS_INERTIA_ESTIMATE after the restart (an experiment the restart cut short is ABORTED).

The store-and-forward ring of unsent frames (`fsw.telemetry.store_forward`) is not kept. Its samples
are in the numbered sample store (`samples.store`, the ground asks for what it missed) and its latest
inertia estimate in ``ident.json``; what is lost are the rate estimates (and SITL's truth) queued during
an outage that a restart ends. Keeping them would mean rewriting up to `DEFAULT_CAPACITY` frames (~0.5 MB)
while the link is down — every few seconds on an SD card for data the ground can recompute from the
samples — and their times are the old run's loop time, which the new run starts again at 0.
"""
from __future__ import annotations

import math
import threading
from collections import deque
from pathlib import Path
from typing import Callable

from .state_files import load_state, save_state
from .telemetry.signing import Verdict

SIGNING, TIME = "signing", "time"
#: the onboard applications' results (`restore_apps`): the host calibration, the kit's field, the inertia
CALIBRATION, KIT_FIELD, IDENT = "calibration", "kit_field", "ident"
CLOCK_SAVE_PERIOD_S = 60.0


class BoxState:
    """The state directory `state_dir`: restore at start (:meth:`restore`), save from the loop (:meth:`tick`)."""

    def __init__(self, state_dir: str | Path, *, monotonic: Callable[[], float], boot_id: str | None) -> None:
        self.dir = Path(state_dir)
        self._mono = monotonic
        self.boot_id = boot_id
        self.notes: list[str] = []
        self.saves = 0
        self.save_errors = 0
        self.last_error = ""
        self.restored: dict[str, str] = {}
        self._verifier = None
        self.system_id: int | None = None
        self._apps: dict = {}
        self._app_seen: dict = {}
        self._timeorbit = None
        self._restore_utc: tuple[float, float] | None = None
        self._ok_seen = 0
        self._sets_seen = 0
        self._clock_saved_s = -math.inf
        self._pending: dict[str, dict] = {}
        self._lock = threading.Lock()
        self._wake = threading.Event()
        self._stop = False
        self._writer = threading.Thread(target=self._write_forever, name="state files", daemon=True)
        self._writer.start()

    def path(self, kind: str) -> Path:
        return self.dir / f"{kind}.json"

    # --- start-up -----------------------------------------------------------------------------------
    def restore(self, verifier, timeorbit) -> None:
        """Before the loop: the signing streams and clock into `verifier` (None: no key), the time for
        `timeorbit` (set at the first tick)."""
        self._verifier, self._timeorbit = verifier, timeorbit
        if verifier is not None:
            payload, why = load_state(self.path(SIGNING), SIGNING)
            if payload is not None:
                why = self._restore_signing(verifier, payload)
            self.notes.append(f"signing state: {why}")
            self._ok_seen = verifier.counts[Verdict.OK]
        if timeorbit is not None:
            payload, why = load_state(self.path(TIME), TIME)
            if payload is not None:
                why = self._restore_time(payload)
            self.notes.append(f"time: {why}")
            self._sets_seen = timeorbit.clock.sets

    def _restore_signing(self, verifier, payload: dict) -> str:
        try:
            clock_last = int(payload["clock_last"])
            streams = [tuple(int(x) for x in s) for s in payload["streams"]]
            if any(len(s) != 4 or min(s) < 0 for s in streams) or clock_last < 0:
                raise ValueError
        except (KeyError, TypeError, ValueError):
            return "saved fields not understood: ignored"
        verifier.clock.advance_to(clock_last)
        for sysid, compid, link_id, ts in streams:
            recent = verifier.streams.get((sysid, compid, link_id))
            if recent is None or recent[-1] < ts:
                verifier.streams[(sysid, compid, link_id)] = deque([ts], maxlen=max(verifier.window, 1))
        self.restored[SIGNING] = f"{len(streams)} streams"
        return f"{len(streams)} command streams restored (a replayed command stays refused)"

    def _restore_time(self, payload: dict) -> str:
        try:
            boot, mono_s, utc_s = str(payload["boot_id"]), float(payload["mono_s"]), float(payload["utc_s"])
        except (KeyError, TypeError, ValueError):
            return "saved fields not understood: ignored"
        if self.boot_id is None or boot != self.boot_id:
            return "saved before a reboot: not restored (set it again)"
        if not (math.isfinite(mono_s) and math.isfinite(utc_s)) or self._mono() < mono_s:
            return "saved clock readings not usable: ignored"
        self._restore_utc = (utc_s, mono_s)
        self.restored[TIME] = "same boot"
        return "restored from before the restart (same boot)"

    def restore_apps(self, system_id: int, *, calibration=None, kit_field=None, ident=None) -> None:
        """Before the loop, after :meth:`restore`: the results of the host calibration
        (`fsw.host_calibration.HostCalibration`), the kit's field model (`fsw.deorbit.kit_field`) and the
        identification (`fsw.ident.IdentExperiment`) that were saved by this box (`system_id`), each
        through its ``restore``; None: not on this box. Each is saved again whenever it changes."""
        self.system_id = int(system_id)
        self._apps = {k: a for k, a in ((CALIBRATION, calibration), (KIT_FIELD, kit_field), (IDENT, ident))
                      if a is not None}
        for kind, app in self._apps.items():
            payload, why = load_state(self.path(kind), kind)
            if payload is not None:
                why = self._restore_app(kind, app, payload)
            self.notes.append(f"{kind.replace('_', ' ')}: {why}")
            self._app_seen[kind] = self._app_version(kind, app)

    def _restore_app(self, kind: str, app, payload: dict) -> str:
        sid = payload.get("system_id")
        if sid != self.system_id:
            return f"saved by system id {sid!r}, not this box's {self.system_id}: ignored"
        snap = payload.get("snapshot")
        if snap is None:
            return "none kept"
        try:
            if kind == CALIBRATION:
                utc0 = payload.get("utc0_s")
                shift = None
                if self._restore_utc is not None and isinstance(utc0, (int, float)):
                    utc_s, mono_s = self._restore_utc  # the UTC at the new loop's 0 (the loop starts now)
                    shift = utc_s + (self._mono() - mono_s) - float(utc0)
                how = app.restore(snap, shift)
            else:
                app.restore(snap)
                how = "applied"
        except (KeyError, TypeError, ValueError, IndexError, AttributeError, ArithmeticError) as e:
            return f"saved fields not understood ({type(e).__name__}: {e}): ignored"
        self.restored[kind] = how
        return f"restored from before the restart ({how})"

    @staticmethod
    def _app_version(kind: str, app):
        if kind == IDENT:
            return (id(app.result), app.state)
        return app.version

    # --- the loop -----------------------------------------------------------------------------------
    def tick(self, now_s: float) -> None:
        """After each tick: apply a restored time, queue the files whose state changed."""
        for kind, app in self._apps.items():
            version = self._app_version(kind, app)
            if version != self._app_seen.get(kind):
                self._app_seen[kind] = version
                payload = {"system_id": self.system_id, "snapshot": app.snapshot()}
                if kind == CALIBRATION and self._timeorbit is not None and self._timeorbit.clock.known:
                    payload["utc0_s"] = self._timeorbit.utc_s(now_s) - now_s  # the UTC at loop time 0
                self._queue(kind, payload)
        to = self._timeorbit
        if self._restore_utc is not None and to is not None:
            utc_s, mono_s = self._restore_utc
            self._restore_utc = None
            to.set_time(now_s, utc_s + (self._mono() - mono_s))
        v = self._verifier
        if v is not None and (v.counts[Verdict.OK] != self._ok_seen
                              or now_s - self._clock_saved_s >= CLOCK_SAVE_PERIOD_S):
            self._ok_seen = v.counts[Verdict.OK]
            self._clock_saved_s = now_s
            self._queue(SIGNING, {"clock_last": int(v.clock.last),
                                  "streams": [[*k, int(r[-1])] for k, r in sorted(v.streams.items()) if r]})
        if to is not None and to.clock.sets != self._sets_seen and to.clock.known:
            self._sets_seen = to.clock.sets
            if self.boot_id is not None:
                self._queue(TIME, {"boot_id": self.boot_id, "mono_s": self._mono(), "utc_s": to.utc_s(now_s)})

    def summary_line(self) -> str:
        line = f"state in {self.dir}: {self.saves} files saved, {self.save_errors} save errors"
        return line + (f" (last: {self.last_error})" if self.save_errors else "")

    def close(self) -> None:
        """Write what is pending, stop the writer."""
        with self._lock:
            self._stop = True
        self._wake.set()
        self._writer.join(timeout=10.0)

    # --- the writer ---------------------------------------------------------------------------------
    def _queue(self, kind: str, payload: dict) -> None:
        with self._lock:
            self._pending[kind] = payload
        self._wake.set()

    def _write_forever(self) -> None:
        while True:
            self._wake.wait()
            with self._lock:
                self._wake.clear()
                pending, self._pending = self._pending, {}
                stop = self._stop
            for kind, payload in pending.items():
                try:
                    save_state(self.path(kind), kind, payload)
                    self.saves += 1
                except OSError as e:
                    self.save_errors += 1
                    self.last_error = f"{kind}: {e.strerror or e}"
            if stop:
                return
