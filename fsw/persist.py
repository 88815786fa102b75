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
the program's edge (`fsw.main`). Not yet kept: the host calibration and the identification's result.
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

    # --- the loop -----------------------------------------------------------------------------------
    def tick(self, now_s: float) -> None:
        """After each tick: apply a restored time, queue the files whose state changed."""
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
