"""Allocation-light loop: over 10,000 ticks after warm-up, no growth in allocated blocks attributable to
the flight software (tracemalloc). A per-tick leak would show as ~10,000 blocks; counters that grow past
small-int caching and the scheduler's statistics account for a few dozen."""
import tracemalloc

import numpy as np
from scipy.spatial.transform import Rotation

from fsw.flight import FlightSoftware
from ground.replay import RecordingReplay
from fsw.telemetry.telemetry import Telemetry
from support import NullLink


def test_no_growth_in_allocated_blocks_over_10000_ticks():
    # a tumbling body's field sampled at the loop rate (the driver's own allocation is tested with the
    # driver; here every tick runs gate, three estimators and telemetry)
    t = np.arange(12_000) * 0.01
    b = Rotation.from_rotvec(-np.outer(t, np.radians([6.0, -5.0, 6.5]))).apply([20e-6, -15e-6, 35e-6])
    b += np.random.default_rng(0).normal(0, 0.05e-6, b.shape)
    fsw = FlightSoftware(RecordingReplay(t, b), Telemetry(NullLink()), rate_hz=100, sigma_b_T=0.05e-6,
                         sample_rate_hz=100)
    k = 0

    def run(n):
        nonlocal k
        for _ in range(n):
            fsw.tick(k * 0.01)
            k += 1

    run(2000)
    tracemalloc.start(5)
    try:
        before = tracemalloc.take_snapshot()
        run(10_000)
        after = tracemalloc.take_snapshot()
    finally:
        tracemalloc.stop()
    only_fsw = [tracemalloc.Filter(True, "*/fsw/*")]
    diff = after.filter_traces(only_fsw).compare_to(before.filter_traces(only_fsw), "filename")
    grown = sum(max(0, s.count_diff) for s in diff)
    assert fsw.samples > 9_000
    assert grown < 200, "\n".join(str(s) for s in diff[:10])
