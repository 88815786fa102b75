"""The magnetometer's samples between their acquisition and their processing: a bounded FIFO.

The sensor task reads every sample the chip has (a register read, cheap) and puts it here; the sample
pipeline (gate, calibration, estimators, applications, telemetry) takes the oldest one when the tick's
time budget has room for it, and again in later passes of the same tick while there is room
(`fsw.scheduler`). A sample that cannot be processed in its tick therefore waits instead of making the
tick overrun — which, at the chip's 1 kHz, would let the next sample be overwritten in the chip and lost.
When the queue is full the newest sample is refused and counted (`dropped`), never silently.

Preallocated arrays, no allocation per sample.
"""
from __future__ import annotations

import numpy as np

#: samples held at most: a quarter of a second at the chip's 1 kHz
DEFAULT_CAPACITY = 256


class SampleQueue:
    """Bounded FIFO of (time s, field T) with its counters: `pushed`, `popped`, `dropped` (refused: full),
    `max_depth` (the deepest it has been), `deferred` (times the pipeline left a sample for later)."""

    def __init__(self, capacity: int = DEFAULT_CAPACITY) -> None:
        if capacity < 1:
            raise ValueError(f"sample queue capacity must be >= 1, got {capacity!r}")
        self.capacity = int(capacity)
        self._t = np.zeros(self.capacity)
        self._b = np.zeros((self.capacity, 3))
        self._head = 0  # index of the oldest sample
        self.depth = 0
        self.pushed = 0
        self.popped = 0
        self.dropped = 0
        self.max_depth = 0
        self.deferred = 0

    def __len__(self) -> int:
        return self.depth

    def push(self, t_s: float, b_T: np.ndarray) -> bool:
        """Queue a sample (copied); False, and counted in `dropped`, when the queue is full."""
        if self.depth >= self.capacity:
            self.dropped += 1
            return False
        i = (self._head + self.depth) % self.capacity
        self._t[i] = t_s
        self._b[i] = b_T
        self.depth += 1
        self.pushed += 1
        if self.depth > self.max_depth:
            self.max_depth = self.depth
        return True

    def pop_into(self, b_out_T: np.ndarray) -> float:
        """The oldest sample: its field copied into `b_out_T`, its time returned. The queue must not be empty."""
        if not self.depth:
            raise IndexError("pop from an empty sample queue")
        i = self._head
        b_out_T[:] = self._b[i]
        self._head = (i + 1) % self.capacity
        self.depth -= 1
        self.popped += 1
        return float(self._t[i])
