"""Where a sampled applied moment is unknown, and what a fit may assume and use around it.

A recording's moment columns (``m*_Nm``) hold NaN where the moment is not known — the ground writes
NaN for a sample whose truth frame (DEBRIS_SIM_STATE) was lost on the link. An unknown moment is not
zero: counting it as zero inside a pulse biases the tensor (the pulse's impulse shrinks by its holes)
while the fit's intervals stay as narrow as with the whole pulse (aist2d, 8 % of the frames lost: Ixx
160 ± 0.9 kg·m² against 175).

Fitting every lost sample's moment as a free constant is honest but throws away what fixes the
tensor's scale: a free impulse inside a pulse can cancel any part of the known one, and with 8 % of
the frames lost the Cramér–Rao half-width of Ixx grows from 1.0 to 115 kg·m². What is known about the
action is that it is piecewise constant with few switches (tug pulses, magnet flips), so:

- a run of unknown samples between two known samples with the *same* moment, shorter than the
  shortest stretch of constant moment seen among the known samples (:func:`shortest_hold_s`), holds
  that moment. The assumption, stated: no whole pulse shorter than every pulse seen hides in a gap
  (one that did would show as a jump the model cannot follow: χ²).
- such a short run between two *different* moments holds one switch, at an unknown time: its moment
  is fitted as a constant about the mean of the two, with the spread of a switch time uniform over
  the gap as its prior.
- every other run (long, or at an end) is an interval on which a constant moment of unknown size
  acts, fitted free. The samples after it see its impulse (a jump of the rate), which the fitted
  constant reproduces exactly; only the attitude inside the interval differs, by second order in its
  length. A long run is cut into pieces of at most :data:`RUN_MAX_SAMPLES` samples so that a switch
  inside one costs less than a tenth of the noise of a typical record (0.2 N·m on 175 kg·m² over
  5 s: 3.6 mrad, 0.15 µT of a 40 µT field).
- at the ends of the record nothing fixes such a moment (before the first sample the state is free
  anyway; after the last one nothing sees it): :func:`known_span` gives the samples to fit, which
  leave out the leading and trailing runs of unknown moment.

:func:`plan` applies all of it; `euler_fit.KnownAction.from_samples` builds the fit's action from it.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: Longest run of samples fitted with one constant unknown moment; longer runs are cut.
RUN_MAX_SAMPLES = 5


def unknown_rows(moment_Nm: np.ndarray) -> np.ndarray:
    """(N,) bool: rows whose moment is unknown (any NaN in the row)."""
    return np.any(np.isnan(np.asarray(moment_Nm, float)), axis=1)


def runs(mask: np.ndarray, max_len: int | None = None) -> list[tuple[int, int]]:
    """Maximal runs [i, j) of True in ``mask``, cut into pieces of at most ``max_len``."""
    m = np.concatenate([[False], np.asarray(mask, bool), [False]])
    edges = np.flatnonzero(m[1:] != m[:-1])
    out = []
    for i, j in zip(edges[::2], edges[1::2]):
        step = (j - i) if not max_len else int(max_len)
        out.extend((int(a), int(min(a + step, j))) for a in range(i, j, step))
    return out


def _interval(t: np.ndarray, i: int, j: int, hold: str) -> tuple[float, float]:
    """The time over which the held moment of rows [i, j) acts, clipped to the record [t₀, t_end]."""
    n = len(t)
    if hold == "centered":
        a = t[0] if i == 0 else 0.5 * (t[i - 1] + t[i])
        b = t[-1] if j == n else 0.5 * (t[j - 1] + t[j])
    else:
        a, b = t[i], (t[-1] if j == n else t[j])
    return float(a), float(b)


def samples_in(t_s: np.ndarray, intervals) -> int:
    """How many samples lie in the intervals (t0 ≤ t < t1, the last sample counted in an interval that
    ends at it)."""
    t = np.asarray(t_s, float)
    inside = np.zeros(len(t), bool)
    for a, b in intervals:
        inside |= (t >= a) & ((t < b) | (t == t[-1]) & (b >= t[-1]))
    return int(inside.sum())


def known_span(moment_Nm: np.ndarray) -> tuple[int, int]:
    """[i0, i1): the samples from the first to the last one with a known moment ((0, 0) when none)."""
    known = np.flatnonzero(~unknown_rows(moment_Nm))
    return (0, 0) if known.size == 0 else (int(known[0]), int(known[-1]) + 1)


def merged(given, intervals, sigma=()) -> tuple[tuple, tuple]:
    """The union of the ``given`` (t0, t1) intervals (free) and ``intervals`` (1-σ ``sigma`` each, free
    when not given) as sorted, non-overlapping intervals with their 1-σ: overlapping ones become one
    interval (one constant unknown moment on the union), free."""
    sig = dict(zip(((float(a), float(b)) for a, b in intervals), sigma))
    free = (math.inf,) * 3
    ivs = sorted([((float(a), float(b)), free) for a, b in given]
                 + [((float(a), float(b)), tuple(sig.get((float(a), float(b)), free))) for a, b in intervals])
    out: list[list] = []
    for (a, b), s in ivs:
        if out and a < out[-1][1]:
            out[-1][1], out[-1][2] = max(out[-1][1], b), free
        else:
            out.append([a, b, s])
    return tuple((a, b) for a, b, _ in out), tuple(s for _, _, s in out)


def shortest_hold_s(t_s: np.ndarray, moment_Nm: np.ndarray) -> float:
    """The shortest stretch of constant moment among the known samples [s], from its first to its last
    known sample (stretches cut by the record's ends only count when there is no other; 0 with fewer
    than two known samples)."""
    t = np.asarray(t_s, float)
    m = np.asarray(moment_Nm, float)
    known = ~unknown_rows(m)
    tk, mk = t[known], m[known]
    if len(tk) < 2:
        return 0.0
    change = np.flatnonzero(np.any(mk[1:] != mk[:-1], axis=1)) + 1
    first, last = np.r_[0, change], np.r_[change, len(tk)] - 1
    dur = tk[last] - tk[first]
    return float(dur[1:-1].min() if len(dur) > 2 else dur.min())


@dataclass(frozen=True)
class MomentPlan:
    """What a fit takes the sampled moment to be (:func:`plan`)."""

    moment_Nm: np.ndarray          # (N, 3) known rows; held gaps; a switch gap at its neighbours' mean; 0 else
    intervals: tuple               # (t0, t1) on which a constant moment of unknown size is fitted
    sigma_Nm: tuple                # per interval (3,) 1-σ of that moment about moment_Nm; inf: free
    unknown: int                   # rows with a NaN
    held: int                      # of them, held between equal known moments
    switch: int                    # fitted with the one-switch prior
    free: int                      # fitted free
    shortest_hold_s: float


def plan(t_s: np.ndarray, moment_Nm: np.ndarray, hold: str = "centered",
         max_len: int = RUN_MAX_SAMPLES) -> MomentPlan:
    """Each run of unknown rows, between known rows a (before) and b (after), shorter from a to b than
    :func:`shortest_hold_s` and so holding at most one switch:

    - m_a = m_b: held at m_a;
    - m_a ≠ m_b (the switch is inside, at a time uniform over the gap), at most ``max_len`` rows: the
      moment is m_a + f (m_b − m_a), f ∈ [0, 1]: fitted as an unknown constant about the mean
      (m_a + m_b)/2 with the uniform's 1-σ |m_b − m_a|/√12 per axis as its prior (a thousandth of
      |m_b − m_a| on an axis that does not change: no switch moves it);
    - any other run (longer, at an end, or long enough to hide a pulse): free unknown constants on
      pieces of at most ``max_len`` rows.
    """
    if hold not in ("centered", "forward"):
        raise ValueError(f"hold must be 'centered' or 'forward', got {hold!r}")
    t = np.asarray(t_s, float)
    m = np.array(moment_Nm, float)
    n = len(t)
    unk = unknown_rows(m)
    d = shortest_hold_s(t, m)
    out = np.where(unk[:, None], 0.0, m)
    intervals, sigma = [], []
    held = switch = free = 0
    for i, j in runs(unk):
        short = 0 < i and j < n and t[j] - t[i - 1] < d
        if short and np.array_equal(m[i - 1], m[j]):
            out[i:j] = m[i - 1]
            held += j - i
            continue
        if short and j - i <= max_len:
            dm = np.abs(m[j] - m[i - 1])
            out[i:j] = 0.5 * (m[i - 1] + m[j])
            pieces, s = [(i, j)], np.maximum(dm / math.sqrt(12.0), 1e-3 * float(np.linalg.norm(dm)))
            switch += j - i
        else:
            pieces, s = [(a, min(a + max_len, j)) for a in range(i, j, max_len)], np.full(3, math.inf)
            free += j - i
        for a, b in pieces:
            iv = _interval(t, a, b, hold)
            if iv[1] > iv[0]:
                intervals.append(iv)
                sigma.append(tuple(float(x) for x in s))
    return MomentPlan(out, tuple(intervals), tuple(sigma), int(unk.sum()), held, switch, free, d)
