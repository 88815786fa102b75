"""A recording as the flight software's magnetometer: `python -m ground.replay INPUT.csv --rates-out OUT.csv`
(or `python -m fsw.main --replay ...`, which hands over to it).

The flight software is composed as on target (`fsw.system.build_flight`: sample gate, estimators,
telemetry on `--link`) with :class:`RecordingReplay` in place of the driver, on a virtual clock, as fast
as possible. The loop clock starts at the recording's first sample time; a sample is delivered at the
first tick at or after its time, one per tick, so a loop at least as fast as the recording delivers
every sample at its own time and a slower one falls behind (counted in `max_lag_s`), never skipping a
sample. `--rates-out` writes the flown Kalman filter's estimates, one row per sample replayed.
The de-orbit kit's field the box recorded is taken out first and the samples flagged KIT_MOVING are
not replayed (`ground.kit_field`; the first line says how many; `--kit-raw` replays them as recorded).
"""
from __future__ import annotations

if __name__ == "__main__":
    from fsw.startup import interrupt_quietly

    interrupt_quietly()

import sys  # noqa: E402
from dataclasses import replace  # noqa: E402
from typing import TextIO  # noqa: E402

import numpy as np  # noqa: E402

from fsw.argtypes import ArgumentParser, check_paths_or_exit  # noqa: E402
from fsw.config import RunConfig, add_run_options, check_key_or_exit, run_config  # noqa: E402
from fsw.estimation import field_check  # noqa: E402
from fsw.estimation.rate_formulas import unobserved_sigma  # noqa: E402
from fsw.runner import run_loop, run_program, status_line, summary  # noqa: E402
from fsw.system import build_flight  # noqa: E402

from . import kit_field  # noqa: E402
from .recording import RateEstimates, read_recording, write_rate_estimates  # noqa: E402


def _stderr(text: str) -> None:
    print(text, file=sys.stderr)


class RecordingReplay:
    """Replays (t_s, b_T) samples: `update(now_s)` latches the next due sample into `b_body_T` and
    `sample_time_s` (the recording's own time) and returns True."""

    def __init__(self, t_s: np.ndarray, b_T: np.ndarray) -> None:
        self.t = np.asarray(t_s, float)
        self.b = np.asarray(b_T, float)
        if self.b.shape != (len(self.t), 3) or len(self.t) == 0:
            raise ValueError(f"expected t_s (N,) and b_T (N, 3) with N > 0, got {self.t.shape} and {self.b.shape}")
        if np.any(np.diff(self.t) <= 0):
            raise ValueError("sample times must be strictly increasing")
        self.b_body_T = np.zeros(3)
        self.sample_time_s = float("nan")
        self.index = 0  # next sample to deliver
        self.max_lag_s = 0.0
        self.kit_line = ""  # what was done with the recording's kit field (`ground.kit_field.take_out`)

    @classmethod
    def from_csv(cls, path, warn=None, *, kit_raw: bool = False) -> "RecordingReplay":
        """From a recording-format-v1 file (the reference columns are not read), the kit's field taken
        out unless `kit_raw`. A field that cannot be µT is refused (`field_check.FieldMagnitudeError`, a
        ValueError naming the file); the check's warnings go to ``warn`` (default: stderr)."""
        rec, line = kit_field.take_out(read_recording(path), raw=kit_raw)
        if not len(rec):
            raise ValueError(f"{path}: no sample left once the samples flagged KIT_MOVING are skipped")
        for w in field_check.check_recording(rec.b_T, str(path), rec.t_s, rec.metadata):
            (warn or _stderr)(f"warning: {w}")
        source = cls(rec.t_s, rec.b_T)
        source.kit_line = line
        return source

    @property
    def done(self) -> bool:
        return self.index >= len(self.t)

    @property
    def start_s(self) -> float:
        return float(self.t[0])

    @property
    def sample_rate_hz(self) -> float:
        """The recording's median sample rate."""
        return 1.0 / float(np.median(np.diff(self.t))) if len(self.t) > 1 else 1.0

    def update(self, now_s: float) -> bool:
        i = self.index
        if i >= len(self.t) or self.t[i] > now_s + 1e-9:
            return False
        self.sample_time_s = float(self.t[i])
        self.b_body_T[:] = self.b[i]
        self.max_lag_s = max(self.max_lag_s, now_s - self.sample_time_s)
        self.index = i + 1
        return True


def replay(path: str, cfg: RunConfig, *, rates_out: str | None = None, out: TextIO = sys.stdout,
           kit_raw: bool = False):
    """Run the flight software on the recording at `path`; returns (flight software, loop result). The loop
    runs at twice the recording's rate at least (one sample a tick at most), on the virtual clock."""
    source = RecordingReplay.from_csv(path, kit_raw=kit_raw)
    print(source.kit_line, file=out, flush=True)
    rate = min(1000.0, max(cfg.rate_hz, 2.0 * source.sample_rate_hz))
    cfg = replace(cfg, rate_hz=rate, speed=0.0)
    flight = build_flight(cfg, source, sigma_b_T=cfg.sigma_T, sample_rate_hz=source.sample_rate_hz)
    fsw = flight.fsw
    print(f"replay {path}: {len(source.t)} samples at {source.sample_rate_hz:.3g} Hz, loop {rate:g} Hz "
          f"(virtual clock), link {cfg.link}\n" + "\n".join(flight.notes), file=out, flush=True)
    rates = {}  # sample time -> (ω, σ) of the Kalman filter

    def keep() -> None:  # after each sample's pass (a tick may take more than one)
        kf = fsw.estimators["kalman"]
        if fsw.new_estimate["kalman"] and not kf.flags & kf.NO_ESTIMATE:
            rates[fsw.sample_t_s] = (kf.omega_radps.copy(), kf.sigma_radps.copy())

    fsw.sample_listeners.append(keep)
    try:
        res = run_loop(fsw, duration_s=cfg.duration_s, speed=0.0, lockstep=True, t0_s=source.start_s,
                       done=lambda: source.done and not fsw.new_sample and not fsw.queue.depth,
                       status=None if cfg.quiet else (lambda t: status_line(t, fsw)), out=out)
    finally:
        flight.close()
    if rates_out:
        write_replay_rates(rates_out, source, rates, path)
        print(f"wrote {len(rates)} Kalman estimates for {len(source.t)} samples: {rates_out}", file=out)
    return fsw, res


def write_replay_rates(path, source: RecordingReplay, rates: dict, recording: str) -> None:
    """The replay's Kalman estimates in the rate-estimate format: one row per recording sample (NaN
    where the sample gate refused the sample or the filter had no estimate yet; σ = inf where it had no
    information: the link's finite "unobserved" σ, or no field)."""
    n = len(source.t)
    w = np.full((n, 3), np.nan)
    s = np.full((n, 3), np.nan)
    for i, tk in enumerate(source.t):
        est = rates.get(float(tk))
        if est is not None:
            w[i], s[i] = est
    write_rate_estimates(path, RateEstimates(source.t, w, unobserved_sigma(s, source.b, 0.0), metadata={
        "source": f"python -m ground.replay {recording}",
        "method": "kalman (onboard RateKalman, DEBRIS_RATE_METHOD_KALMAN)"}))


def main(argv=None) -> int:
    ap = ArgumentParser(prog="python -m ground.replay", description=__doc__.splitlines()[0])
    ap.add_argument("input", metavar="INPUT.csv", help="a recording (format v1)")
    ap.add_argument("--rates-out", metavar="OUT.csv",
                    help="write the onboard Kalman filter's estimates, one row per sample")
    kit_field.add_arguments(ap)
    add_run_options(ap)

    def body() -> str:
        args = ap.parse_args(argv)
        check_paths_or_exit(ap, inputs={"INPUT.csv": args.input, "--key": args.key},
                            outputs={"--rates-out": args.rates_out, "--sample-store": args.sample_store})
        check_key_or_exit(ap, args.key)
        return summary(*replay(args.input, run_config(args), rates_out=args.rates_out, kit_raw=args.kit_raw))

    return run_program(body)


if __name__ == "__main__":
    from fsw.startup import exit_with

    exit_with(main)
