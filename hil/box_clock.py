"""The box's clock against true time: an offset and a rate error (drift).

    t_box = offset_s + (1 + drift_ppm · 1e-6) · t_true

``t_true`` is the simulator's time (seconds from the start of the simulated world); ``t_box`` is what
the flight software's injected clock reads (SITL's loop time). A quartz clock drifts by 10-50 ppm; an
offset is whatever the box was last set to. Scenario table ``[clock]``: ``offset_s``, ``drift_ppm``
(both optional, default 0: the box's clock is true time).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

#: the largest rate error accepted (a clock off by more than 0.1 % is broken, not drifting)
MAX_DRIFT_PPM = 1000.0


@dataclass(frozen=True)
class BoxClock:
    offset_s: float = 0.0
    drift_ppm: float = 0.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.offset_s) and math.isfinite(self.drift_ppm)):
            raise ValueError("clock offset and drift must be finite")
        if abs(self.drift_ppm) > MAX_DRIFT_PPM:
            raise ValueError(f"clock drift must be within ±{MAX_DRIFT_PPM:g} ppm")

    @property
    def rate(self) -> float:
        return 1.0 + self.drift_ppm * 1e-6

    @property
    def is_true(self) -> bool:
        return self.offset_s == 0.0 and self.drift_ppm == 0.0

    @property
    def start_s(self) -> float:
        """What the box's clock reads when the simulated world starts (true time 0), or 0 for a clock behind
        true time (the box's time stamps are unsigned: it starts when its clock reads 0, the world then
        already `true_s(0)` in); `hil.sitl.box_t0_s` of a simulator."""
        return max(0.0, self.box_s(0.0))

    def box_s(self, true_s: float) -> float:
        """What the box's clock reads at true time `true_s`."""
        return self.offset_s + self.rate * true_s if not self.is_true else true_s

    def true_s(self, box_s: float) -> float:
        """The true time at which the box's clock reads `box_s`."""
        return (box_s - self.offset_s) / self.rate if not self.is_true else box_s
