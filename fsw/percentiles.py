"""Two percentiles of an array as np.percentile gives them, by a partial sort (the flight loop's
calibration spread and cycle-time statistics)."""
from __future__ import annotations

import numpy as np


def percentile_pair(x: np.ndarray, p_lo: float, p_hi: float) -> tuple[float, float]:
    """np.percentile(x, (p_lo, p_hi)) (linear interpolation), the same values, by a partial sort: a few µs
    instead of tens for the few hundred to few thousand values the loop ranks."""
    n = len(x)
    pos = [p / 100.0 * (n - 1) for p in (p_lo, p_hi)]
    ks = sorted({min(int(q) + d, n - 1) for q in pos for d in (0, 1)})
    part = np.partition(x, ks)
    out = []
    for q in pos:
        k = int(q)
        a, b = float(part[k]), float(part[min(k + 1, n - 1)])
        out.append(a + (b - a) * (q - k))
    return out[0], out[1]
