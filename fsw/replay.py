"""A recording as the flight software's magnetometer: a FieldSource that replays samples on the loop clock.

`python -m fsw.main --replay INPUT.csv --rates-out OUT.csv` runs the same task table as SITL and the
target (sample gate, estimators, telemetry) with this source in place of the driver. The loop clock
starts at the recording's first sample time; a sample is delivered at the first tick at or after its
time, one per tick, so a loop at least as fast as the recording delivers every sample at its own time
and a slower one falls behind (counted in `max_lag_s`), never skipping a sample.
"""
from __future__ import annotations

import sys

import numpy as np

from .estimation import field_check


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

    @classmethod
    def from_csv(cls, path, warn=None) -> "RecordingReplay":
        """From a recording-format-v1 file (ground.recording; the reference columns are not read). A
        field that cannot be µT is refused (`field_check.FieldMagnitudeError`, a ValueError naming the
        file); the check's warnings go to ``warn`` (default: stderr)."""
        from ground.recording import read_recording
        rec = read_recording(path)
        for w in field_check.check_recording(rec.b_T, str(path), rec.t_s, rec.metadata):
            (warn or _stderr)(f"warning: {w}")
        return cls(rec.t_s, rec.b_T)

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
